"""How well the model agrees with the measurements, per dataset, before and after."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import partial
from typing import Any

import casadi as ca
import numpy as np

from symcal.analysis.floors import Residuals
from symcal.analysis.verdicts import FloorTest
from symcal.base import jit
from symcal.base.numeric import Mapped, mapped, owned
from symcal.base.units import DISPLAY_UNITS
from symcal.data.dataset import Dataset
from symcal.problem.symbolic import Problem
from symcal.solvers.executor import default_executor


@dataclass(frozen=True)
class Spread:
    """RMS, mean and standard deviation of a residual series (internal units)."""

    rms: float
    mean: float
    std: float

    @classmethod
    def of(cls, values: np.ndarray) -> Spread:
        """Spread of ``values``."""
        return cls(float(np.sqrt(np.mean(values**2))), float(np.mean(values)),
                   float(np.std(values)))

    def size(self, remove_mean: bool) -> float:
        """The residual's size as a model's fit is judged by it: its RMS (a constraint's
        mean is an error of the model like its scatter: an offset moves the mean only),
        its standard deviation where ``remove_mean`` says the mean is an arbitrary zero."""
        return self.std if remove_mean else self.rms


@dataclass(frozen=True)
class SeriesStats:
    """A constraint residual or a reference comparison on one dataset, before and after.

    ``kind`` is ``"constraint"`` (model against itself: the redundancy) or ``"comparison"``
    (model against an independent reference sensor; ``remove_mean`` says that its mean is
    an arbitrary zero, e.g. the interferometer's, and carries no information).  ``noise``
    is its noise floor and the test against it (:class:`~symcal.analysis.verdicts.FloorTest`,
    found at solve time; None before).
    """

    name: str
    kind: str
    dataset: str
    unit: str
    n: int
    before: Spread
    after: Spread
    remove_mean: bool = False
    noise: FloorTest | None = None

    @property
    def floor(self) -> float | None:
        """The noise floor (internal units), None when unknown."""
        return None if self.noise is None else self.noise.floor

    @property
    def chi2_dof(self) -> float | None:
        """χ²/dof against the floor, None when unknown."""
        return None if self.noise is None else self.noise.chi2_dof

    def shown(self, which: str) -> Spread:
        """``before`` or ``after`` in the display unit."""
        spread = getattr(self, which)
        scale = DISPLAY_UNITS[self.unit]
        return Spread(spread.rms / scale, spread.mean / scale, spread.std / scale)

    def to_dict(self) -> dict:
        """Plain-data form, values in the display unit: ``floor`` (null when unknown) and
        ``chi2_dof`` (null when unknown) beside the spreads, the whole test in
        ``noise``."""
        scale = DISPLAY_UNITS[self.unit]
        floor = self.floor
        return {
            "name": self.name, "kind": self.kind, "dataset": self.dataset,
            "unit": self.unit or "(internal)", "n": self.n, "remove_mean": self.remove_mean,
            "before": self.shown("before").__dict__, "after": self.shown("after").__dict__,
            "floor": None if floor is None else floor / scale, "chi2_dof": self.chi2_dof,
            "noise": None if self.noise is None else self.noise.to_dict(scale),
        }

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> SeriesStats:
        """Inverse of :meth:`to_dict` (values back in internal units)."""
        unit = "" if doc["unit"] == "(internal)" else doc["unit"]
        scale = DISPLAY_UNITS[unit]

        def spread(d: Mapping[str, float]) -> Spread:
            return Spread(d["rms"] * scale, d["mean"] * scale, d["std"] * scale)

        noise = doc.get("noise")
        return cls(doc["name"], doc["kind"], doc["dataset"], unit, doc["n"],
                   spread(doc["before"]), spread(doc["after"]), doc["remove_mean"],
                   None if noise is None else FloorTest.from_dict(noise, scale))


@dataclass(frozen=True)
class _Series:
    """What :func:`series_statistics` examines on one dataset: the entries, the notes of
    the comparisons skipped there, and the mapped function of all the entries."""

    names: tuple[str, ...]
    kinds: tuple[str, ...]
    units: tuple[str, ...]
    means: tuple[bool, ...]
    notes: tuple[str, ...]
    fn: Mapped


def _series(problem: Problem, ds: Dataset) -> _Series:
    names, kinds, exprs, units, means = [], [], [], [], []
    notes: list[str] = []
    for c in problem.constraints:
        names.append(c.name)
        kinds.append("constraint")
        exprs.append(c.sx)
        units.append(c.unit)
        means.append(False)
    for comp in problem.comparisons:
        if comp.datasets is not None and ds.name not in comp.datasets:
            continue
        missing = [c for c in problem.columns_of(comp.reference) if c not in ds.columns]
        if missing:
            notes.append(f"comparison '{comp.name}' skipped on '{ds.name}': "
                         f"no column {', '.join(repr(m) for m in missing)}")
            continue
        names.append(comp.name)
        kinds.append("comparison")
        exprs.append(comp.estimate - comp.reference)
        units.append(comp.unit)
        means.append(comp.remove_mean)
    fn = mapped(problem.theta, problem.u, [ca.vertcat(*exprs)], "series")
    return _Series(tuple(names), tuple(kinds), tuple(units), tuple(means), tuple(notes), fn)


def series_statistics(
    problem: Problem, datasets: dict[str, Dataset], theta0: np.ndarray, theta: np.ndarray,
    residuals: Mapping[str, Residuals] | None = None,
) -> tuple[tuple[SeriesStats, ...], tuple[str, ...]]:
    """Statistics of every constraint and applicable comparison on every dataset (their
    function built once per problem, dataset name and columns; its compiled twin when it
    pays, the same bits).

    ``residuals``: what the noise floors' pass evaluated of a dataset at ``theta`` and
    ``theta0`` (:func:`~symcal.analysis.floors.floor_outcome`): the same expressions
    with the readings' errors at zero, the same bits, read instead of evaluated again.

    Returns
    -------
    (stats, notes)
        The statistics, and one note per comparison skipped on a dataset (why).
    """
    stats: list[SeriesStats] = []
    notes: list[str] = []
    for ds in datasets.values():
        key = ("series", ds.name, frozenset(ds.columns))
        series = owned(problem, key, partial(_series, problem, ds))
        notes.extend(series.notes)
        given = (residuals or {}).get(ds.name)
        if given is not None and given.names == series.names and given.before is not None:
            before, after = given.before, given.after
        else:
            fn = jit.select(series.fn, 2 * ds.n)
            u = ds.matrix(problem.columns)
            threads = default_executor(ds.n).map       # threads for a large dataset
            before = fn(theta0, u, map_pieces=threads)[0]
            after = fn(theta, u, map_pieces=threads)[0]
        for j, name in enumerate(series.names):
            stats.append(SeriesStats(name, series.kinds[j], ds.name, series.units[j], ds.n,
                                     Spread.of(before[:, j]), Spread.of(after[:, j]),
                                     series.means[j]))
    return tuple(stats), tuple(notes)

