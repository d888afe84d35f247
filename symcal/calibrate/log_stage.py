"""One stage of a problem on a log kept as shards: :func:`symcal.calibrate.solve.run_stage`
in passes.

The same steps as a stage in memory, each a pass over the log (a task per shard on the
executor of the solve) instead of arrays of N rows: the robust losses by IRLS with the
weights computed in the passes (:mod:`symcal.solvers.robust_passes`); the ``propagated``
weighting with each observation's ``C_i^-½`` computed in the passes from the noisy view
(:mod:`symcal.analysis.propagated`); the ``estimated`` weighting; the sandwich, its robust
meat and, on time-ordered rows, the serial correlation and its Newey-West standard errors
(:mod:`symcal.analysis.serial_passes`); the outliers, their medians found exactly by
passes (:mod:`symcal.analysis.outlier_passes`).  The gauges are found on a bounded sample
of the log.  Held in the lead: reductions of the size of the parameters, the selection's
bounded histograms, the listed outliers.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from symcal.analysis.outlier_passes import KeptWeights, find_outliers_passes
from symcal.analysis.outliers import Outliers
from symcal.analysis.propagated import (
    Covariances,
    PropagatedWeights,
    covariances,
    weight_stats,
)
from symcal.analysis.serial import SerialCorrelation
from symcal.analysis.serial_passes import serial_passes, time_column
from symcal.base.errors import SymcalError
from symcal.base.numeric import chunks
from symcal.base.options import SolveOptions
from symcal.base.units import DISPLAY_UNITS
from symcal.calibrate.result import StageResult
from symcal.calibrate.stage_run import Inner, run_stage_on
from symcal.data.dataset import Dataset
from symcal.problem.symbolic import Problem, Stage
from symcal.solvers.base import SolverOutput
from symcal.solvers.objective import Objective, Source
from symcal.solvers.robust import RowLosses
from symcal.solvers.robust_passes import RobustPasses, sandwich_meat_passes, solve_robust_passes
from symcal.solvers.weighed import (
    Aside,
    Flags,
    Residuals,
    Weighed,
    map_pieces,
    read_piece,
    residual_rows,
)

Progress = Callable[[str], None] | None


@dataclass(frozen=True)
class _Finite:
    """A piece's ``(rows, non-finite residual rows, first (row, constraint, value))``."""

    rows: Residuals
    columns: tuple[str, ...]

    def __call__(self, piece: Any) -> tuple[int, int, tuple[int, int, float] | None]:
        u = read_piece(piece, self.columns)
        bad_rows, first = 0, None
        for part in chunks(u.shape[1]):
            g = self.rows(u[:, part])
            bad = ~np.isfinite(g)
            if bad.any():
                bad_rows += int(bad.any(axis=1).sum())
                if first is None:
                    row, k = (int(i) for i in np.argwhere(bad)[0])
                    first = (row + part.start, k, float(g[row, k]))
        return u.shape[1], bad_rows, first


def _check_finite(objective: Objective, data: Source, theta: np.ndarray) -> None:
    """Refuse constraints that are inf or NaN at the start, naming where (one pass)."""
    parts = map_pieces(_Finite(residual_rows(objective, theta, data.n),
                               tuple(objective.problem.columns)), data, "check_finite")
    offset = 0
    for rows, _, first in parts:
        if first is not None:
            row, k, value = first
            total = sum(p[1] for p in parts)
            raise SymcalError(
                f"constraint '{objective.constraints[k]}' is {value} at the initial "
                f"parameters on observation {offset + row + 1} of '{data.name}' "
                f"({data.source}), and on {total} observation(s) in all; check its "
                "expression and the data there")
        offset += rows


def _outliers(plain: Objective, data: Source, columns: Any, theta: np.ndarray,
              robust: RobustPasses | None, losses: RowLosses | None,
              solve_again: Callable[[Objective], SolverOutput],
              weighted: Objective | None = None) -> Outliers | None:
    """The observations the stage's fit treats as outliers (as ``symcal.solve``'s), by
    passes; ``solve_again`` solves the stage's objective with per-row weights;
    ``weighted``, the fit's objective where it is weighted by the propagated covariances
    (a :class:`~symcal.solvers.weighed.Weighed`): the residuals standardized by each
    row's propagated standard deviation, the refit weighed as the fit."""
    problem = plain.problem
    quantities = [problem.constraint(n) for n in plain.constraints]
    weigher = getattr(weighted, "weigher", None)
    cov = None if weigher is None else covariances(problem, plain.constraints, theta)

    def refit(flags: Flags) -> np.ndarray | None:
        rows: Any = Aside(flags) if weigher is None else KeptWeights(weigher, flags)
        out = solve_again(Weighed.of(plain, rows))
        return out.theta if out.success else None

    weights = None if robust is None else replace(robust.weights, power=1.0)
    return find_outliers_passes(
        data.name, plain.constraints, tuple(q.unit for q in quantities),
        np.array([q.sigma / DISPLAY_UNITS[q.unit] for q in quantities]),
        residual_rows(plain, theta, data.n), data, tuple(problem.columns), weights,
        "squared" if losses is None else "; ".join(losses.texts),
        time_column(problem, columns), refit, cov)


def run_stage_passes(problem: Problem, stage: Stage, data: Source, sample: Dataset,
                     theta: np.ndarray, options: SolveOptions, progress: Progress,
                     ordered: bool) -> tuple[np.ndarray, StageResult]:
    """Solve one stage on ``data`` (a log kept as shards, or a dataset in memory) from
    ``theta`` and analyse its outcome, every step a pass
    (:func:`~symcal.calibrate.stage_run.run_stage_on`, see the module); ``sample``: a
    bounded sample of the log (gauges), ``ordered``: whether its rows are in time order.

    Returns
    -------
    (theta, StageResult)
        As :func:`symcal.calibrate.solve.run_stage`.
    """
    return run_stage_on(InPasses(data, sample, ordered), problem, stage, theta, options,
                        progress)


@dataclass(frozen=True)
class InPasses:
    """A stage's steps on a log kept as shards (a
    :class:`~symcal.calibrate.stage_run.StageData`), each a pass over ``data``;
    ``sample``, a bounded sample of it, for the gauges; ``ordered``, whether its rows are
    in time order."""

    data: Source
    sample: Dataset
    ordered: bool

    def check_finite(self, objective: Objective, theta: np.ndarray) -> None:
        """Refuse constraints that are inf or NaN at the start (one pass)."""
        _check_finite(objective, self.data, theta)

    def robust(self, objective: Objective, theta: np.ndarray, losses: RowLosses,
               inner: Inner, progress: Progress, label: str) -> RobustPasses:
        """IRLS rounds, the weights computed in the passes."""
        return solve_robust_passes(objective, self.data, theta, losses, inner, progress,
                                   label)

    def robust_meat(self, objective: Objective, theta: np.ndarray, robust: RobustPasses,
                    losses: RowLosses, rank: int) -> np.ndarray:
        """The robust sandwich's meat, ``ψ`` from the Gram matrix of a pass."""
        return sandwich_meat_passes(objective, self.data, theta, losses, rank)

    def propagation(self, objective: Objective) -> _Propagated:
        """Each observation's ``C_i^-½`` computed in the passes."""
        return _Propagated(objective, self.data)

    def serial(self, objective: Objective, out: SolverOutput
               ) -> tuple[SerialCorrelation | None, np.ndarray | None]:
        """On time-ordered rows, by passes (boundary rows joined)."""
        if not self.ordered:
            return None, None
        return serial_passes(objective, self.data, out)

    def outliers(self, objective: Objective, theta: np.ndarray, robust: RobustPasses | None,
                 losses: RowLosses | None, solve_again: Callable[[Objective], SolverOutput],
                 weighted: Objective | None = None) -> Outliers | None:
        """Exact medians and spreads by passes."""
        return _outliers(objective, self.data, self.sample.columns, theta, robust, losses,
                         solve_again, weighted)


#: The propagated covariances at a point and their mean variance per constraint.
_Weights = tuple[Covariances, np.ndarray]


@dataclass(frozen=True)
class _Propagated:
    """The propagated weights of ``objective`` on a log kept as shards (a
    :class:`~symcal.calibrate.stage_run.Propagation`): each observation's ``C_i^-½``
    computed in the passes from its covariances at a point."""

    objective: Objective
    data: Source

    def weights(self, theta: np.ndarray, before: _Weights | None
                ) -> tuple[_Weights, int, float]:
        """The covariances at ``theta`` and, by one pass, the observations where they are
        singular, their mean variance and the largest relative change from ``before``."""
        columns = tuple(self.objective.problem.columns)
        if before is None:
            cov = covariances(self.objective.problem, self.objective.constraints, theta)
            singular, variance, change = weight_stats(cov, self.data, columns)
        else:
            cov = before[0].at(theta)
            singular, variance, change = weight_stats(cov, self.data, columns,
                                                      before=before[0])
        return (cov, variance), singular, change

    def weighted(self, weights: _Weights) -> Objective:
        """The objective weighed in every pass by the rows' ``C_i^-½``."""
        return Weighed.of(self.objective, PropagatedWeights(weights[0]))

    def floor(self, theta: np.ndarray, weights: _Weights, there: bool) -> np.ndarray:
        """The noise floor at ``theta``: the mean variance of ``weights`` when taken
        there, else one more pass."""
        variance = weights[1]
        if not there:
            variance = weight_stats(weights[0].at(theta), self.data,
                                    tuple(self.objective.problem.columns))[1]
        return np.sqrt(variance)
