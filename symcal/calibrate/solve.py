"""The public entry point: solve a problem's study stage by stage, then analyse."""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path

import numpy as np

from symcal.analysis.fit import series_statistics
from symcal.analysis.floors import (
    Fit,
    floor_tests,
    inverse_sqrt_rows,
    row_covariances,
    time_ordered,
)
from symcal.analysis.gauges import find_gauges
from symcal.analysis.identifiability import Uncertainty, analyse, conditioning
from symcal.analysis.implicit import implicit_checks
from symcal.analysis.outliers import Outliers, find_outliers
from symcal.analysis.serial import SerialCorrelation, bandwidth, detect, hac_meat
from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import DataError, SolveError, SymcalError
from symcal.base.linalg import is_singular, numerical_rank, sqrt_psd, whitening
from symcal.base.options import METHODS, SolveOptions
from symcal.base.progress import Bars, reporting
from symcal.base.units import DISPLAY_UNITS, symbol
from symcal.calibrate.result import (
    ConstraintCost,
    DatasetInfo,
    ParameterResult,
    Result,
    StageResult,
    file_hashes,
    parameter_table,
)
from symcal.data.dataset import Dataset
from symcal.data.loading import load_datasets
from symcal.problem.build import load_problem
from symcal.problem.symbolic import Problem, Stage
from symcal.solvers.base import SolverOutput
from symcal.solvers.executor import blas_limited
from symcal.solvers.linear import solve_linear
from symcal.solvers.objective import Objective, Source
from symcal.solvers.robust import RowLosses, row_losses, sandwich_meat, solve_robust
from symcal.solvers.stage import ipopt, lm, out_of_bounds, solve_stage

Progress = Callable[[str], None] | None


def _robust(
    objective: Objective, data: Dataset, theta: np.ndarray, losses: RowLosses, method: str,
    progress: Progress, label: str, options: SolveOptions,
) -> tuple[SolverOutput, list[str], np.ndarray]:
    """Solve a stage with robust losses: reweighting rounds, each on the path the first
    round takes (:func:`_solve_stage`), warm-started."""
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

    robust = solve_robust(objective, data, theta, losses, inner, progress, label)
    return robust.output, notes, robust.weights


def _outliers(objective: Objective, data: Dataset, theta: np.ndarray,
              weights: np.ndarray | None, losses: RowLosses | None,
              solve_again: Callable[[Objective], SolverOutput] | None = None
              ) -> Outliers | None:
    """The observations the stage's fit treats as outliers (None where a residual is not
    finite at the estimate); ``solve_again`` solves the stage's objective with per-row
    weights, for the outliers' noise measured without them."""
    problem = objective.problem
    g = objective.residuals(data, theta)
    if not np.all(np.isfinite(g)):
        return None
    quantities = [problem.constraint(n) for n in objective.constraints]
    time_col = next((c for c, spec in problem.column_specs.items()
                     if spec.role == "time" and c in data.columns), None)
    return find_outliers(
        data.name, objective.constraints, tuple(q.unit for q in quantities),
        np.array([q.sigma / DISPLAY_UNITS[q.unit] for q in quantities]), g, weights,
        "squared" if losses is None else "; ".join(losses.texts),
        None if time_col is None else np.asarray(data.columns[time_col], dtype=float),
        None if solve_again is None else _refit(objective, data, solve_again))


def _refit(objective: Objective, data: Dataset,
           solve_again: Callable[[Objective], SolverOutput]) -> Callable[[np.ndarray],
                                                                          np.ndarray | None]:
    """The residual rows of the stage solved again with some residuals set aside."""
    def refit(aside: np.ndarray) -> np.ndarray | None:
        out = solve_again(objective.with_row_weights((~aside).astype(float)))
        return objective.residuals(data, out.theta) if out.success else None

    return refit


def _constraint_costs(objective: Objective, data: Source, before: np.ndarray,
                      after: np.ndarray) -> tuple[ConstraintCost, ...]:
    start, end = objective.cost_terms(data, before), objective.cost_terms(data, after)
    out = []
    for name in objective.constraints:
        q = objective.problem.constraint(name)
        to_rms = q.sigma / np.sqrt(data.n) / DISPLAY_UNITS[q.unit]
        out.append(ConstraintCost(name, q.unit, start[name], end[name],
                                  float(np.sqrt(start[name]) * to_rms),
                                  float(np.sqrt(end[name]) * to_rms)))
    return tuple(out)


def _reweighted(
    objective: Objective, first: SolverOutput, data: Dataset, method: str,
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
    merged = SolverOutput(
        second.theta, second.free, second.method, second.success, second.status,
        second.message + "; weighted by the estimated covariance of the constraints",
        second.r_factor, second.rows, second.rss, first.iterations + second.iterations,
        first.seconds + second.seconds)
    problem = objective.problem
    sizes = []
    for k, name in enumerate(objective.constraints):
        q = problem.constraint(name)
        sizes.append(f"{name} {np.sqrt(cov[k, k]) * q.sigma / DISPLAY_UNITS[q.unit]:.3g} "
                     f"{q.unit or '(internal)'}")
    note = ("weighting: solved with equal weights, then again with each observation's "
            "constraints whitened by their covariance estimated from those residuals "
            f"(residual std {', '.join(sizes)})")
    return whitened, merged, note


def _propagated_weights(objective: Objective, data: Dataset, theta: np.ndarray
                        ) -> tuple[np.ndarray | None, str]:
    """Each observation's ``C_i^-½`` of the stage's weighted constraints at ``theta`` (the
    covariance propagated from the readings' declared noise), or None and why not."""
    problem = objective.problem
    missing = sorted({c for n in objective.constraints
                      for c in problem.undeclared(problem.constraint(n).sx)})
    if missing:
        raise SymcalError(f"weighting 'propagated' needs the noise of every reading the "
                          f"constraints read; no noise is declared for the column(s) "
                          f"{', '.join(repr(m) for m in missing)}: declare it ('noise: 0.5 um' "
                          "on the column, on the model input bound to it, or in the "
                          "problem's 'noise:' section), or choose another weighting")
    cov = row_covariances(problem, objective.constraints, data, theta)
    t, singular = inverse_sqrt_rows(cov)
    if singular:
        return None, (f"weighting: the propagated covariance of the constraints is singular "
                      f"on {singular} of {data.n} observations (the readings they use are "
                      "declared exact there); kept equal weights")
    return t, ""


#: Propagated weights that change by at most this fraction (per observation) when taken
#: again at the estimate are converged: the stage is not solved again.
REWEIGHT = 1e-2


def _propagated(
    plain: Objective, data: Dataset, theta: np.ndarray, method: str, progress: Progress,
    label: str, options: SolveOptions,
) -> tuple[Objective, SolverOutput, list[str]]:
    """Solve weighted by the covariance propagated from the readings' noise: at the start,
    then again at that estimate (the covariance depends on the parameters through the
    constraints' derivatives by the readings)."""
    weights, why = _propagated_weights(plain, data, theta)
    if weights is None:
        out, notes = solve_stage(plain, data, theta, method, progress, label, options)
        return plain, out, [*notes, why]
    weighted = plain.with_row_weights(weights)
    first, notes = solve_stage(weighted, data, theta, method, progress, label, options)
    if not first.success:
        return weighted, first, notes
    again, why = _propagated_weights(plain, data, first.theta)
    if again is None:
        return weighted, first, [*notes, why]
    change = float(np.max(np.linalg.norm(again - weights, axis=(1, 2))
                          / np.maximum(np.linalg.norm(weights, axis=(1, 2)), 1e-300)))
    when = "at the start and again at that estimate"
    if change <= REWEIGHT:    # the weights have converged: solving again moves nothing
        second, when = first, (f"at the start (at that estimate they differ by "
                               f"{change:.1g} at most)")
    else:
        reweighted = plain.with_row_weights(again)
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
    problem = plain.problem
    floor = np.sqrt(np.mean(np.diagonal(row_covariances(problem, plain.constraints, data,
                                                        second.theta), axis1=1, axis2=2),
                            axis=0))
    sizes = []
    for k, name in enumerate(plain.constraints):
        q = problem.constraint(name)
        sizes.append(f"{name} {floor[k] * q.sigma / DISPLAY_UNITS[q.unit]:.3g} "
                     f"{symbol(q.unit)}")
    note = ("weighting: each observation's constraints whitened by their covariance "
            f"propagated from the readings' declared noise, {when} (noise floor "
            f"{', '.join(sizes)})")
    return weighted, merged, [*notes, note]


def _check_finite(objective: Objective, data: Dataset, theta: np.ndarray) -> None:
    """Refuse constraints that are inf or NaN at the start, naming where."""
    g = objective.residuals(data, theta)
    bad = ~np.isfinite(g)
    if bad.any():
        row, k = (int(i) for i in np.argwhere(bad)[0])
        raise SymcalError(
            f"constraint '{objective.constraints[k]}' is {g[row, k]} at the initial "
            f"parameters on observation {row + 1} of '{data.name}' ({data.source}), and on "
            f"{int(bad.any(axis=1).sum())} observation(s) in all; check its expression and "
            "the data there")


#: An iterative solve has diverged when a free parameter moved more than this many times
#: its nominal scale from where the stage started.
DIVERGED = 1e6


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


def _check_information(stage: Stage, data: Dataset, rows: int, rank: int,
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


@blas_limited
def run_stage(
    problem: Problem, stage: Stage, data: Dataset, theta: np.ndarray,
    options: SolveOptions | None = None, progress: Progress = None,
) -> tuple[np.ndarray, StageResult]:
    """Solve one stage from ``theta`` and analyse its outcome.

    Returns
    -------
    (theta, StageResult)
        The new parameter vector and what happened.
    """
    options = options or problem.options
    free = np.array([p.name in stage.free for p in problem.parameters])
    plain = Objective(problem, stage.constraints, free)
    _check_finite(plain, data, theta)
    r_start, _, tail0, rows0 = plain.accumulate_r(data, theta)
    ident0, unc0 = analyse(r_start, rows0, tail0, plain.names, plain.scales,
                           theta[plain.index])
    _check_information(stage, data, rows0, ident0.rank,
                       sum(unc0.se[n] is None for n in plain.names), len(plain.names))
    gauges = find_gauges(plain, data, theta)
    if progress is not None:
        for gauge in gauges.gauges:
            progress(f"  {stage.name}: before the solve, a gauge: {gauge.text}")
    method = options.method or stage.method
    losses = row_losses(plain)
    weights = None
    objective = plain
    if losses is not None and problem.weighting in ("estimated", "propagated"):
        raise SymcalError(f"stage '{stage.name}': {losses.texts[0]} is a robust loss, which "
                          f"weighting '{problem.weighting}' does not support: remove one of "
                          "them")
    if losses is not None:
        out, notes, weights = _robust(plain, data, theta, losses, method, progress,
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
        objective, out, note = _reweighted(plain, out, data, method, progress, stage.name,
                                           options)
        notes.append(note)
    names, scales, idx = objective.names, objective.scales, objective.index
    meat = None
    if weights is not None:
        meat = sandwich_meat(plain, data, out.theta,
                             weights, numerical_rank(out.r_factor, out.rows, scales))
    elif len(stage.constraints) > 1:
        rank = numerical_rank(out.r_factor, out.rows, scales)
        cov_g = objective.residual_covariance(data, out.theta, rank)
        meat = objective.accumulate_r(data, out.theta, sqrt_psd(cov_g).T)[0]
    serial = None
    if weights is None and out.success and time_ordered(problem, data):
        serial, hac = _serial(objective, data, out)
        if hac is not None:
            meat = hac
    exact_null, held = gauges.confirmed(plain, data, out.theta)
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
    outliers = _outliers(plain, data, out.theta, weights, losses, lambda weighted:
                         solve_stage(weighted, data, out.theta, method, None, stage.name,
                                     options)[0])
    result = StageResult(
        stage.name, stage.doc, out.method, out.success, out.status, out.message,
        out.iterations, out.seconds, names, _constraint_costs(plain, data, theta, out.theta),
        tuple(n for n, m in zip(names, moved, strict=True) if not m), tuple(at_bound),
        conditioning(r_start, out.rows, names, scales),
        conditioning(out.r_factor, out.rows, names, scales, gauges=exact_null), ident, unc,
        tuple(notes), outliers, gauges, serial,
    )
    return out.theta, result


def _serial(objective: Objective, data: Dataset, out: SolverOutput
            ) -> tuple[SerialCorrelation, np.ndarray | None]:
    """Serial correlation of the stage's weighted residuals on time-ordered rows, and
    where it is found the HAC meat (``M`` with ``MᵀM`` the Newey-West sum of the scores,
    scaled by rows/(rows - rank)) for its standard errors."""
    found = detect(objective.constraints, objective.residuals(data, out.theta))
    if not found.detected:
        return found, None
    lags = bandwidth(max(found.rho, key=abs), data.n)
    rank = numerical_rank(out.r_factor, out.rows, objective.scales)
    meat = hac_meat(objective.score_chunks(data, out.theta), lags, len(objective.index))
    meat *= out.rows / max(out.rows - rank, 1)
    return replace(found, lags=lags), sqrt_psd(meat).T


@blas_limited
def solve(
    problem: Problem | str | Path,
    data: Mapping[str, Dataset | str | Path] | None = None,
    options: SolveOptions | None = None,
    *,
    drop_invalid: bool = False,
    progress: Progress = None,
    initial: Mapping[str, float] | None = None,
    bars: Bars | None = None,
) -> Result:
    """Calibrate: estimate the parameters on the ``calibration`` dataset, stage by stage.

    Parameters
    ----------
    problem
        A :class:`~symcal.problem.symbolic.Problem` or the path of a problem file.
    data
        Datasets by name, as :class:`~symcal.data.dataset.Dataset` objects or file paths; those not
        given come from the problem's ``datasets`` section.
    options
        How to solve (:class:`~symcal.base.options.SolveOptions`: method, iteration
        limit, IPOPT options); default: the problem file's ``solver:`` section.
    drop_invalid
        Drop rows with NaN/inf instead of refusing them.
    progress
        Called with each line of progress: one per solver iteration, and notes such as
        the gauges found before a stage's solve (None: no lines).  See
        :mod:`symcal.base.progress`.
    initial
        Initial values by parameter name, replacing those of the problem file.
    bars
        Progress bars (:func:`symcal.base.progress.terminal_bars`): one meter counting
        the solver's iterations, the latest iteration's line beside it (then not passed
        to ``progress``).  None: no bars.

    Returns
    -------
    Result
        Frozen: the problem, the estimate with standard errors, identifiability (rank,
        condition number, named null space), every stage's report, before/after
        statistics on every dataset, and the datasets themselves.  ``success`` is False
        when a stage failed.
    """
    if not isinstance(problem, Problem):
        problem = load_problem(problem)
    options = options or problem.options
    if options.method is not None and options.method not in METHODS:
        raise SolveError(f"unknown method '{options.method}'"
                         f"{did_you_mean(options.method, METHODS)}; "
                         f"methods: {', '.join(METHODS)}")
    datasets = load_datasets(problem, data, drop_invalid)
    for name, ds in datasets.items():
        if not isinstance(ds, Dataset):
            raise DataError(f"dataset '{name}' ({ds.source}) is a folder of shards: solve a log "
                            "kept as shards with symcal.solve_partitioned (symcal solve "
                            "--data NAME=FOLDER does so by itself), and give held-out "
                            "datasets as files")
    theta0 = _initial(problem, initial or {})
    theta = theta0
    stages: list[StageResult] = []
    with reporting(progress, bars, "solve", None, "it") as report:
        for stage in problem.stages:
            theta, result = run_stage(problem, stage, datasets[problem.fit_dataset], theta,
                                      options, report.callback())
            stages.append(result)
            if not result.success:
                break
    return _result(problem, datasets, data or {}, theta0, theta, tuple(stages))


def _initial(problem: Problem, initial: Mapping[str, float]) -> np.ndarray:
    theta = np.array([p.value for p in problem.parameters])
    names = problem.parameter_names
    for name, value in initial.items():
        if name not in problem.index:
            raise SolveError(f"initial value for unknown parameter '{name}'"
                             f"{did_you_mean(name, names)}")
        theta[problem.index[name]] = float(value)
    return theta


def _info(ds: Dataset, given: Dataset | str | Path | None, spec_path: Path | None
          ) -> DatasetInfo:
    """What a dataset was; a file's absolute path and hash, so a result can find it again."""
    file = None if isinstance(given, Dataset) else (Path(given) if given is not None
                                                     else spec_path)
    if file is None:
        return DatasetInfo(ds.name, ds.source, ds.n, ds.dropped)
    file = file.resolve()
    return DatasetInfo(ds.name, ds.source, ds.n, ds.dropped, str(file),
                       hashlib.sha256(file.read_bytes()).hexdigest())


def _result(problem: Problem, datasets: dict[str, Dataset],
            given: Mapping[str, Dataset | str | Path], theta0: np.ndarray,
            theta: np.ndarray, stages: tuple[StageResult, ...]) -> Result:
    last = stages[-1]
    params = parameter_table(
        ParameterResult(p.name, float(theta[i]), float(theta0[i]), p.unit, p.fixed,
                        last.uncertainty.se.get(p.name),
                        last.uncertainty.reason.get(p.name, _no_se_reason(p.name, p.fixed,
                                                                          last)),
                        p.lower, p.upper, p.doc, correlations(last.uncertainty, p.name))
        for i, p in enumerate(problem.parameters)
    )
    stats, skipped = series_statistics(problem, datasets, theta0, theta)
    found, tests = floor_tests(problem, datasets, theta, _fit(problem, datasets, theta, last),
                               theta0)
    stats = tuple(replace(s, noise=found.get((s.dataset, s.name))) for s in stats)
    checks = implicit_checks(problem, datasets, theta)
    notes = list(skipped) + [
        f"'{c.name}' is not a contraction on dataset '{c.dataset}': max |dF/dx| = "
        f"{c.contraction:.3g} >= 1, so its fixed-point steps do not converge and the result "
        "is not to be trusted (the errors are too large for this form of the model)"
        for c in checks if not c.contracts]
    infos = tuple(_info(d, given.get(d.name), problem.datasets[d.name].path)
                  for d in datasets.values())
    return Result(problem, theta0, theta, stages, params, last.identifiability,
                  last.uncertainty, stats, infos, tuple(notes), checks, tests,
                  _hashes(problem), datasets)


def _hashes(problem: Problem) -> dict[str, str] | None:
    """The problem's files' hashes at solve time (None where a file cannot be read: the
    document then hashes them when it is written, and says why it cannot)."""
    try:
        return file_hashes(problem)
    except SymcalError:
        return None


def _fit(problem: Problem, datasets: Mapping[str, Dataset], theta: np.ndarray,
         last: StageResult) -> Fit:
    """How the last stage fitted the estimate, for the noise's share in it."""
    stage = next(st for st in problem.stages if st.name == last.name)
    free = np.array([p.name in last.free for p in problem.parameters])
    weighting = problem.weighting
    if last.outliers is not None and not last.outliers.squared:
        weighting = "equal"          # a robust fit: its weights are the losses'
    if any(n.startswith("weighting:") and "kept equal weights" in n for n in last.notes):
        weighting = "equal"
    whiten = None
    if weighting == "estimated":
        fit = problem.fit_dataset
        if len(stage.constraints) > 1 and fit in datasets:
            plain = Objective(problem, stage.constraints, free)
            rank = last.identifiability.rank
            whiten = whitening(plain.residual_covariance(datasets[fit], theta, rank))[0]
        else:
            weighting = "equal"
    return Fit(problem.fit_dataset, stage.constraints, free, weighting, whiten)


def correlations(unc: Uncertainty, name: str) -> dict[str, float]:
    """``name``'s finite correlations with the other free parameters of a stage."""
    if name not in unc.names:
        return {}
    k = unc.names.index(name)
    row = np.asarray(unc.correlation[k], dtype=float)
    keep = np.isfinite(row)
    keep[k] = False
    return {unc.names[j]: float(row[j]) for j in np.flatnonzero(keep)}


def _no_se_reason(name: str, fixed: bool, last: StageResult) -> str | None:
    if fixed:
        return "fixed"
    if name not in last.free:
        return f"not free in the last stage ('{last.name}')"
    return None
