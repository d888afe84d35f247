"""One stage of a calibration, solved and analysed: the same steps whether its data are
in memory (:func:`symcal.calibrate.solve.run_stage`) or a log kept as shards
(:func:`symcal.calibrate.log_stage.run_stage_passes`).

:func:`run_stage_on` holds the steps and their order: the start checked (finite
constraints, enough information), the gauges found, the solve (robust losses by IRLS on
the path the first round takes, ``propagated`` weighting at the start and again at that
estimate, ``estimated`` weighting after an equal-weights solve), divergence and collapse,
then the analysis (the sandwich and its robust meat, the serial correlation and its
Newey-West meat, the gauges confirmed at the estimate, ``analyse``, which parameters moved
or sit at a bound, the outliers, the :class:`~symcal.calibrate.result.StageResult`).

What differs between the data in memory and in passes is passed in as a
:class:`StageData`: how the start is checked, how the IRLS weights, the robust meat, the
propagated weights, the serial correlation and the outliers are found (arrays of N rows
or passes over the shards), and the sample the gauges are found and confirmed on (the
dataset itself in memory).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import Any, Protocol, TypeVar

import numpy as np

from symcal.analysis.declared_errors import declared_errors
from symcal.analysis.gauges import find_gauges
from symcal.analysis.identifiability import analyse, conditioning
from symcal.analysis.outliers import Outliers
from symcal.analysis.serial import SerialCorrelation
from symcal.base.errors import DataError, SymcalError
from symcal.base.linalg import is_singular, numerical_rank, sqrt_psd, whitening
from symcal.base.options import SolveOptions
from symcal.base.units import DISPLAY_UNITS, symbol
from symcal.calibrate.result import ConstraintCost, StageResult
from symcal.data.dataset import Dataset
from symcal.problem.symbolic import Problem, Stage
from symcal.solvers.base import SolverOutput
from symcal.solvers.linear import solve_linear
from symcal.solvers.objective import Objective, Source
from symcal.solvers.robust import RobustOutput, RowLosses, row_losses
from symcal.solvers.stage import ipopt, lm, out_of_bounds, solve_stage

Progress = Callable[[str], None] | None
#: Solves a weighted objective from a parameter vector (one IRLS round).
Inner = Callable[[Objective, np.ndarray], SolverOutput]
#: The propagated weighting's weights, held or computed in the passes.
P = TypeVar("P")

#: Propagated weights that change by at most this fraction (per observation) when taken
#: again at the estimate are converged: the stage is not solved again.
REWEIGHT = 1e-2

#: An iterative solve has diverged when a free parameter moved more than this many times
#: its nominal scale from where the stage started.
DIVERGED = 1e6


class Propagation(Protocol[P]):
    """The ``propagated`` weighting's weights of one objective, wherever they live."""

    def weights(self, theta: np.ndarray, before: P | None) -> tuple[P, int, float]:
        """The weights at ``theta`` (each observation's ``C_i^-½``), on how many
        observations the propagated covariance is singular there, and by how much they
        differ from ``before`` (the largest relative change of an observation's; 0
        without ``before``, unused where singular)."""
        ...

    def weighted(self, weights: P) -> Objective:
        """The objective weighted by ``weights``."""
        ...

    def floor(self, theta: np.ndarray, weights: P, there: bool) -> np.ndarray:
        """Each constraint's noise floor at ``theta`` (the root mean square of its
        propagated standard deviation, weighted units); ``weights`` were taken at
        ``theta`` when ``there``, else at another point."""
        ...


class StageData(Protocol):
    """A stage's data and the steps that depend on where they are held."""

    @property
    def data(self) -> Source:
        """The observations the stage is solved on."""
        ...

    @property
    def sample(self) -> Dataset:
        """Where the gauges are found and confirmed (in memory: the data)."""
        ...

    def check_finite(self, objective: Objective, theta: np.ndarray) -> None:
        """Refuse constraints that are inf or NaN at ``theta``, naming where."""
        ...

    def robust(self, objective: Objective, theta: np.ndarray, losses: RowLosses,
               inner: Inner, progress: Progress, label: str) -> RobustOutput[Any]:
        """IRLS rounds of ``losses`` from ``theta``, each solved by ``inner``."""
        ...

    def robust_meat(self, objective: Objective, theta: np.ndarray,
                    robust: RobustOutput[Any], losses: RowLosses, rank: int) -> np.ndarray:
        """The meat of the robust sandwich at the estimate ``theta``."""
        ...

    def propagation(self, objective: Objective) -> Propagation[Any]:
        """The propagated weights of ``objective``."""
        ...

    def serial(self, objective: Objective, out: SolverOutput
               ) -> tuple[SerialCorrelation | None, np.ndarray | None]:
        """Serial correlation of the weighted residuals at ``out`` (None where the rows
        are not in time order) and, where found, the Newey-West meat."""
        ...

    def outliers(self, objective: Objective, theta: np.ndarray,
                 robust: RobustOutput[Any] | None, losses: RowLosses | None,
                 solve_again: Callable[[Objective], SolverOutput],
                 weighted: Objective | None = None) -> Outliers | None:
        """The observations the fit at ``theta`` treats as outliers; ``solve_again``
        solves the stage's objective with per-row weights; ``weighted``, the fit's
        objective where it is weighted by the propagated covariances (the residuals are
        then standardized by each row's propagated standard deviation)."""
        ...


def run_stage_on(
    held: StageData, problem: Problem, stage: Stage, theta: np.ndarray,
    options: SolveOptions, progress: Progress,
) -> tuple[np.ndarray, StageResult]:
    """Solve one stage from ``theta`` on ``held.data`` and analyse its outcome (see the
    module).

    Returns
    -------
    (theta, StageResult)
        The new parameter vector and what happened.
    """
    data = held.data
    free = np.array([p.name in stage.free for p in problem.parameters])
    plain = Objective(problem, stage.constraints, free)
    r_start, c_start, tail0, rows0 = plain.accumulate_r(data, theta)
    if not (np.isfinite(tail0) and np.all(np.isfinite(c_start))):
        held.check_finite(plain, theta)     # a constraint inf or NaN at the start: where
    # the cost per constraint at the start, from that pass (the solver's passes that
    # follow would take its place: asked at the end, it would cost a pass of its own)
    start_terms = plain.cost_terms(data, theta)
    ident0, unc0 = analyse(r_start, rows0, tail0, plain.names, plain.scales,
                           theta[plain.index])
    _check_information(stage, data, rows0, ident0.rank,
                       sum(unc0.se[n] is None for n in plain.names), len(plain.names))
    gauges = find_gauges(plain, held.sample, theta)
    if progress is not None:
        for gauge in gauges.gauges:
            progress(f"  {stage.name}: before the solve, a gauge: {gauge.text}")
    method = options.method or stage.method
    losses = row_losses(plain)
    robust: RobustOutput[Any] | None = None
    objective = plain
    if losses is not None and problem.weighting in ("estimated", "propagated"):
        raise SymcalError(f"stage '{stage.name}': {losses.texts[0]} is a robust loss, which "
                          f"weighting '{problem.weighting}' does not support: remove one of "
                          "them")
    if losses is not None:
        out, notes, robust = _robust(held, plain, theta, losses, method, progress,
                                     stage.name, options)
    elif problem.weighting == "propagated":
        objective, out, notes = _propagated(plain, data, theta, method, progress, stage.name,
                                            options, held.propagation(plain))
    else:
        out, notes = solve_stage(plain, data, theta, method, progress, stage.name, options)
    out = _diverged(out, problem, theta, plain)
    collapse = gauges.collapse(theta, out.theta, plain) if out.success else None
    if collapse is not None:
        out = replace(out, success=False, status="Collapsed", message=collapse)
    if problem.weighting == "estimated" and len(stage.constraints) > 1 and out.success:
        objective, out, note = _reweighted(plain, out, data, method, progress, stage.name,
                                           options)
        notes.append(note)
    names, scales, idx = objective.names, objective.scales, objective.index
    meat = None
    declared = None
    if robust is None and problem.weighting in ("equal", "estimated"):
        declared = declared_errors(problem, objective, data, out.theta, out.rss, out.rows)
    if robust is not None and losses is not None:
        meat = held.robust_meat(plain, out.theta, robust, losses,
                                numerical_rank(out.r_factor, out.rows, scales))
    elif declared is not None:
        meat = declared.meat
    elif len(stage.constraints) > 1:
        rank = numerical_rank(out.r_factor, out.rows, scales)
        cov_g = objective.residual_covariance(data, out.theta, rank)
        meat = objective.accumulate_r(data, out.theta, sqrt_psd(cov_g).T)[0]
    serial: SerialCorrelation | None = None
    if robust is None and out.success:
        serial, hac = held.serial(objective, out)
        if hac is not None:
            meat = hac
    if declared is not None and meat is declared.meat:
        notes.append(declared.note())
    exact_null, confirmed = gauges.confirmed(plain, held.sample, out.theta)
    if len(confirmed.gauges) < len(gauges.gauges):
        gone = [g.text.split(":")[0] + " of " + ", ".join(g.parameters)
                for g in gauges.gauges if g.key not in [c.key for c in confirmed.gauges]]
        notes.append(f"the {'; '.join(gone)} found before the solve does not hold at the "
                     "estimate: a degeneracy of the region the start lies in, not a gauge")
        gauges = confirmed
        if collapse is not None:     # said with the fix of the gauges that hold
            out = replace(out, message=gauges.collapse(theta, out.theta, plain) or collapse)
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

    propagated = objective if problem.weighting == "propagated" and objective is not plain \
        else None
    outliers = held.outliers(plain, out.theta, robust, losses, solve_again, propagated)
    result = StageResult(
        stage.name, stage.doc, out.method, out.success, out.status, out.message,
        out.iterations, out.seconds, names, _constraint_costs(plain, data, start_terms,
                                                              out.theta),
        tuple(n for n, m in zip(names, moved, strict=True) if not m), tuple(at_bound),
        conditioning(r_start, out.rows, names, scales),
        conditioning(out.r_factor, out.rows, names, scales, gauges=exact_null), ident, unc,
        tuple(notes), outliers, gauges, serial,
    )
    return out.theta, result


def _robust(
    held: StageData, objective: Objective, theta: np.ndarray, losses: RowLosses,
    method: str, progress: Progress, label: str, options: SolveOptions,
) -> tuple[SolverOutput, list[str], RobustOutput[Any]]:
    """Solve a stage with robust losses: reweighting rounds, each on the path the first
    round takes (:func:`~symcal.solvers.stage.solve_stage`), warm-started."""
    data = held.data
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

    robust = held.robust(objective, theta, losses, inner, progress, label)
    return robust.output, notes, robust


def _singular(count: int, n: int, kept: str = "kept equal weights", where: str = "") -> str:
    return (f"weighting: the propagated covariance of the constraints is singular on "
            f"{count} of {n} observations{where} (the readings they use are declared exact "
            f"there, or one constraint is a combination of the others, as g3 = g1 + g2: "
            f"leave it out); {kept}")


def _propagated(
    plain: Objective, data: Source, theta: np.ndarray, method: str, progress: Progress,
    label: str, options: SolveOptions, weights: Propagation[P],
) -> tuple[Objective, SolverOutput, list[str]]:
    """Solve weighted by the covariance propagated from the readings' noise: at the start,
    then again at that estimate (the covariance depends on the parameters through the
    constraints' derivatives by the readings) unless the weights there differ by at most
    :data:`REWEIGHT`."""
    problem = plain.problem
    missing = sorted({c for n in plain.constraints
                      for c in problem.undeclared(problem.constraint(n).sx)})
    if missing:
        raise SymcalError(f"weighting 'propagated' needs the noise of every reading the "
                          f"constraints read; no noise is declared for the column(s) "
                          f"{', '.join(repr(m) for m in missing)}: declare it ('noise: 0.5 um' "
                          "on the column, on the model input bound to it, or in the "
                          "problem's 'noise:' section), or choose another weighting")
    start, singular, _ = weights.weights(theta, None)
    if singular:
        out, notes = solve_stage(plain, data, theta, method, progress, label, options)
        return plain, out, [*notes, _singular(singular, data.n)]
    weighted = weights.weighted(start)
    first, notes = solve_stage(weighted, data, theta, method, progress, label, options)
    if not first.success:
        return weighted, first, notes
    again, singular, change = weights.weights(first.theta, start)
    if singular:            # at that estimate: it is kept, weighted as at the start
        return weighted, first, [*notes, _singular(
            singular, data.n, "kept that estimate, weighted as at the start",
            " at the estimate weighted at the start")]
    when = "at the start and again at that estimate"
    if change <= REWEIGHT:    # the weights have converged: solving again moves nothing
        second, when = first, (f"at the start (at that estimate they differ by "
                               f"{change:.1g} at most)")
    else:
        reweighted = weights.weighted(again)
        second, _ = solve_stage(reweighted, data, first.theta, method, progress, label,
                                options)
        if second.success:
            weighted = reweighted
        else:   # from a converged point: keep it, weighted as at the start
            notes.append(f"weighting: solving again with the weights at the estimate did "
                         f"not succeed ({second.message}); kept the estimate weighted at "
                         "the start")
            second, when = first, "at the start"
    merged = _chained(first, second,
                      "; weighted by the covariance propagated from the readings' noise")
    floor = weights.floor(second.theta, again, second is first)
    note = ("weighting: each observation's constraints whitened by their covariance "
            f"propagated from the readings' declared noise, {when} (noise floor "
            f"{_sizes(problem, plain.constraints, floor)})")
    return weighted, merged, [*notes, note]


def _sizes(problem: Problem, names: Sequence[str], scaled: np.ndarray) -> str:
    """``name size unit, ...``: each constraint's spread (``scaled``, in units of its
    scale σ) in its display unit."""
    out = []
    for k, name in enumerate(names):
        q = problem.constraint(name)
        out.append(f"{name} {scaled[k] * q.sigma / DISPLAY_UNITS[q.unit]:.3g} {symbol(q.unit)}")
    return ", ".join(out)


def _chained(first: SolverOutput, second: SolverOutput, how: str) -> SolverOutput:
    """The second solve's output (``how`` added to its message), counting the iterations
    and time of both (once where the second is the first)."""
    again = second is not first
    return SolverOutput(
        second.theta, second.free, second.method, second.success, second.status,
        second.message + how, second.r_factor, second.rows, second.rss,
        first.iterations + (second.iterations if again else 0),
        first.seconds + (second.seconds if again else 0.0))


def _reweighted(
    objective: Objective, first: SolverOutput, data: Source, method: str,
    progress: Progress, label: str, options: SolveOptions,
) -> tuple[Objective, SolverOutput, str]:
    """Solve again, weighted by the constraints' covariance estimated from the residuals."""
    rank = numerical_rank(first.r_factor, first.rows, objective.scales)
    cov = objective.residual_covariance(data, first.theta, rank)
    if is_singular(cov):
        return objective, first, ("weighting: the constraints' residual covariance is "
                                  "singular; kept equal weights")
    whitened = Objective(objective.problem, objective.constraints, objective.free,
                         whitening(cov)[0])
    second, _ = solve_stage(whitened, data, first.theta, method, progress, label, options)
    merged = _chained(first, second, "; weighted by the estimated covariance of the constraints")
    note = ("weighting: solved with equal weights, then again with each observation's "
            "constraints whitened by their covariance estimated from those residuals "
            f"(residual std "
            f"{_sizes(objective.problem, objective.constraints, np.sqrt(np.diag(cov)))})")
    return whitened, merged, note


def _constraint_costs(objective: Objective, data: Source, start: Mapping[str, float],
                      after: np.ndarray) -> tuple[ConstraintCost, ...]:
    """Each constraint's cost at the start (``start``: :meth:`Objective.cost_terms` there)
    and at ``after``."""
    end = objective.cost_terms(data, after)
    out = []
    for name in objective.constraints:
        q = objective.problem.constraint(name)
        to_rms = q.sigma / np.sqrt(data.n) / DISPLAY_UNITS[q.unit]
        out.append(ConstraintCost(name, q.unit, start[name], end[name],
                                  float(np.sqrt(start[name]) * to_rms),
                                  float(np.sqrt(end[name]) * to_rms)))
    return tuple(out)


def _diverged(out: SolverOutput, problem: Problem, theta0: np.ndarray,
              objective: Objective) -> SolverOutput:
    """``out`` marked failed when an iterative method carried a parameter away (a
    divergence, whatever the solver's own status says)."""
    if out.method == "linear" or not out.success:
        return out
    moved = np.abs(out.theta[objective.index] - theta0[objective.index]) / objective.scales
    worst = int(np.argmax(moved)) if moved.size else 0
    if moved.size and moved[worst] > DIVERGED:
        name = objective.names[worst]
        i = problem.index[name]
        return replace(out, success=False, status="Diverged",
                       message=f"failed: the iterates diverged ({name} went from "
                               f"{theta0[i]:.6g} to {out.theta[i]:.6g}, more than "
                               f"{DIVERGED:g} times its scale {objective.scales[worst]:g})")
    return out


def _check_information(stage: Stage, data: Source, rows: int, rank: int,
                       unidentifiable: int, n_free: int) -> None:
    """Refuse data that determine no parameter at the start, or leave no degree of
    freedom: bad input, found before anything is solved."""
    if rows <= rank:
        raise DataError(f"stage '{stage.name}': {data.n} observations of '{data.name}' give "
                        f"{rows} residual values for {rank} identifiable parameters; at "
                        f"least {rank + 1} are needed (more for a useful fit)")
    if unidentifiable == n_free:
        raise DataError(f"stage '{stage.name}': the {data.n} observations of '{data.name}' "
                        f"determine none of the {n_free} free parameters individually (only "
                        f"{rank} combination(s) of them): the data do not excite the model; "
                        "check that the inputs vary over the calibration")
