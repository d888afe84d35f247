"""Calibrate on one huge log: a problem's stages on its fitted dataset kept as shards.

The log stays on disk as shards (:mod:`symcal.data.shards`: partitioned Parquet, NPZ
shards or CSV shards); every pass of the solve over it (cost, normal equations, TSQR,
residual covariance) is one task per shard on an executor
(:mod:`symcal.solvers.executor`: Dask workers, threads or this process), each returning a
small reduction, so memory is bounded per worker and the lead never holds the log.  The
solvers are the ones of :func:`symcal.solve`, with the same choice of method per stage,
so the estimate equals the one of the same solve on the log in memory (to rounding: the
shards are reduced in another grouping).

It returns a :class:`~symcal.calibrate.result.Result` like :func:`symcal.solve`: every
stage's outcome, costs, conditioning, identifiability and standard errors from the R
factor (sandwich included); the gauges, found on a bounded sample of the log; the
before/after statistics of every residual and comparison, on the log shard by shard
(exact: the moments of the shards combined) and on the held-out datasets, which are read
into memory as usual; the implicit definitions' checks.  What needs every row at once is
not computed on the log, and the result says so in its notes: the outliers, per-row
weights (``propagated`` weighting and robust losses: refused, or equal weights with a
note) and the noise floor of the log.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar, cast

import numpy as np

from symcal.analysis.fit import SeriesStats, Spread, series_statistics
from symcal.analysis.floors import floor_tests
from symcal.analysis.gauges import find_gauges
from symcal.analysis.identifiability import analyse, conditioning
from symcal.analysis.implicit import ImplicitCheck, implicit_checks
from symcal.base.errors import DataError, SolveError
from symcal.base.linalg import is_singular, numerical_rank, sqrt_psd, whitening
from symcal.base.options import SolveOptions
from symcal.base.progress import Bars, Meter, meter
from symcal.calibrate.result import (
    DatasetInfo,
    ParameterResult,
    Result,
    StageResult,
    parameter_table,
)
from symcal.calibrate.solve import (
    _constraint_costs,
    _diverged,
    _fit,
    _hashes,
    _info,
    _initial,
    _no_se_reason,
    correlations,
)
from symcal.data.dataset import Dataset
from symcal.data.loading import load_datasets, needed_columns
from symcal.data.shards import ShardedDataset, open_shards
from symcal.problem.build import load_problem
from symcal.problem.symbolic import Problem, Stage
from symcal.solvers.base import SolverOutput
from symcal.solvers.executor import Executor, SerialExecutor, current, using
from symcal.solvers.objective import Objective, Source
from symcal.solvers.stage import solve_stage

if TYPE_CHECKING:
    from distributed import Client

T = TypeVar("T")

#: Observations of the log the gauge analysis looks at (evenly spaced in its first shards).
GAUGE_SAMPLE = 2_000


class _Metered:
    """An executor whose finished pieces advance a progress meter."""

    def __init__(self, inner: Executor, m: Meter) -> None:
        self.inner, self.meter = inner, m
        self.remote = inner.remote

    def map(self, task: Callable[[Any], T], pieces: Iterable[Any]) -> Iterator[T]:
        for value in self.inner.map(task, pieces):
            self.meter.advance()
            yield value


def _reweighted(problem: Problem, stage: Stage, objective: Objective, out: SolverOutput,
                data: Source, method: str, progress: Callable[[str], None] | None,
                options: SolveOptions) -> tuple[Objective, SolverOutput, list[str]]:
    """``estimated`` weighting on the log: again, whitened by the residual covariance."""
    rank = numerical_rank(out.r_factor, out.rows, objective.scales)
    cov = objective.residual_covariance(data, out.theta, rank)
    if is_singular(cov):
        return objective, out, ["weighting: the constraints' residual covariance is "
                                "singular; kept equal weights"]
    whitened = Objective(problem, stage.constraints, objective.free, whitening(cov)[0])
    second, more = solve_stage(whitened, data, out.theta, method, progress, stage.name,
                               options)
    merged = SolverOutput(second.theta, second.free, second.method, second.success,
                          second.status, second.message + "; weighted by the estimated "
                          "covariance of the constraints", second.r_factor, second.rows,
                          second.rss, out.iterations + second.iterations,
                          out.seconds + second.seconds)
    return whitened, merged, more + ["weighting: solved with equal weights, then again "
                                     "whitened by the constraints' covariance estimated "
                                     "from those residuals"]


def _run_stage(problem: Problem, stage: Stage, data: Source, sample: Dataset,
               theta: np.ndarray, options: SolveOptions,
               progress: Callable[[str], None] | None) -> tuple[np.ndarray, StageResult]:
    free = np.array([p.name in stage.free for p in problem.parameters])
    robust = [n for n in stage.constraints if problem.constraint(n).loss is not None]
    if robust:
        raise SolveError(f"stage '{stage.name}': constraint(s) {', '.join(robust)} have a "
                         "robust loss, which reweights every row; a partitioned log is "
                         "solved with squared losses only")
    plain = Objective(problem, stage.constraints, free)
    r_start, _, _, rows0 = plain.accumulate_r(data, theta)
    gauges = find_gauges(plain, sample, theta)
    method = options.method or stage.method
    out, notes = solve_stage(plain, data, theta, method, progress, stage.name, options)
    if problem.weighting == "propagated":
        notes.append("weighting: 'propagated' weights each observation, which a "
                     "partitioned log does not support yet: solved with equal weights")
    out = _diverged(out, problem, theta, plain)
    collapse = gauges.collapse(theta, out.theta, plain) if out.success else None
    if collapse is not None:
        out = replace(out, success=False, status="Collapsed", message=collapse)
    objective = plain
    if problem.weighting == "estimated" and len(stage.constraints) > 1 and out.success:
        objective, out, more = _reweighted(problem, stage, plain, out, data, method,
                                           progress, options)
        notes += more
    names, scales, idx = objective.names, objective.scales, objective.index
    meat = None
    if len(stage.constraints) > 1:
        rank = numerical_rank(out.r_factor, out.rows, scales)
        cov_g = objective.residual_covariance(data, out.theta, rank)
        meat = objective.accumulate_r(data, out.theta, sqrt_psd(cov_g).T)[0]
    exact_null, held = gauges.confirmed(plain, sample, out.theta)
    gauges = held
    ident, unc = analyse(out.r_factor, out.rows, out.rss, names, scales, out.theta[idx],
                         meat, exact_null)
    moved = np.abs(out.theta[idx] - theta[idx]) > 1e-12 * scales
    at_bound = [p.name for p in (problem.parameters[i] for i in idx)
                if min(abs(out.theta[problem.index[p.name]] - b) for b in (p.lower, p.upper))
                <= 1e-7 * p.scale]
    notes.append(f"the outliers and the serial correlation of the residuals are not looked "
                 f"for on the partitioned log '{data.name}' (they need every row's residual "
                 "at once)")
    result = StageResult(
        stage.name, stage.doc, out.method, out.success, out.status, out.message,
        out.iterations, out.seconds, names, _constraint_costs(plain, data, theta, out.theta),
        tuple(n for n, m in zip(names, moved, strict=True) if not m), tuple(at_bound),
        conditioning(r_start, rows0, names, scales),
        conditioning(out.r_factor, out.rows, names, scales, gauges=exact_null), ident, unc,
        tuple(notes), None, gauges)
    return out.theta, result


def _combined(parts: list[SeriesStats]) -> SeriesStats:
    """One residual's statistics over the whole log from those of its shards (exact)."""
    n = sum(p.n for p in parts)

    def spread(which: str) -> Spread:
        total = sum(p.n * getattr(p, which).mean for p in parts)
        squares = sum(p.n * getattr(p, which).rms ** 2 for p in parts)
        mean, rms = total / n, float(np.sqrt(squares / n))
        return Spread(rms, mean, float(np.sqrt(max(rms * rms - mean * mean, 0.0))))

    return replace(parts[0], n=n, before=spread("before"), after=spread("after"))


def _log_analysis(problem: Problem, log: ShardedDataset, theta0: np.ndarray,
                  theta: np.ndarray) -> tuple[list[SeriesStats], list[str],
                                              list[ImplicitCheck]]:
    """Statistics and implicit checks of the log, one shard in memory at a time."""
    by_name: dict[str, list[SeriesStats]] = {}
    notes: list[str] = []
    worst: dict[str, ImplicitCheck] = {}
    for shard in log.shards:
        ds = shard.dataset(log.name)
        stats, skipped = series_statistics(problem, {log.name: ds}, theta0, theta)
        for s in stats:
            by_name.setdefault(s.name, []).append(s)
        notes += [n for n in skipped if n not in notes]
        for c in implicit_checks(problem, {log.name: ds}, theta):
            old = worst.get(c.name)
            worst[c.name] = c if old is None else replace(
                old, contraction=max(old.contraction, c.contraction),
                last_step=max(old.last_step, c.last_step))
    return [_combined(parts) for parts in by_name.values()], notes, list(worst.values())


def solve_partitioned(
    problem: Problem | str | Path,
    calibration: ShardedDataset | Dataset | str | Path,
    options: SolveOptions | None = None,
    *,
    data: Mapping[str, Dataset | str | Path] | None = None,
    executor: Executor | str | Any | None = None,
    workers: int | None = None,
    progress: Callable[[str], None] | None = None,
    bars: Bars | None = None,
) -> Result:
    """Solve a problem's stages on its fitted dataset kept as shards.

    Parameters
    ----------
    problem
        The problem, or its YAML file.
    calibration
        The log of the fitted dataset (``problem.fit_dataset``): a folder of shards or an
        opened :class:`~symcal.data.shards.ShardedDataset` (an in-memory
        :class:`~symcal.data.dataset.Dataset` is accepted too, e.g. to compare).
    options
        Solve options (default: the problem's).
    data
        The held-out datasets, as for :func:`symcal.solve` (default: the problem's own).
    executor
        Where to run, as for :func:`symcal.solve_fleet`: a scheduler address (a Dask
        cluster, opened and closed here; ``"local"``: an embedded one), a
        :class:`distributed.Client` or a
        :class:`~symcal.solvers.dask_executor.DaskExecutor` of your own (left open), a
        thread executor, or None: the executor of an enclosing ``using`` block, else
        shard after shard in this process.
    workers
        Worker processes of an embedded local cluster (``executor="local"``; default one
        per core).
    progress
        Called with one line per solver iteration (None: silent).
    bars
        Progress bars: one meter counting the shards done.

    Returns
    -------
    Result
        As :func:`symcal.solve` gives it (see the module's docstring for what is not
        computed on the log, said in its notes).

    Raises
    ------
    DataError
        If the shards cannot be read or lack a needed column (named by file).
    SolveError
        If a stage asks for the closed form on constraints that are not linear, or has a
        constraint with a robust loss.
    """
    problem = problem if isinstance(problem, Problem) else load_problem(problem)
    options = options or problem.options
    fit = problem.fit_dataset
    log: ShardedDataset | Dataset
    if isinstance(calibration, ShardedDataset | Dataset):
        log = calibration
    else:
        log = open_shards(fit, calibration, needed_columns(problem))
    if log.n == 0:
        raise DataError(f"{log.source}: no observations")
    held = load_datasets(problem, data, names=[n for n in problem.datasets if n != fit])
    with contextlib.ExitStack() as opened:
        if isinstance(executor, str):
            from symcal.solvers.dask_executor import dask_executor

            executor = opened.enter_context(dask_executor(
                None if executor == "local" else executor, workers))
        elif executor is not None and not hasattr(executor, "remote"):
            from symcal.solvers.dask_executor import DaskExecutor

            executor = DaskExecutor(cast("Client", executor))   # a distributed.Client
        return _solve(problem, log, held, options, executor, progress, bars, calibration,
                      dict(data or {}))


def _solve(problem: Problem, log: ShardedDataset | Dataset, held: dict[str, Dataset],
           options: SolveOptions, executor: Executor | None,
           progress: Callable[[str], None] | None, bars: Bars | None,
           given: Any, data: dict[str, Dataset | str | Path]) -> Result:
    inner = executor or current()
    if inner is None and isinstance(log, ShardedDataset):
        inner = SerialExecutor()
    sample = log.sample(GAUGE_SAMPLE) if isinstance(log, ShardedDataset) else log
    theta0 = _initial(problem, {})
    theta = theta0
    stages: list[StageResult] = []
    with contextlib.ExitStack() as stack:
        m = stack.enter_context(meter(bars, "log", None, "shard"))
        if inner is not None:           # in memory without one: the default policy
            stack.enter_context(using(_Metered(inner, m)))
        for stage in problem.stages:
            m.note(stage.name)
            theta, outcome = _run_stage(problem, stage, log, sample, theta, options, progress)
            stages.append(outcome)
            if not outcome.success:
                break
    last = stages[-1]
    params = parameter_table(
        ParameterResult(p.name, float(theta[i]), float(theta0[i]), p.unit, p.fixed,
                        last.uncertainty.se.get(p.name),
                        last.uncertainty.reason.get(p.name, _no_se_reason(p.name, p.fixed,
                                                                          last)),
                        p.lower, p.upper, p.doc, correlations(last.uncertainty, p.name))
        for i, p in enumerate(problem.parameters))
    notes: list[str] = []
    if isinstance(log, ShardedDataset):
        stats, notes, checks = _log_analysis(problem, log, theta0, theta)
        notes.append(f"the noise floor of the partitioned log '{log.name}' is not computed "
                     "(its residuals are summarised shard by shard)")
        info = DatasetInfo(log.name, log.source, log.n, 0,
                           str(Path(str(given)).resolve()) if isinstance(given, str | Path)
                           else None, log.manifest())
        tests: tuple = ()
    else:
        stats_t, skipped = series_statistics(problem, {log.name: log}, theta0, theta)
        stats, notes = list(stats_t), list(skipped)
        checks = list(implicit_checks(problem, {log.name: log}, theta))
        info = _info(log, None, None)
        tests = ()
    more, skipped = series_statistics(problem, held, theta0, theta)
    notes += [n for n in skipped if n not in notes]
    found, held_tests = floor_tests(problem, held, theta, _fit(problem, held, theta, last))
    stats += [replace(s, noise=found.get((s.dataset, s.name))) for s in more]
    checks += list(implicit_checks(problem, held, theta))
    infos = (info, *(_info(d, data.get(d.name), problem.datasets[d.name].path)
                     for d in held.values()))
    datasets: dict[str, Any] = {log.name: log, **held}
    return Result(problem, theta0, theta, tuple(stages), params, last.identifiability,
                  last.uncertainty, tuple(stats), infos, tuple(notes), tuple(checks),
                  tuple(tests) + tuple(held_tests), _hashes(problem), datasets)
