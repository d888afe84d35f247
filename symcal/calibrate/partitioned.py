"""Calibrate on one huge log: a problem's stages on a partitioned ``calibration`` dataset.

The log stays on disk as shards (:mod:`symcal.data.shards`: partitioned Parquet, NPZ shards or
CSV shards); every pass over it (cost, normal equations, TSQR, residual covariance) is
one task per shard on an executor (:mod:`symcal.solvers.executor`: Dask workers, threads
or this process), each returning a small reduction, so memory is bounded per worker and
the lead never holds the log.  The solvers are the ones of :func:`symcal.solve` (closed
form, ``lm``, IPOPT with the Gauss-Newton Hessian), with the same choice of method per
stage (``auto``: the closed form when linear, else ``lm`` from the explicit model's
closed-form estimate when there is one) and the same estimated weighting, so the
estimate equals the one of the same solve on the log in memory (to rounding: the shards
are reduced in another grouping).  Robust losses (which reweight every row) are refused.

What it gives is the estimate, each stage's solver outcome and its identifiability and
standard errors from the R factor; the fit statistics and plots of a full
:class:`~symcal.calibrate.result.Result`, which need the residuals in memory, are not computed.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar, cast

import numpy as np

from symcal.analysis.identifiability import analyse
from symcal.base.errors import DataError, SolveError
from symcal.base.linalg import is_singular, numerical_rank, whitening
from symcal.base.options import SolveOptions
from symcal.base.progress import Bars, Meter, meter
from symcal.data.dataset import Dataset
from symcal.data.loading import needed_columns
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


@dataclass(frozen=True)
class PartitionedStage:
    """One stage solved on a partitioned log.

    Attributes
    ----------
    name
        The stage's name.
    output
        The solver's outcome (estimate, R factor, RSS, iterations, message).
    standard_errors
        Free parameter → standard error (None where not identifiable).
    rank
        Identifiable combinations of the free parameters.
    notes
        What was done beyond the plain solve (start, weighting).
    """

    name: str
    output: SolverOutput
    standard_errors: Mapping[str, float | None]
    rank: int
    notes: tuple[str, ...]


@dataclass(frozen=True)
class PartitionedResult:
    """The outcome of :func:`solve_partitioned`.

    Attributes
    ----------
    problem
        The problem solved.
    observations
        Observations in the ``calibration`` log.
    theta0, theta
        The parameters before and after (problem order).
    stages
        Every stage's outcome, in order.
    """

    problem: Problem
    observations: int
    theta0: np.ndarray
    theta: np.ndarray
    stages: tuple[PartitionedStage, ...]

    @property
    def success(self) -> bool:
        """Whether every stage succeeded."""
        return all(s.output.success for s in self.stages)

    @property
    def params(self) -> dict[str, float]:
        """Parameter name → estimated value."""
        return {p.name: float(v) for p, v in zip(self.problem.parameters, self.theta,
                                                 strict=True)}

    def to_dict(self) -> dict[str, Any]:
        """Plain data (JSON-ready)."""
        return {"problem": self.problem.name, "observations": self.observations,
                "success": self.success, "params": self.params,
                "stages": [{"name": s.name, "method": s.output.method,
                            "success": s.output.success, "message": s.output.message,
                            "iterations": s.output.iterations, "rss": s.output.rss,
                            "rank": s.rank, "standard_errors": dict(s.standard_errors),
                            "notes": list(s.notes)} for s in self.stages]}


class _Metered:
    """An executor whose finished pieces advance a progress meter."""

    def __init__(self, inner: Executor, m: Meter) -> None:
        self.inner, self.meter = inner, m
        self.remote = inner.remote

    def map(self, task: Callable[[Any], T], pieces: Iterable[Any]) -> Iterator[T]:
        for value in self.inner.map(task, pieces):
            self.meter.advance()
            yield value


def _run_stage(problem: Problem, stage: Stage, data: Source, theta: np.ndarray,
               options: SolveOptions, progress: Callable[[str], None] | None
               ) -> PartitionedStage:
    free = np.array([p.name in stage.free for p in problem.parameters])
    robust = [n for n in stage.constraints if problem.constraint(n).loss is not None]
    if robust:
        raise SolveError(f"stage '{stage.name}': constraint(s) {', '.join(robust)} have a "
                         "robust loss, which reweights every row; a partitioned log is "
                         "solved with squared losses only")
    objective = Objective(problem, stage.constraints, free)
    method = options.method or stage.method
    out, notes = solve_stage(objective, data, theta, method, progress, stage.name, options)
    if problem.weighting == "propagated":
        notes.append("weighting: 'propagated' weights each observation, which a "
                     "partitioned log does not support yet: solved with equal weights")
    if problem.weighting == "estimated" and len(stage.constraints) > 1 and out.success:
        rank = numerical_rank(out.r_factor, out.rows, objective.scales)
        cov = objective.residual_covariance(data, out.theta, rank)
        if is_singular(cov):
            notes.append("weighting: the constraints' residual covariance is singular; "
                         "kept equal weights")
        else:
            objective = Objective(problem, stage.constraints, free, whitening(cov)[0])
            second, more = solve_stage(objective, data, out.theta, method, progress,
                                         stage.name, options)
            out = SolverOutput(second.theta, second.free, second.method, second.success,
                               second.status, second.message + "; weighted by the "
                               "estimated covariance of the constraints", second.r_factor,
                               second.rows, second.rss, out.iterations + second.iterations,
                               out.seconds + second.seconds)
            notes += more + ["weighting: solved with equal weights, then again whitened by "
                             "the constraints' covariance estimated from those residuals"]
    ident, unc = analyse(out.r_factor, out.rows, out.rss, objective.names, objective.scales,
                         out.theta[objective.index])
    return PartitionedStage(stage.name, out, dict(unc.se), ident.rank, tuple(notes))


def solve_partitioned(
    problem: Problem | str | Path,
    calibration: ShardedDataset | Dataset | str | Path,
    options: SolveOptions | None = None,
    *,
    executor: Executor | str | Any | None = None,
    workers: int | None = None,
    progress: Callable[[str], None] | None = None,
    bars: Bars | None = None,
) -> PartitionedResult:
    """Solve a problem's stages on a ``calibration`` log kept as shards.

    Parameters
    ----------
    problem
        The problem, or its YAML file.
    calibration
        The log: a folder of shards or an opened :class:`~symcal.data.shards.ShardedDataset`
        (an in-memory :class:`~symcal.data.dataset.Dataset` is accepted too, e.g. to compare).
    options
        Solve options (default: the problem's).
    executor
        Where to run, as for :func:`symcal.solve_fleet`: a scheduler address (a Dask
        cluster, opened and closed here), a :class:`distributed.Client` or a
        :class:`~symcal.solvers.dask_executor.DaskExecutor` of your own (left open), a
        thread executor, or None: the executor of an enclosing ``using`` block, else
        shard after shard in this process.
    workers
        Unused unless ``executor`` is ``"local"``: the worker processes of an embedded
        local Dask cluster (default one per core).
    progress
        Called with one line per IPOPT iteration (None: silent).
    bars
        Progress bars (:mod:`symcal.base.progress`): one meter counting the shards done.

    Returns
    -------
    PartitionedResult

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
    data: Source
    if isinstance(calibration, ShardedDataset | Dataset):
        data = calibration
    else:
        data = open_shards(problem.fit_dataset, calibration, needed_columns(problem))
    if data.n == 0:
        raise DataError(f"{data.source}: no observations")
    theta0 = np.array([p.value for p in problem.parameters], dtype=float)
    theta = theta0.copy()
    with contextlib.ExitStack() as opened:
        if isinstance(executor, str):
            from symcal.solvers.dask_executor import dask_executor

            executor = opened.enter_context(dask_executor(
                None if executor == "local" else executor, workers))
        elif executor is not None and not hasattr(executor, "remote"):
            from symcal.solvers.dask_executor import DaskExecutor

            executor = DaskExecutor(cast("Client", executor))   # a distributed.Client
        return _solve(problem, data, options, theta0, theta, executor, progress, bars)


def _solve(problem: Problem, data: Source, options: SolveOptions, theta0: np.ndarray,
           theta: np.ndarray, executor: Executor | None,
           progress: Callable[[str], None] | None, bars: Bars | None) -> PartitionedResult:
    inner = executor or current()
    if inner is None and isinstance(data, ShardedDataset):
        inner = SerialExecutor()
    stages: list[PartitionedStage] = []
    with contextlib.ExitStack() as stack:
        m = stack.enter_context(meter(bars, "log", None, "shard"))
        if inner is not None:           # in memory without one: the default policy
            stack.enter_context(using(_Metered(inner, m)))
        for stage in problem.stages:
            m.note(stage.name)
            outcome = _run_stage(problem, stage, data, theta, options, progress)
            theta = outcome.output.theta
            stages.append(outcome)
    return PartitionedResult(problem, data.n, theta0, theta, tuple(stages))
