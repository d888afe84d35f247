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
from typing import Any, cast

import numpy as np

from symcal.analysis.gauges import find_gauges
from symcal.analysis.identifiability import analyse, conditioning
from symcal.analysis.outlier_passes import find_outliers_passes
from symcal.analysis.outliers import Outliers
from symcal.analysis.propagated import PropagatedWeights, covariances, weight_stats
from symcal.analysis.serial import SerialCorrelation
from symcal.analysis.serial_passes import serial_passes, time_column
from symcal.base.errors import SymcalError
from symcal.base.linalg import numerical_rank, sqrt_psd
from symcal.base.numeric import chunks
from symcal.base.options import SolveOptions
from symcal.base.units import DISPLAY_UNITS, symbol
from symcal.calibrate.result import StageResult
from symcal.calibrate.solve import (
    REWEIGHT,
    _check_information,
    _constraint_costs,
    _diverged,
    _reweighted,
)
from symcal.data.dataset import Dataset
from symcal.problem.symbolic import Problem, Stage
from symcal.solvers.base import SolverOutput
from symcal.solvers.linear import solve_linear
from symcal.solvers.objective import Objective, Source
from symcal.solvers.robust import RowLosses, row_losses
from symcal.solvers.robust_passes import RobustPasses, sandwich_meat_passes, solve_robust_passes
from symcal.solvers.stage import ipopt, lm, out_of_bounds, solve_stage
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


def _robust(objective: Objective, data: Source, theta: np.ndarray, losses: RowLosses,
            method: str, progress: Progress, label: str, options: SolveOptions
            ) -> tuple[SolverOutput, list[str], RobustPasses]:
    """A stage with robust losses: reweighting rounds, each on the path the first round
    takes, warm-started (as ``symcal.solve``'s)."""
    notes: list[str] = []
    path: list[str] = []

    def inner(weighted: Objective, start: np.ndarray) -> SolverOutput:
        if not path:
            out, first = solve_stage(weighted, data, start, method, progress, label, options)
            notes.extend(first)
            path.append(out.method)
            return out
        if path[0] == "linear":
            out = solve_linear(weighted, data, start)
            if not out_of_bounds(objective, out.theta):
                return out
            path[0] = "ipopt"
        if path[0] == "lm":
            return lm(weighted, data, start, progress, label, options)
        return ipopt(weighted, data, start, progress, label, options)

    robust = solve_robust_passes(objective, data, theta, losses, inner, progress, label)
    return robust.output, notes, robust


def _singular(count: int, n: int) -> str:
    return (f"weighting: the propagated covariance of the constraints is singular on "
            f"{count} of {n} observations (the readings they use are declared exact "
            "there); kept equal weights")


def _propagated(plain: Objective, data: Source, theta: np.ndarray, method: str,
                progress: Progress, label: str, options: SolveOptions
                ) -> tuple[Objective, SolverOutput, list[str]]:
    """``weighting: propagated`` (as ``symcal.solve``'s): weighted at the start, then again
    at that estimate unless the weights there differ by at most :data:`REWEIGHT`; each
    observation's weights computed in the passes."""
    problem = plain.problem
    columns = tuple(problem.columns)
    missing = sorted({c for n in plain.constraints
                      for c in problem.undeclared(problem.constraint(n).sx)})
    if missing:
        raise SymcalError(f"weighting 'propagated' needs the noise of every reading the "
                          f"constraints read; no noise is declared for the column(s) "
                          f"{', '.join(repr(m) for m in missing)}: declare it ('noise: 0.5 um' "
                          "on the column, on the model input bound to it, or in the "
                          "problem's 'noise:' section), or choose another weighting")
    start = covariances(problem, plain.constraints, theta)
    singular, _, _ = weight_stats(start, data, columns)
    if singular:
        out, notes = solve_stage(plain, data, theta, method, progress, label, options)
        return plain, out, [*notes, _singular(singular, data.n)]
    weighted: Objective = Weighed.of(plain, PropagatedWeights(start))
    first, notes = solve_stage(weighted, data, theta, method, progress, label, options)
    if not first.success:
        return weighted, first, notes
    there = start.at(first.theta)
    singular, variance, change = weight_stats(there, data, columns, before=start)
    if singular:
        return weighted, first, [*notes, _singular(singular, data.n)]
    when = "at the start and again at that estimate"
    if change <= REWEIGHT:    # the weights have converged: solving again moves nothing
        second, when = first, (f"at the start (at that estimate they differ by "
                               f"{change:.1g} at most)")
    else:
        reweighted = Weighed.of(plain, PropagatedWeights(there))
        second, _ = solve_stage(reweighted, data, first.theta, method, progress, label,
                                options)
        if second.success:
            weighted = reweighted
        else:   # from a converged point: keep it, weighted as at the start
            notes.append(f"weighting: solving again with the weights at the estimate did "
                         f"not succeed ({second.message}); kept the estimate weighted at "
                         "the start")
            second, when = first, "at the start"
    merged = SolverOutput(
        second.theta, second.free, second.method, second.success, second.status,
        second.message + "; weighted by the covariance propagated from the readings' noise",
        second.r_factor, second.rows, second.rss,
        first.iterations + (second.iterations if second is not first else 0),
        first.seconds + (second.seconds if second is not first else 0.0))
    if second is not first:
        variance = weight_stats(start.at(second.theta), data, columns)[1]
    floor = np.sqrt(variance)
    sizes = []
    for k, name in enumerate(plain.constraints):
        q = problem.constraint(name)
        sizes.append(f"{name} {floor[k] * q.sigma / DISPLAY_UNITS[q.unit]:.3g} "
                     f"{symbol(q.unit)}")
    note = ("weighting: each observation's constraints whitened by their covariance "
            f"propagated from the readings' declared noise, {when} (noise floor "
            f"{', '.join(sizes)})")
    return weighted, merged, [*notes, note]


def _outliers(plain: Objective, data: Source, columns: Any, theta: np.ndarray,
              robust: RobustPasses | None, losses: RowLosses | None,
              solve_again: Callable[[Objective], SolverOutput]) -> Outliers | None:
    """The observations the stage's fit treats as outliers (as ``symcal.solve``'s), by
    passes; ``solve_again`` solves the stage's objective with per-row weights."""
    problem = plain.problem
    quantities = [problem.constraint(n) for n in plain.constraints]

    def refit(flags: Flags) -> np.ndarray | None:
        out = solve_again(Weighed.of(plain, Aside(flags)))
        return out.theta if out.success else None

    weights = None if robust is None else replace(robust.weights, power=1.0)
    return find_outliers_passes(
        data.name, plain.constraints, tuple(q.unit for q in quantities),
        np.array([q.sigma / DISPLAY_UNITS[q.unit] for q in quantities]),
        residual_rows(plain, theta, data.n), data, tuple(problem.columns), weights,
        "squared" if losses is None else "; ".join(losses.texts),
        time_column(problem, columns), refit)


def run_stage_passes(problem: Problem, stage: Stage, data: Source, sample: Dataset,
                     theta: np.ndarray, options: SolveOptions, progress: Progress,
                     ordered: bool) -> tuple[np.ndarray, StageResult]:
    """Solve one stage on ``data`` (a log kept as shards, or a dataset in memory) from
    ``theta`` and analyse its outcome, every step a pass (see the module); ``sample``: a
    bounded sample of the log (gauges), ``ordered``: whether its rows are in time order.

    Returns
    -------
    (theta, StageResult)
        As :func:`symcal.calibrate.solve.run_stage`.
    """
    free = np.array([p.name in stage.free for p in problem.parameters])
    plain = Objective(problem, stage.constraints, free)
    _check_finite(plain, data, theta)
    r_start, _, tail0, rows0 = plain.accumulate_r(data, theta)
    ident0, unc0 = analyse(r_start, rows0, tail0, plain.names, plain.scales,
                           theta[plain.index])
    _check_information(stage, cast(Dataset, data), rows0, ident0.rank,
                       sum(unc0.se[n] is None for n in plain.names), len(plain.names))
    gauges = find_gauges(plain, sample, theta)
    if progress is not None:
        for gauge in gauges.gauges:
            progress(f"  {stage.name}: before the solve, a gauge: {gauge.text}")
    method = options.method or stage.method
    losses = row_losses(plain)
    robust: RobustPasses | None = None
    objective = plain
    if losses is not None and problem.weighting in ("estimated", "propagated"):
        raise SymcalError(f"stage '{stage.name}': {losses.texts[0]} is a robust loss, which "
                          f"weighting '{problem.weighting}' does not support: remove one of "
                          "them")
    if losses is not None:
        out, notes, robust = _robust(plain, data, theta, losses, method, progress,
                                     stage.name, options)
    elif problem.weighting == "propagated":
        objective, out, notes = _propagated(plain, data, theta, method, progress, stage.name,
                                            options)
    else:
        out, notes = solve_stage(plain, data, theta, method, progress, stage.name, options)
    out = _diverged(out, problem, theta, plain)
    collapse = gauges.collapse(theta, out.theta, plain) if out.success else None
    if collapse is not None:
        out = replace(out, success=False, status="Collapsed", message=collapse)
    if problem.weighting == "estimated" and len(stage.constraints) > 1 and out.success:
        objective, out, note = _reweighted(plain, out, cast(Dataset, data), method, progress,
                                           stage.name, options)
        notes.append(note)
    names, scales, idx = objective.names, objective.scales, objective.index
    meat = None
    if robust is not None and losses is not None:
        meat = sandwich_meat_passes(plain, data, out.theta, losses,
                                    numerical_rank(out.r_factor, out.rows, scales))
    elif len(stage.constraints) > 1:
        rank = numerical_rank(out.r_factor, out.rows, scales)
        cov_g = objective.residual_covariance(data, out.theta, rank)
        meat = objective.accumulate_r(data, out.theta, sqrt_psd(cov_g).T)[0]
    serial: SerialCorrelation | None = None
    if robust is None and out.success and ordered:
        serial, hac = serial_passes(objective, data, out)
        if hac is not None:
            meat = hac
    exact_null, held = gauges.confirmed(plain, sample, out.theta)
    if len(held.gauges) < len(gauges.gauges):
        gone = [g.text.split(":")[0] + " of " + ", ".join(g.parameters)
                for g in gauges.gauges if g not in held.gauges]
        notes.append(f"the {'; '.join(gone)} found before the solve does not hold at the "
                     "estimate: a degeneracy of the region the start lies in, not a gauge")
        gauges = held
    ident, unc = analyse(out.r_factor, out.rows, out.rss, names, scales, out.theta[idx],
                         meat, exact_null)
    if out.success and ident.rank == 0:
        out = replace(out, success=False, status="Collapsed",
                      message="failed: the iterates left the region the data describe: where "
                              "they ended, the data determine none of the free parameters")
    moved = np.abs(out.theta[idx] - theta[idx]) > 1e-12 * scales
    at_bound = [p.name for p in (problem.parameters[i] for i in idx)
                if min(abs(out.theta[problem.index[p.name]] - b) for b in (p.lower, p.upper))
                <= 1e-7 * p.scale]
    final = out

    def solve_again(weighted: Objective) -> SolverOutput:
        return solve_stage(weighted, data, final.theta, method, None, stage.name, options)[0]

    outliers = _outliers(plain, data, sample.columns, out.theta, robust, losses, solve_again)
    result = StageResult(
        stage.name, stage.doc, out.method, out.success, out.status, out.message,
        out.iterations, out.seconds, names, _constraint_costs(plain, data, theta, out.theta),
        tuple(n for n, m in zip(names, moved, strict=True) if not m), tuple(at_bound),
        conditioning(r_start, out.rows, names, scales),
        conditioning(out.r_factor, out.rows, names, scales, gauges=exact_null), ident, unc,
        tuple(notes), outliers, gauges, serial)
    return out.theta, result

