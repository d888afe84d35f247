"""The frozen outcome of a calibration: its problem, estimate, data, identifiability, fit.

A :class:`Result` carries the :class:`~symcal.problem.symbolic.Problem` it solved, the estimate
and the datasets, so that diagnosis, comparison and code generation work from it without
solving again.  :meth:`Result.save` and :meth:`Result.load` are the one writer and reader
of ``result.json``.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from symcal.analysis.fit import SeriesStats, Spread
from symcal.analysis.gauges import GaugeAnalysis
from symcal.analysis.identifiability import Conditioning, Identifiability, Uncertainty
from symcal.analysis.implicit import ImplicitCheck
from symcal.analysis.outliers import Outliers
from symcal.analysis.serial import SerialCorrelation
from symcal.analysis.verdicts import (
    ALONE_LEVEL,
    PROPAGATED,
    DatasetTest,
    alone_above,
    at_floor,
    family_document,
)
from symcal.base.errors import SymcalError, excerpt
from symcal.base.files import atomic_write_text, check_set, json_text
from symcal.base.numeric import mapped
from symcal.data.dataset import Dataset
from symcal.language.yamlio import display_path
from symcal.problem.symbolic import Problem

#: Version of the ``result.json`` layout.
FORMAT = 1

#: How much larger a spread must be after calibration than before to count as a
#: regression (relative).  On clean simulated data, where the model is exact, a calibrated
#: sensor passes its reading noise through the slope of its error model, which raised an
#: already noise-limited spread by up to 11 % (the courier's fly-by angle, seeds 1-8, both
#: platen models); 20 % leaves that margin so noise does not flag.
REGRESSION_TOLERANCE = 0.2


@dataclass(frozen=True)
class ParameterResult:
    """One parameter after the solve: value, standard error, unit, fixed, bounds and its
    correlations with the other free parameters of the last stage (the lmfit-like view of
    :attr:`Result.params`).

    Attributes
    ----------
    value, initial
        The estimate and the start, in ``unit``.
    se
        Standard error in ``unit``; None when it has none (``se_reason`` says why).
    fixed
        Fixed by the problem (never estimated).
    lower, upper
        Bounds (infinite when none).
    correlations
        Other free parameter → correlation coefficient (finite values only).
    """

    name: str
    value: float
    initial: float
    unit: str
    fixed: bool
    se: float | None
    se_reason: str | None
    lower: float
    upper: float
    doc: str
    correlations: Mapping[str, float] = field(default_factory=dict)

    @property
    def at_bound(self) -> str | None:
        """``"lower"``/``"upper"`` when the value sits on (or beyond) a bound."""
        if self.value <= self.lower:
            return "lower"
        if self.value >= self.upper:
            return "upper"
        return None

    def to_dict(self) -> dict:
        """Plain-data form (infinite bounds as None)."""
        def bound(x: float) -> float | None:
            return None if math.isinf(x) else x

        return {"name": self.name, "value": self.value, "initial": self.initial,
                "unit": self.unit, "fixed": self.fixed, "se": self.se,
                "se_reason": self.se_reason, "lower": bound(self.lower),
                "upper": bound(self.upper), "at_bound": self.at_bound, "doc": self.doc,
                "correlations": dict(self.correlations)}

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> ParameterResult:
        """Inverse of :meth:`to_dict`."""
        lower = -math.inf if doc.get("lower") is None else doc["lower"]
        upper = math.inf if doc.get("upper") is None else doc["upper"]
        return cls(doc["name"], doc["value"], doc["initial"], doc["unit"], doc["fixed"],
                   doc["se"], doc["se_reason"], lower, upper, doc.get("doc", ""),
                   dict(doc.get("correlations", {})))


@dataclass(frozen=True)
class Regression:
    """A residual or reference comparison that calibration made worse on one dataset.

    ``measure`` is ``"std"`` for a comparison whose mean is an arbitrary zero
    (``remove_mean``) and ``"rms"`` otherwise (an offset is an error too); ``before`` and
    ``after`` are that measure with the initial parameters and with the estimate, in the
    display unit ``unit`` (``""``: internal units).
    """

    dataset: str
    name: str
    kind: str
    measure: str
    before: float
    after: float
    unit: str

    @property
    def ratio(self) -> float:
        """``after / before`` (inf when ``before`` is 0)."""
        return self.after / self.before if self.before > 0 else math.inf

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (the unit string as in ``statistics``)."""
        return {"dataset": self.dataset, "name": self.name, "kind": self.kind,
                "measure": self.measure, "before": self.before, "after": self.after,
                "ratio": None if math.isinf(self.ratio) else self.ratio,
                "unit": self.unit or "(internal)"}


def regressions(statistics: tuple[SeriesStats, ...],
                tolerance: float = REGRESSION_TOLERANCE) -> tuple[Regression, ...]:
    """The residuals and comparisons whose spread calibration made worse.

    Where a residual's noise floor is known (propagated from declared noise), by test: it
    is above its floor and its χ²/dof grew from the initial parameters by more than noise
    moves a χ²/dof at the floor (:attr:`~symcal.analysis.verdicts.FloorTest.worse`).
    Elsewhere a spread counts as worse when it grew by more than ``tolerance``
    (relative).  The spread shown is the standard deviation for a comparison whose mean
    carries no information (``remove_mean``), the RMS otherwise.

    Parameters
    ----------
    statistics
        Before/after statistics (:attr:`Result.statistics`).
    tolerance
        Relative growth allowed before a spread counts as worse (default
        :data:`REGRESSION_TOLERANCE`).

    Returns
    -------
    tuple of Regression
        In the order of ``statistics``.
    """
    out = []
    for s in statistics:
        measure = "std" if s.remove_mean else "rms"
        before = getattr(s.shown("before"), measure)
        after = getattr(s.shown("after"), measure)
        test = s.noise if s.noise is not None and s.noise.chi2_before is not None else None
        worse = test.worse if test is not None else after > (1.0 + tolerance) * before
        if worse and after > 0:
            out.append(Regression(s.dataset, s.name, s.kind, measure, before, after, s.unit))
    return tuple(out)


@dataclass(frozen=True)
class Statistic:
    """A residual or reference comparison on one dataset, before and after calibration,
    in the unit ``unit`` names (``""``: symcal's internal units); what
    :meth:`Result.stat` returns.

    ``kind`` is ``"constraint"`` or ``"comparison"``; ``remove_mean`` says that a
    comparison's mean is an arbitrary zero; ``floor`` is the noise floor (in ``unit``,
    None when unknown) and ``chi2_dof`` the residual's χ²/dof against it.
    """

    name: str
    kind: str
    dataset: str
    unit: str
    n: int
    before: Spread
    after: Spread
    remove_mean: bool = False
    floor: float | None = None
    chi2_dof: float | None = None

    def shown(self, which: str) -> Spread:
        """``before`` or ``after`` (already in :attr:`unit`)."""
        spread: Spread = getattr(self, which)
        return spread


def _conversion(declared: str, wanted: str | None, name: str) -> tuple[str, float]:
    """The unit a value of a quantity declared in ``declared`` is given in, and that
    unit's size in internal units (divide an internal value by it)."""
    from symcal.base.units import internal_unit, size

    if wanted is None:
        return declared, size(declared)
    if wanted in ("", "(internal)"):
        return internal_unit(declared), 1.0
    if not declared:
        raise ValueError(f"'{name}' declares no unit, so its values are in internal units; "
                         f"ask for '(internal)' or declare its unit")
    if internal_unit(wanted) != internal_unit(declared):
        raise ValueError(f"'{wanted}' is not a unit of '{name}', which is in '{declared}'")
    return wanted, size(wanted)


def _scaled(spread: Spread, factor: float) -> Spread:
    if factor == 1.0:
        return spread
    return Spread(spread.rms / factor, spread.mean / factor, spread.std / factor)


@dataclass(frozen=True)
class DatasetInfo:
    """Which data a result was computed on: ``file`` (absolute) and its ``sha256`` when
    the data came from a file, None when simulated or given as an object."""

    name: str
    source: str
    n: int
    dropped: int
    file: str | None = None
    sha256: str | None = None


@dataclass(frozen=True)
class ConstraintCost:
    """One constraint's share of a stage's cost before and after the stage.

    ``cost_*`` is Σ (g/σ)²; ``rms_*`` is the RMS of g in the constraint's display unit.
    """

    name: str
    unit: str
    cost_before: float
    cost_after: float
    rms_before: float
    rms_after: float


@dataclass(frozen=True, eq=False)
class StageResult:
    """The outcome of one stage of a calibration; ``outliers`` are the observations its
    fit treats as outliers (None where its residuals were not finite); ``serial`` is the
    serial correlation of its residuals on time-ordered rows (None: rows not in time
    order), and when detected the standard errors allow for it."""

    name: str
    doc: str
    method: str
    success: bool
    status: str
    message: str
    iterations: int
    seconds: float
    free: tuple[str, ...]
    costs: tuple[ConstraintCost, ...]
    unmoved: tuple[str, ...]
    at_bound: tuple[str, ...]
    conditioning_before: Conditioning
    conditioning_after: Conditioning
    identifiability: Identifiability
    uncertainty: Uncertainty
    notes: tuple[str, ...] = ()
    outliers: Outliers | None = None
    gauges: GaugeAnalysis | None = None  # the stage's gauges, found before its solve
    serial: SerialCorrelation | None = None

    @property
    def cost_before(self) -> float:
        """Total cost Σ (g/σ)² at the stage's start."""
        return sum(c.cost_before for c in self.costs)

    @property
    def cost_after(self) -> float:
        """Total cost Σ (g/σ)² at the stage's end."""
        return sum(c.cost_after for c in self.costs)

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form."""
        return {
            "name": self.name, "doc": self.doc, "method": self.method,
            "success": self.success, "status": self.status, "message": self.message,
            "iterations": self.iterations, "seconds": self.seconds, "free": list(self.free),
            "costs": [c.__dict__ for c in self.costs],
            "cost_before": self.cost_before, "cost_after": self.cost_after,
            "unmoved": list(self.unmoved), "at_bound": list(self.at_bound),
            "hessian_conditioning": {"before": self.conditioning_before.to_dict(),
                                     "after": self.conditioning_after.to_dict()},
            "identifiability": self.identifiability.to_dict(),
            "uncertainty": self.uncertainty.to_dict(),
            "notes": list(self.notes),
            "outliers": None if self.outliers is None else self.outliers.to_dict(),
            "gauges": None if self.gauges is None else self.gauges.to_dict(),
            "serial_correlation": None if self.serial is None else self.serial.to_dict(),
        }

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> StageResult:
        """Inverse of :meth:`to_dict`."""
        cond = doc["hessian_conditioning"]
        return cls(doc["name"], doc["doc"], doc["method"], doc["success"], doc["status"],
                   doc["message"], doc["iterations"], doc["seconds"], tuple(doc["free"]),
                   tuple(ConstraintCost(**c) for c in doc["costs"]), tuple(doc["unmoved"]),
                   tuple(doc["at_bound"]), Conditioning.from_dict(cond["before"]),
                   Conditioning.from_dict(cond["after"]),
                   Identifiability.from_dict(doc["identifiability"]),
                   Uncertainty.from_dict(doc["uncertainty"]), tuple(doc["notes"]),
                   None if doc.get("outliers") is None
                   else Outliers.from_dict(doc["outliers"]),
                   None if doc.get("gauges") is None
                   else GaugeAnalysis.from_dict(doc["gauges"]),
                   None if doc.get("serial_correlation") is None
                   else SerialCorrelation.from_dict(doc["serial_correlation"]))


def file_hashes(problem: Problem) -> dict[str, str]:
    """sha256 of every file the problem was built from (the problem file, the files it
    extends, its models), by path relative to the problem file's folder (so that a moved
    project keeps its results)."""
    home = Path(problem.path).resolve().parent
    out = {}
    for path in problem.source_files():
        key = Path(os.path.relpath(Path(path).resolve(), home)).as_posix()
        try:
            out[key] = hashlib.sha256(Path(path).read_bytes()).hexdigest()
        except OSError as exc:
            raise SymcalError(f"cannot read {display_path(Path(path))} to hash it: "
                              f"{exc.strerror}") from None
    return out


@dataclass(frozen=True, eq=False)
class Result:
    """A calibration result.

    Use ``.params`` for the parameters by name (``result.params["s1.k1"].value``, ``.se``,
    ``.unit``, ``.correlations``), :func:`symcal.text_report` for the table a person
    reads and ``.to_dict()`` for the machine-readable document
    (``symcal solve --json``).  ``identifiability`` and ``uncertainty`` are those of the
    last stage; each stage's own are in ``stages``.  ``success`` is False when a stage
    failed (the estimate is then the failed stage's last iterate and later stages did not
    run) or when an implicit definition's fixed-point map does not contract on the data
    (``implicit``).

    Attributes
    ----------
    problem
        The problem solved.
    theta0, theta
        The parameter vector at the start and the estimate, in ``problem.theta`` order.
    params
        Every parameter by name (:class:`ParameterResult`), in ``problem.theta`` order.
    data
        The datasets by name (loaded again from their files for a loaded result).
    provenance
        What each dataset was: source, size, file and hash.
    floor_tests
        The global test of the model on every dataset: its constraints' χ²/dof against
        the floor their readings' declared noise sets (:mod:`symcal.analysis.floors`);
        each residual's own floor and test is in its ``statistics`` entry.
    files
        sha256 of every file the problem was built from, taken at solve time (None:
        hashed when the document is written).
    """

    problem: Problem
    theta0: np.ndarray
    theta: np.ndarray
    stages: tuple[StageResult, ...]
    params: Mapping[str, ParameterResult]
    identifiability: Identifiability
    uncertainty: Uncertainty
    statistics: tuple[SeriesStats, ...]
    provenance: tuple[DatasetInfo, ...]
    notes: tuple[str, ...]
    implicit: tuple[ImplicitCheck, ...] = ()
    floor_tests: tuple[DatasetTest, ...] = ()
    files: Mapping[str, str] | None = None
    _data: Mapping[str, Dataset] | None = field(default=None, repr=False)

    @property
    def name(self) -> str:
        """The problem's name."""
        return self.problem.name

    @property
    def problem_path(self) -> str:
        """The problem file as shown in messages."""
        return display_path(Path(self.problem.path))

    @property
    def success(self) -> bool:
        """Whether every stage succeeded and every implicit definition converged."""
        return all(st.success for st in self.stages) and all(c.contracts for c in self.implicit)

    @property
    def failure(self) -> str | None:
        """Why the solve failed, in one sentence (the first stage that failed, or the
        first implicit definition that does not converge); None when it succeeded."""
        for st in self.stages:
            if not st.success:
                return f"stage '{st.name}' ({st.method}): {st.message}"
        for c in self.implicit:
            if not c.contracts:
                return (f"implicit definition '{c.name}' does not converge on "
                        f"'{c.dataset}' (max |dF/dx| {c.contraction:.3g}, not a contraction)")
        return None

    @property
    def method(self) -> str:
        """The methods of the stages, e.g. ``"linear"`` or ``"linear+linear+ipopt"``."""
        return "+".join(st.method for st in self.stages)

    @property
    def data(self) -> Mapping[str, Dataset]:
        """The datasets by name; for a loaded result, read again from their sources (and
        refused when a file changed since the solve)."""
        if self._data is None:
            object.__setattr__(self, "_data", MappingProxyType(self._reload()))
        assert self._data is not None
        return self._data

    def _reload(self) -> dict[str, Dataset]:
        from symcal.data.loading import load_datasets

        files = {d.name: d.file for d in self.provenance if d.file is not None}
        self.check_data()
        for info in self.provenance:
            spec = self.problem.datasets.get(info.name)
            if info.file is None and (spec is None or spec.source != info.source):
                raise SymcalError(f"dataset '{info.name}' ({info.source}) was given as data in "
                                  "memory, not as a file: it cannot be read again; solve again "
                                  "with it")
        data = load_datasets(self.problem, files, drop_invalid=any(d.dropped
                                                                   for d in self.provenance),
                             names=[d.name for d in self.provenance])
        for info in self.provenance:
            if data[info.name].n != info.n:
                raise SymcalError(f"dataset '{info.name}' ({info.source}) has "
                                  f"{data[info.name].n} observations now, {info.n} when the "
                                  "result was computed; solve again")
        return data

    def check_data(self) -> None:
        """Refuse the result when a data file it was computed on changed or vanished since.

        Raises
        ------
        SymcalError
            Naming the dataset and its file.  Datasets given as objects or simulated have
            no file to check.
        """
        for info in self.provenance:
            if info.file is None or info.sha256 is None:
                continue
            path = Path(str(info.file))
            if info.sha256.startswith("shards:"):     # a partitioned log: its manifest
                from symcal.data.shards import open_shards

                try:
                    now = open_shards(info.name, path, ()).manifest()
                except (SymcalError, OSError) as exc:
                    raise SymcalError(f"dataset '{info.name}' ({display_path(path)}) cannot "
                                      f"be opened now ({exc}); solve again") from None
                if now != info.sha256:
                    raise SymcalError(f"dataset '{info.name}' ({display_path(path)}) changed "
                                      "since the result was computed; solve again")
                continue
            try:
                digest = hashlib.sha256(path.read_bytes()).hexdigest()
            except OSError as exc:
                raise SymcalError(f"dataset '{info.name}' ({display_path(path)}) cannot be "
                                  f"read now ({exc.strerror}); solve again") from None
            if digest != info.sha256:
                raise SymcalError(f"dataset '{info.name}' ({display_path(path)}) changed since "
                                  "the result was computed; solve again")

    @property
    def at_floor(self) -> bool | None:
        """Whether every dataset is at its noise floor (:attr:`floor_tests`), one decision
        at 95 % for the datasets together (each dataset's band at the Šidák level,
        :func:`~symcal.analysis.verdicts.at_floor`): False when one is above or below it, or
        when a constraint's own test is above its floor at 1 % over them all
        (:attr:`alone`); None when one's floor is unknown and none is off it."""
        return at_floor(self.floor_tests,
                        tuple(s.noise for s in self.alone if s.noise is not None))

    @property
    def alone(self) -> tuple[SeriesStats, ...]:
        """The fitted dataset's constraints whose own test against a propagated floor is
        known, in the order of :attr:`statistics` (what :attr:`at_floor` tests beside the
        datasets' joint tests).  Not a held-out dataset's: there a constraint's statistic
        carries the estimate's error, one draw shared by its rows, and spreads more than
        its χ² (the joint test allows for it, :func:`~symcal.analysis.floors.held_out_test`;
        a constraint's own band does not: the power bench's validation g_V stood 3.2 of
        its standard deviations high on a seed with nothing there)."""
        fit = self.problem.fit_dataset
        return tuple(s for s in self.statistics if s.kind == "constraint"
                     and s.dataset == fit
                     and s.noise is not None and s.noise.method == PROPAGATED
                     and s.noise.chi2 is not None and s.noise.dof)

    @property
    def above_alone(self) -> tuple[tuple[SeriesStats, float], ...]:
        """The constraints above their own floor at 1 % over them all, with the bound
        each passed (:func:`~symcal.analysis.verdicts.alone_above`)."""
        alone = self.alone
        bounds = alone_above(tuple(s.noise for s in alone if s.noise is not None))
        return tuple((s, b) for s, b in zip(alone, bounds, strict=True) if b is not None)

    @property
    def outliers(self) -> Outliers | None:
        """The observations the last stage's fit treats as outliers."""
        return self.stages[-1].outliers

    @property
    def regressions(self) -> tuple[Regression, ...]:
        """Residuals and reference comparisons that calibration made worse, on any
        dataset (more than :data:`REGRESSION_TOLERANCE` larger after than before; see
        :func:`regressions`)."""
        return regressions(self.statistics)

    @property
    def rows(self) -> int:
        """Residual rows of the last stage's fit (observations × constraints)."""
        return int(self.uncertainty.dof + self.identifiability.rank)

    @property
    def rss(self) -> float:
        """The calibration fit's residual sum of squares, as the information criteria take
        it: where the weights are propagated from the readings' declared noise, the fitted
        dataset's χ² at the estimate (each row's residual whitened by its propagated
        covariance, the weighting the fit minimises); otherwise the last stage's cost
        Σ (g/σ)².  Two revisions whose rows differ in noise are then compared by how
        well they fit each row against its own noise, not by their noisiest rows."""
        if self.problem.weighting == "propagated":
            fit = self.problem.fit_dataset
            chi2 = next((t.chi2 for t in self.floor_tests if t.dataset == fit
                         and t.method == PROPAGATED and t.chi2 is not None), None)
            if chi2 is not None:
                return float(chi2)
        return float(self.stages[-1].cost_after)

    @property
    def aic(self) -> float:
        """Akaike information criterion of the calibration fit (Gaussian residuals)."""
        return self.rows * float(np.log(self.rss / self.rows)) + 2 * self.identifiability.rank

    @property
    def bic(self) -> float:
        """Bayesian information criterion of the calibration fit."""
        return (self.rows * float(np.log(self.rss / self.rows))
                + self.identifiability.rank * float(np.log(self.rows)))

    def stat(self, name: str, dataset: str | None = None, unit: str | None = None
             ) -> Statistic:
        """The statistics of constraint or comparison ``name`` on ``dataset`` (default:
        the fitted one), in the unit its ``unit`` field names: the one the quantity is
        declared in, or ``unit`` (any unit of its dimension; ``"(internal)"``: symcal's
        internal units, mm, rad, s).

        Raises
        ------
        KeyError
            No such statistics.
        ValueError
            A ``unit`` of another dimension.
        """
        dataset = dataset or self.problem.fit_dataset
        for s in self.statistics:
            if s.name == name and s.dataset == dataset:
                shown, factor = _conversion(s.unit, unit, name)
                return Statistic(s.name, s.kind, s.dataset, shown, s.n,
                                 _scaled(s.before, factor), _scaled(s.after, factor),
                                 s.remove_mean,
                                 None if s.floor is None else s.floor / factor, s.chi2_dof)
        raise KeyError(f"no statistics for '{name}' on dataset '{dataset}'")

    def unit_of(self, name: str) -> str:
        """The unit a named constraint, expression, sensor signal or comparison is declared
        in (``""``: none, so :meth:`value` gives it in internal units).

        Raises
        ------
        KeyError
            An unknown quantity, naming the ones there are.
        """
        problem = self.problem
        for group in (problem.constraints, problem.expressions, problem.signals,
                      problem.comparisons):
            for q in group:
                if q.name == name:
                    return q.unit
        problem.quantity(name)      # raises with the names there are
        return ""

    def value(self, name: str, dataset: str | None = None, unit: str | None = None
              ) -> np.ndarray:
        """A named constraint, expression, sensor signal or comparison (estimate minus
        reference) evaluated at the estimate on every observation of ``dataset`` (default:
        the fitted one), in the unit it is declared in (:meth:`unit_of`; internal units
        when it declares none), or in ``unit`` (any unit of its dimension;
        ``"(internal)"``: symcal's internal units).

        Raises
        ------
        KeyError
            An unknown quantity or dataset, naming the ones there are.
        ValueError
            A ``unit`` of another dimension.
        """
        sx = self.problem.quantity(name)
        _, factor = _conversion(self.unit_of(name), unit, name)
        dataset = dataset or self.problem.fit_dataset
        if dataset not in self.data:
            raise KeyError(f"no dataset '{dataset}'; datasets: {', '.join(self.data)}")
        ds: Any = self.data[dataset]
        fn = mapped(self.problem.theta, self.problem.u, [sx], "value")
        if hasattr(ds, "shards"):          # a partitioned log: shard by shard, in order
            parts = [fn(self.theta, shard.dataset(ds.name).matrix(self.problem.columns))[0]
                     for shard in ds.shards]
            values = np.concatenate(parts)[:, 0]
        else:
            values = fn(self.theta, ds.matrix(self.problem.columns))[0][:, 0]
        return values if factor == 1.0 else values / factor

    def to_dict(self) -> dict[str, Any]:
        """The whole result as plain data (JSON-ready)."""
        return {
            "symcal_result": FORMAT,
            "problem": self.problem.name, "problem_path": self.problem_path,
            "problem_file": str(Path(self.problem.path).resolve()),
            "files": dict(self.files) if self.files is not None
            else file_hashes(self.problem),
            "solver": {"method": self.method, "success": self.success,
                       "seconds": sum(st.seconds for st in self.stages)},
            "stages": [st.to_dict() for st in self.stages],
            "datasets": [d.__dict__ for d in self.provenance],
            "parameters": [p.to_dict() for p in self.params.values()],
            "identifiability": self.identifiability.to_dict(),
            "uncertainty": self.uncertainty.to_dict(),
            "statistics": [s.to_dict() for s in self.statistics],
            "regressions": [r.to_dict() for r in self.regressions],
            "outliers": None if self.outliers is None else self.outliers.to_dict(),
            "implicit": [c.to_dict() for c in self.implicit],
            "floor_tests": [t.to_dict() for t in self.floor_tests],
            "at_floor": self.at_floor,
            "at_floor_test": {**family_document(self.floor_tests),
                              "alone": {"level": ALONE_LEVEL, "above": [
                                  {"dataset": s.dataset, "name": s.name, "chi2_dof":
                                   s.chi2_dof, "bound": b} for s, b in self.above_alone]}},
            "information_criteria": {"aic": self.aic, "bic": self.bic, "rows": self.rows,
                                     "rss": self.rss},
            "notes": list(self.notes),
        }

    def save(self, path: str | Path) -> Path:
        """Write ``result.json`` (the document of :meth:`to_dict`) atomically to ``path``.

        Over a file a symcal command wrote (``--out DIR``), the file is recorded again as
        symcal's own, a set of its own, so that readers do not take it for a mixed set."""
        from symcal.base.files import write_output, written_by_symcal

        if written_by_symcal(path):
            return write_output(path, json_text(self.to_dict()))
        return atomic_write_text(path, json_text(self.to_dict()))

    @classmethod
    def load(cls, path: str | Path | Mapping[str, Any], problem: Problem | None = None
             ) -> Result:
        """Read a ``result.json`` written by :meth:`save` (or its document, :meth:`to_dict`).

        Parameters
        ----------
        path
            The result file, or its document as a dict.
        problem
            The problem it is for (default: load the file it names).  Refused when its
            name differs, or when the problem or model files changed since the solve.

        Raises
        ------
        SymcalError
            A missing, unreadable or foreign file, another format version, another
            problem, changed problem or model files, or a document that is incomplete:
            without a record of its solve's success, without exactly one number for
            every parameter of the problem.
        """
        doc, label = read_result_document(path)
        return cls.from_document(doc, problem, label)

    @classmethod
    def from_document(cls, doc: Mapping[str, Any], problem: Problem | None = None,
                      label: str = "the result", *,
                      hashes: Mapping[str, str] | None = None) -> Result:
        """The result a document of :meth:`to_dict` describes (what :meth:`load` reads).

        Parameters
        ----------
        doc
            The document (``symcal solve --json``).
        problem
            The problem it is for (default: load the file it names); refused as in
            :meth:`load`.
        label
            How to name the document in messages.
        hashes
            :func:`file_hashes` of ``problem``, when the caller has just computed them (a
            fleet reads its units' documents against the hashes it sent them with);
            None: computed here.

        Raises
        ------
        SymcalError
            As :meth:`load`.
        """
        doc, label = read_result_document(doc) if label == "the result" else (doc, label)
        if problem is None:
            from symcal.problem.build import load_problem

            file = doc.get("problem_file")
            if not isinstance(file, str):
                raise SymcalError(f"{label} does not name its problem file; give the problem")
            problem = load_problem(file)
        check_result_problem(doc, label, problem, hashes)
        solver = doc.get("solver")
        if not isinstance(solver, Mapping) or not isinstance(solver.get("success"), bool):
            raise SymcalError(f"{label} does not record whether its solve succeeded (no "
                              "'solver': {'success': ...}); solve again")
        entries = _parameter_entries(doc, label, problem)
        theta = np.array([_number(entries[p.name], "value", label) for p in problem.parameters])
        theta0 = np.array([_number(entries[p.name], "initial", label)
                           for p in problem.parameters])
        try:
            result = cls(problem, theta0, theta,
                         tuple(StageResult.from_dict(s) for s in doc["stages"]),
                         parameter_table(ParameterResult.from_dict(p) for p in doc["parameters"]),
                         Identifiability.from_dict(doc["identifiability"]),
                         Uncertainty.from_dict(doc["uncertainty"]),
                         tuple(SeriesStats.from_dict(s) for s in doc["statistics"]),
                         tuple(DatasetInfo(**d) for d in doc["datasets"]),
                         tuple(doc["notes"]),
                         tuple(ImplicitCheck.from_dict(c) for c in doc.get("implicit", [])),
                         tuple(DatasetTest.from_dict(t) for t in doc.get("floor_tests", [])),
                         dict(doc["files"]) if isinstance(doc.get("files"), Mapping) else None)
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            what = f"no {exc.args[0]!r}" if isinstance(exc, KeyError) and exc.args \
                else excerpt(exc, 120)
            raise SymcalError(f"{label} is damaged or incomplete ({what}); write it again "
                              "with 'symcal solve PROBLEM --out DIR'") from None
        if result.success != solver["success"]:
            raise SymcalError(f"{label} says its solve {_verb(solver['success'])} but its "
                              f"stages say it {_verb(result.success)}; write it again with "
                              "'symcal solve PROBLEM --out DIR'")
        return result


def parameter_table(entries: Iterable[ParameterResult]) -> Mapping[str, ParameterResult]:
    """Parameters by name, in the given order (read-only)."""
    return MappingProxyType({p.name: p for p in entries})


def read_result_document(result: str | Path | Mapping[str, Any]) -> tuple[Mapping[str, Any],
                                                                          str]:
    """A result file's document (or the given dict) and how to name it in messages.

    Raises
    ------
    SymcalError
        A missing or unreadable file, invalid JSON, not a symcal result, another version.
    """
    if isinstance(result, Mapping):
        doc: Any = result
        label = "the result"
    else:
        label = f"result file {result}"
        check_set(result, label)
        try:
            text = Path(result).read_text(encoding="utf-8")
        except FileNotFoundError:
            raise SymcalError(f"{label} not found") from None
        except (OSError, UnicodeDecodeError) as exc:
            reason = getattr(exc, "strerror", None) or exc.__class__.__name__
            raise SymcalError(f"{label} cannot be read: {reason}") from None
        try:
            doc = json.loads(text)
        except RecursionError:
            raise SymcalError(f"{label} is nested too deeply to be a symcal result") from None
        except json.JSONDecodeError as exc:
            raise SymcalError(f"{label} is not valid JSON: {exc.msg} at line {exc.lineno}, "
                              f"column {exc.colno}") from None
        except ValueError as exc:  # an integer of more than 4300 digits
            raise SymcalError(f"{label} is not a symcal result: {exc}") from None
        _check_numbers(doc, label)
    if not isinstance(doc, Mapping) or "symcal_result" not in doc:
        raise SymcalError(f"{label} is not a symcal result (no 'symcal_result' key); "
                          "write one with 'symcal solve PROBLEM --out DIR'")
    if doc["symcal_result"] != FORMAT:
        raise SymcalError(f"{label} has format version {doc['symcal_result']!r}; this symcal "
                          f"reads version {FORMAT}")
    return doc, label


def _check_numbers(doc: Any, label: str, at: str = "") -> None:
    """Refuse a number symcal never writes: one beyond a double's range (400 digits), or
    inf and NaN (written as null)."""
    stack = [(doc, at)]
    while stack:
        item, where = stack.pop()
        if isinstance(item, Mapping):
            stack += [(v, f"{where}.{k}" if where else str(k)) for k, v in item.items()]
        elif isinstance(item, list):
            stack += [(v, f"{where}[{i}]") for i, v in enumerate(item)]
        elif isinstance(item, int) and not isinstance(item, bool) and abs(item) > 2 ** 1023:
            raise SymcalError(f"{label}: {where}: a number of {len(str(abs(item)))} digits, "
                              "beyond the range of a double (about 1.8e308)")
        elif isinstance(item, float) and not math.isfinite(item):
            raise SymcalError(f"{label}: {where}: {item} is not a finite number (symcal "
                              "writes null there)")


def check_result_problem(doc: Mapping[str, Any], label: str, problem: Problem,
                         hashes: Mapping[str, str] | None = None) -> None:
    """Refuse a result document for another problem, or from changed problem/model files
    (``hashes``: the problem's :func:`file_hashes`, when the caller has them)."""
    if doc.get("problem") != problem.name:
        raise SymcalError(f"{label} is for problem '{doc.get('problem')}', not "
                          f"'{problem.name}'")
    stored = doc.get("files")
    if isinstance(stored, Mapping):
        home = Path(problem.path).resolve().parent
        current = file_hashes(problem) if hashes is None else hashes
        for file, digest in current.items():
            if file in stored and stored[file] != digest:
                raise SymcalError(f"{label} was computed from another version of "
                                  f"{display_path(home / file)} (it changed since the "
                                  "solve); solve again")
        missing = [f for f in current if f not in stored]
        if missing:
            raise SymcalError(f"{label} was not computed with "
                              f"{display_path(home / missing[0])}; solve again")


def _parameter_entries(doc: Mapping[str, Any], label: str, problem: Problem
                       ) -> dict[str, Mapping[str, Any]]:
    """The entries of a result document's ``parameters`` by name: one for every parameter
    of ``problem`` and no other."""
    entries = doc.get("parameters")
    if not isinstance(entries, list):
        raise SymcalError(f"{label} has no 'parameters' list")
    given: dict[str, Mapping[str, Any]] = {}
    for entry in entries:
        if not isinstance(entry, Mapping) or "name" not in entry or "value" not in entry:
            raise SymcalError(f"{label}: every entry of 'parameters' needs a 'name' and a "
                              f"'value', found {excerpt(entry, 120)}")
        name = str(entry["name"])
        if name in given:
            raise SymcalError(f"{label} lists parameter '{name}' twice")
        given[name] = entry
    for p in problem.parameters:
        if p.name not in given:
            raise SymcalError(f"{label} has no value for parameter '{p.name}'")
    names = set(problem.parameter_names)
    for name in given:
        if name not in names:
            raise SymcalError(f"{label} has a value for parameter '{name}', which problem "
                              f"'{problem.name}' does not have")
    return given


def _number(entry: Mapping[str, Any], key: str, label: str) -> float:
    """A parameter entry's number (null, written for a non-finite number, is NaN)."""
    value = entry.get(key)
    if value is None:
        return math.nan
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SymcalError(f"{label}: parameter '{entry['name']}' has the {key} "
                          f"{excerpt(value, 60)}, not a number")
    return float(value)


def _verb(success: bool) -> str:
    return "succeeded" if success else "failed"
