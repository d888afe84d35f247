"""Noise floors and the global test on a log kept as shards, by passes.

:func:`symcal.analysis.floors.floor_outcome` with the fitted dataset kept as shards: the
propagated floors, the tests and the estimate's share are sums over rows
(:class:`~symcal.analysis.floors.SharePlan`, :class:`~symcal.analysis.floors.RowsPlan`), so
each shard's task sums its own rows and the lead joins the sums in the order of the
shards (the successive differences across each boundary included); the held-out datasets
in memory are tested as usual, with the estimate's share from the log.

One rule is not the same maths on shards: a row whose propagated variance is below
:data:`~symcal.analysis.row_noise.EXACT` of the largest so far counts as an exact reading, the
largest taken over the rows accumulated before it; that running scale starts again at each
shard, so a row within 1e-12 of the scale could count otherwise (rows declared exact have
a variance of 0 and count the same).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from symcal.analysis.floors import (
    Differences,
    DifferencesPlan,
    RowsPlan,
    RowSums,
    SharePlan,
    _dataset_tests,
    difference_variances,
    differences_plan,
    rows_plan,
    share_plan,
)
from symcal.analysis.row_noise import Fit, entries_of
from symcal.analysis.verdicts import DatasetTest, FloorTest
from symcal.data.dataset import Dataset
from symcal.problem.symbolic import Problem
from symcal.solvers.objective import Source
from symcal.solvers.weighed import map_pieces


@dataclass(frozen=True)
class ShareSums:
    """One piece's share sums ``(A, B, t)`` of a log kept as shards (picklable)."""

    plan: SharePlan
    theta: np.ndarray
    name: str

    def __call__(self, piece: Any) -> tuple[np.ndarray, np.ndarray, float]:
        return self.plan.sums(piece.dataset(self.name), self.theta)


@dataclass(frozen=True)
class _Rows:
    plan: RowsPlan

    def __call__(self, piece: Any) -> RowSums:
        return self.plan.reduce(piece.dataset(self.plan.dataset))


@dataclass(frozen=True)
class _Diffs:
    plan: DifferencesPlan
    name: str

    def __call__(self, piece: Any) -> Differences:
        return self.plan.reduce(piece.dataset(self.name))


def floor_tests_passes(problem: Problem, log: Source, sample: Dataset,
                       held: Mapping[str, Dataset], theta: np.ndarray, fit: Fit,
                       ordered: bool, theta0: np.ndarray | None = None
                       ) -> tuple[dict[tuple[str, str], FloorTest], tuple[DatasetTest, ...]]:
    """The floors and tests of the fitted dataset ``log`` (by passes; ``sample``: a few of
    its rows, for its name and columns; ``ordered``: whether its rows are in time order)
    and of the datasets ``held`` (in memory), as
    :func:`~symcal.analysis.floors.floor_outcome` gives them on all the data in memory."""
    share = None
    if fit.dataset == log.name and np.any(fit.free):
        plan = share_plan(problem, fit, _log_variances(problem, log, sample, theta, ordered))
        if plan is not None:
            parts = map_pieces(ShareSums(plan, np.array(theta, dtype=float), log.name), log,
                                "floor_share")
            share = plan.finish(np.sum([p[0] for p in parts], axis=0),
                                np.sum([p[1] for p in parts], axis=0))
    rows = rows_plan(problem, sample, theta, fit, share, theta0)
    parts = map_pieces(_Rows(rows), log, "floor_rows")
    total = parts[0]
    for p in parts[1:]:
        total = total.join(p)
    found, joint = rows.finish(total, ordered)
    out = {(log.name, k): v for k, v in found.items()}
    tests = [joint]
    for ds in held.values():
        entries = entries_of(problem, ds)
        assumed = difference_variances(problem, ds, theta, tuple(entries.names),
                                       entries.exprs, entries.declared)
        more, test = _dataset_tests(problem, ds, theta, fit, share, theta0, assumed)
        out.update({(ds.name, k): v for k, v in more.items()})
        tests.append(test)
    return out, tuple(tests)


def _log_variances(problem: Problem, log: Source, sample: Dataset, theta: np.ndarray,
                   ordered: bool) -> dict[str, float]:
    """The floors squared of the log's entries of undeclared noise, estimated by
    successive differences in passes over its shards (in their order, the boundaries
    included), as :func:`~symcal.analysis.floors.difference_variances` gives them in
    memory: what the estimate's share takes for those constraints."""
    entries = entries_of(problem, sample)
    if all(entries.declared) or not ordered or log.n < 3:
        return {}
    plan = differences_plan(problem, theta, tuple(entries.names), entries.exprs)
    parts = map_pieces(_Diffs(plan, log.name), log, "floor_differences")
    total = parts[0]
    for p in parts[1:]:
        total = total.join(p)
    found = total.variances(list(entries.declared))
    return {n: float(v) for n, v in zip(entries.names, found, strict=True) if not np.isnan(v)}
