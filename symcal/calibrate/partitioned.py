"""Calibrate on one huge log: a problem's stages on its fitted dataset kept as shards.

The log stays on disk as shards (:mod:`symcal.data.shards`: partitioned Parquet, NPZ
shards or CSV shards); every pass of the solve over it (cost, normal equations, TSQR,
residual covariance, the analyses' sums) is one task per shard on an executor
(:mod:`symcal.solvers.executor`: Dask workers, threads or this process), each returning a
small reduction, so memory is bounded per worker and the lead never holds the log, nor
anything of its size.  The solvers are the ones of :func:`symcal.solve`, with the same
choice of method per stage, so the estimate equals the one of the same solve on the log
in memory (to rounding: the shards are reduced in another grouping).

It returns a :class:`~symcal.calibrate.result.Result` like :func:`symcal.solve`, every
stage run by :func:`symcal.calibrate.log_stage.run_stage_passes`: its outcome, costs,
conditioning, identifiability and standard errors from the R factor (the sandwich, the
robust losses' and, on time-ordered rows, the Newey-West one included); robust losses by
IRLS and ``propagated`` weights computed in the passes; the gauges, found on a bounded
sample of the log; the outliers (exact medians by passes); the serial correlation; the
before/after statistics of every residual and comparison on the log (the moments of the
shards combined) and on the held-out datasets, which are read into memory as usual; the
noise floors and the global tests of the log (sums over its shards,
:mod:`symcal.analysis.floor_passes`) and of the held-out datasets; the implicit
definitions' checks.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar, cast

import numpy as np

from symcal.analysis.fit import SeriesStats, Spread, series_statistics
from symcal.analysis.floor_passes import floor_tests_passes
from symcal.analysis.implicit import ImplicitCheck, implicit_checks
from symcal.analysis.serial_passes import time_ordered_passes
from symcal.base.cores import thread_count
from symcal.base.errors import DataError
from symcal.base.options import SolveOptions
from symcal.base.progress import Bars, Meter, reporting
from symcal.calibrate.log_stage import run_stage_passes
from symcal.calibrate.result import (
    DatasetInfo,
    ParameterResult,
    Result,
    StageResult,
    parameter_table,
)
from symcal.calibrate.solve import (
    _hashes,
    _info,
    _initial,
    _no_se_reason,
    correlations,
    stage_fit,
)
from symcal.data.dataset import Dataset
from symcal.data.loading import load_datasets, needed_columns
from symcal.data.shards import ShardedDataset, open_shards
from symcal.problem.build import load_problem
from symcal.problem.symbolic import Problem
from symcal.solvers.executor import Executor, SerialExecutor, current, threads, using

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
        Called with each line of progress, as for :func:`symcal.solve`: one per solver
        iteration, and notes (None: no lines).  See :mod:`symcal.base.progress`.
    bars
        Progress bars (:func:`symcal.base.progress.terminal_bars`): one meter counting
        the shards each pass has done, the stage and the latest iteration's line beside
        it (then not passed to ``progress``).  None: no bars.

    Returns
    -------
    Result
        As :func:`symcal.solve` gives it on the same data in memory (see the module).

    Raises
    ------
    DataError
        If the shards cannot be read or lack a needed column (named by file), or hold
        too few observations for the stage's parameters.
    SolveError
        If a stage asks for the closed form on constraints that are not linear.
    SymcalError
        If a constraint is not finite at the start (named with its observation), a
        robust loss meets ``estimated`` or ``propagated`` weighting, or ``propagated``
        weighting lacks a reading's declared noise (as :func:`symcal.solve`).
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
        # one shard per thread, one thread per usable core (the evaluation releases the
        # GIL; the pieces are reduced in their order, so the result is the same)
        workers = min(thread_count(), len(log.shards))
        inner = threads(workers) if workers > 1 else SerialExecutor()
    sample = log.sample(GAUGE_SAMPLE) if isinstance(log, ShardedDataset) else log
    theta0 = _initial(problem, {})
    theta = theta0
    stages: list[StageResult] = []
    with contextlib.ExitStack() as stack:
        report = stack.enter_context(reporting(progress, bars, "log", None, "shard",
                                               counts=False))
        if inner is not None:           # in memory without one: the default policy
            stack.enter_context(using(_Metered(inner, report.meter)))
        ordered = time_ordered_passes(problem, log, sample.columns)
        for stage in problem.stages:
            report.meter.note(stage.name)
            theta, outcome = run_stage_passes(problem, stage, log, sample, theta, options,
                                              report.callback(), ordered)
            stages.append(outcome)
            if not outcome.success:
                break
        last = stages[-1]
        fit = stage_fit(problem, cast("dict[str, Dataset]", {log.name: log, **held}), theta,
                        last)
        found, tests = floor_tests_passes(problem, log, sample, held, theta, fit, ordered,
                                          theta0)
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
        info = DatasetInfo(log.name, log.source, log.n, 0,
                           str(Path(str(given)).resolve()) if isinstance(given, str | Path)
                           else None, log.manifest())
    else:
        stats_t, skipped = series_statistics(problem, {log.name: log}, theta0, theta)
        stats, notes = list(stats_t), list(skipped)
        checks = list(implicit_checks(problem, {log.name: log}, theta))
        info = _info(log, None, None)
    more, skipped = series_statistics(problem, held, theta0, theta)
    notes += [n for n in skipped if n not in notes]
    stats = [replace(s, noise=found.get((s.dataset, s.name))) for s in (*stats, *more)]
    checks += list(implicit_checks(problem, held, theta))
    notes += [_contraction_note(c) for c in checks if not c.contracts]
    infos = (info, *(_info(d, data.get(d.name), problem.datasets[d.name].path)
                     for d in held.values()))
    datasets: dict[str, Any] = {log.name: log, **held}
    return Result(problem, theta0, theta, tuple(stages), params, last.identifiability,
                  last.uncertainty, tuple(stats), infos, tuple(notes), tuple(checks),
                  tests, _hashes(problem), datasets)


def _contraction_note(c: ImplicitCheck) -> str:
    """The note of an implicit definition that is not a contraction (as ``symcal.solve``'s)."""
    return (f"'{c.name}' is not a contraction on dataset '{c.dataset}': max |dF/dx| = "
            f"{c.contraction:.3g} >= 1, so its fixed-point steps do not converge and the "
            "result is not to be trusted (the errors are too large for this form of the "
            "model)")
