"""The public entry point: solve a problem's study stage by stage, then analyse."""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from symcal.analysis.fit import series_statistics
from symcal.analysis.floors import FloorOutcome, fit_chi2, floor_outcome, time_ordered
from symcal.analysis.identifiability import Uncertainty
from symcal.analysis.implicit import implicit_checks
from symcal.analysis.outliers import Outliers, find_outliers
from symcal.analysis.row_noise import Fit, inverse_sqrt_rows, row_covariances
from symcal.analysis.serial import SerialCorrelation, bandwidth, detect, hac_meat
from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import DataError, SolveError, SymcalError
from symcal.base.linalg import information_coordinates, sqrt_psd, whitening
from symcal.base.options import METHODS, SolveOptions
from symcal.base.progress import Bars, reporting
from symcal.base.units import DISPLAY_UNITS
from symcal.calibrate.result import (
    DatasetInfo,
    ParameterResult,
    Result,
    StageResult,
    file_hashes,
    parameter_table,
)
from symcal.calibrate.stage_run import Inner, run_stage_on
from symcal.data.dataset import Dataset
from symcal.data.loading import load_datasets
from symcal.problem.build import load_problem
from symcal.problem.symbolic import Problem, Stage
from symcal.solvers.base import SolverOutput
from symcal.solvers.executor import blas_limited
from symcal.solvers.objective import Objective
from symcal.solvers.robust import RobustOutput, RowLosses, sandwich_meat, solve_robust

Progress = Callable[[str], None] | None


def _outliers(objective: Objective, data: Dataset, theta: np.ndarray,
              weights: np.ndarray | None, losses: RowLosses | None,
              solve_again: Callable[[Objective], SolverOutput] | None = None,
              weighted: Objective | None = None) -> Outliers | None:
    """The observations the stage's fit treats as outliers (None where a residual is not
    finite at the estimate); ``solve_again`` solves the stage's objective with per-row
    weights, for the outliers' noise measured without them.  ``weighted``: the fit's
    objective where it is weighted by the propagated covariances (its rows' ``C_i^-½``):
    the residuals are then standardized by each row's propagated standard deviation at
    the estimate, and the refit keeps those weights."""
    problem = objective.problem
    g = objective.residuals(data, theta)
    if not np.all(np.isfinite(g)):
        return None
    quantities = [problem.constraint(n) for n in objective.constraints]
    time_col = next((c for c, spec in problem.column_specs.items()
                     if spec.role == "time" and c in data.columns), None)
    sd = None
    if weighted is not None:
        cov = row_covariances(problem, objective.constraints, data, theta)
        sd = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    return find_outliers(
        data.name, objective.constraints, tuple(q.unit for q in quantities),
        np.array([q.sigma / DISPLAY_UNITS[q.unit] for q in quantities]), g, weights,
        "squared" if losses is None else "; ".join(losses.texts),
        None if time_col is None else np.asarray(data.columns[time_col], dtype=float),
        None if solve_again is None else _refit(objective, data, solve_again, weighted),
        sd)


def _refit(objective: Objective, data: Dataset,
           solve_again: Callable[[Objective], SolverOutput],
           weighted: Objective | None = None) -> Callable[[np.ndarray], np.ndarray | None]:
    """The residual rows of the stage solved again with some residuals set aside (the
    rows of ``weighted``'s ``C_i^-½`` of those residuals set to 0 where given)."""
    base = None if weighted is None else weighted.row_weights

    def refit(aside: np.ndarray) -> np.ndarray | None:
        keep = (~aside).astype(float)
        factors = keep if base is None else keep[:, :, None] * base
        out = solve_again(objective.with_row_weights(factors))
        return objective.residuals(data, out.theta) if out.success else None

    return refit


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


@blas_limited
def run_stage(
    problem: Problem, stage: Stage, data: Dataset, theta: np.ndarray,
    options: SolveOptions | None = None, progress: Progress = None,
) -> tuple[np.ndarray, StageResult]:
    """Solve one stage from ``theta`` and analyse its outcome
    (:func:`~symcal.calibrate.stage_run.run_stage_on`, the data in memory).

    Returns
    -------
    (theta, StageResult)
        The new parameter vector and what happened.
    """
    return run_stage_on(InMemory(data), problem, stage, theta, options or problem.options,
                        progress)


@dataclass(frozen=True)
class InMemory:
    """A stage's steps on a dataset in memory (a
    :class:`~symcal.calibrate.stage_run.StageData`): arrays of its N rows."""

    data: Dataset

    @property
    def sample(self) -> Dataset:
        """The gauges are found and confirmed on the dataset itself."""
        return self.data

    def check_finite(self, objective: Objective, theta: np.ndarray) -> None:
        """Refuse constraints that are inf or NaN at the start, naming where."""
        _check_finite(objective, self.data, theta)

    def robust(self, objective: Objective, theta: np.ndarray, losses: RowLosses,
               inner: Inner, progress: Progress, label: str) -> RobustOutput[np.ndarray]:
        """IRLS rounds, the weights an ``N × n_g`` array."""
        return solve_robust(objective, self.data, theta, losses, inner, progress, label)

    def robust_meat(self, objective: Objective, theta: np.ndarray,
                    robust: RobustOutput[np.ndarray], losses: RowLosses,
                    rank: int) -> np.ndarray:
        """The robust sandwich's meat from the final weights."""
        return sandwich_meat(objective, self.data, theta, robust.weights, rank)

    def propagation(self, objective: Objective) -> _Propagated:
        """Each observation's ``C_i^-½``, an ``N × n_g × n_g`` array."""
        return _Propagated(objective, self.data)

    def serial(self, objective: Objective, out: SolverOutput
               ) -> tuple[SerialCorrelation | None, np.ndarray | None]:
        """On time-ordered rows: :func:`_serial`."""
        if not time_ordered(objective.problem, self.data):
            return None, None
        return _serial(objective, self.data, out)

    def outliers(self, objective: Objective, theta: np.ndarray,
                 robust: RobustOutput[np.ndarray] | None, losses: RowLosses | None,
                 solve_again: Callable[[Objective], SolverOutput],
                 weighted: Objective | None = None) -> Outliers | None:
        """:func:`_outliers`, weighted by the robust solve's final weights."""
        return _outliers(objective, self.data, theta, None if robust is None
                         else robust.weights, losses, solve_again, weighted)


@dataclass(frozen=True)
class _Propagated:
    """The propagated weights of ``objective`` on a dataset in memory (a
    :class:`~symcal.calibrate.stage_run.Propagation`): each observation's ``C_i^-½``."""

    objective: Objective
    data: Dataset

    def weights(self, theta: np.ndarray, before: np.ndarray | None
                ) -> tuple[np.ndarray, int, float]:
        """``C_i^-½`` at ``theta``, the observations where ``C_i`` is singular, the
        largest relative change from ``before``."""
        cov = row_covariances(self.objective.problem, self.objective.constraints, self.data,
                              theta)
        t, singular = inverse_sqrt_rows(cov)
        if singular or before is None:
            return t, singular, 0.0
        change = float(np.max(np.linalg.norm(t - before, axis=(1, 2))
                              / np.maximum(np.linalg.norm(before, axis=(1, 2)), 1e-300)))
        return t, singular, change

    def weighted(self, weights: np.ndarray) -> Objective:
        """The objective with the rows' ``C_i^-½``."""
        return self.objective.with_row_weights(weights)

    def floor(self, theta: np.ndarray, weights: np.ndarray, there: bool) -> np.ndarray:
        """The noise floor at ``theta``, from the covariances there."""
        cov = row_covariances(self.objective.problem, self.objective.constraints, self.data,
                              theta)
        return np.sqrt(np.mean(np.diagonal(cov, axis1=1, axis2=2), axis=0))


def _serial(objective: Objective, data: Dataset, out: SolverOutput
            ) -> tuple[SerialCorrelation, np.ndarray | None]:
    """Serial correlation of the stage's weighted residuals on time-ordered rows, and
    where it is found the HAC meat (``M`` with ``MᵀM`` the Newey-West sum of the scores,
    scaled by rows/(rows - rank)) for its standard errors."""
    found = detect(objective.constraints, objective.residuals(data, out.theta))
    if not found.detected:
        return found, None
    lags = bandwidth(max(found.rho, key=abs), data.n)
    to, back = information_coordinates(out.r_factor, out.rows, objective.scales)
    rank = to.shape[1]                # the identifiable parameters, by the same SVD
    meat = hac_meat((s @ to for s in objective.score_chunks(data, out.theta)), lags,
                    to.shape[1])
    meat *= out.rows / max(out.rows - rank, 1)
    return replace(found, lags=lags), sqrt_psd(meat).T @ back


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
    return _solved(problem, _in_memory(problem, data, drop_invalid), data or {}, options,
                   initial or {}, progress, bars, floors=True)


@blas_limited
def solve_without_floors(problem: Problem, data: Mapping[str, Dataset],
                         initial: Mapping[str, float]) -> Result:
    """:func:`solve` with the problem's own options, its noise floors left out until
    :func:`with_floors` adds them: the statistics carry no floor and ``floor_tests`` at
    most the fitted dataset's χ² without its band (what :attr:`Result.rss` reads where
    the weights are propagated; ``at_floor`` is None).  For a loop that solves many
    candidate models and keeps few (``improve``): its decisions read the estimate, its
    statistics, information criteria and standard errors, and the floors' passes over
    every dataset are paid for the kept one only."""
    return _solved(problem, _in_memory(problem, data, False), data, problem.options,
                   initial, None, None, floors=False)


def _in_memory(problem: Problem, data: Mapping[str, Dataset | str | Path] | None,
               drop_invalid: bool) -> dict[str, Dataset]:
    """The problem's datasets, ``data`` replacing its own; refused where one is a folder
    of shards."""
    datasets = load_datasets(problem, data, drop_invalid)
    for name, ds in datasets.items():
        if not isinstance(ds, Dataset):
            raise DataError(f"dataset '{name}' ({ds.source}) is a folder of shards: solve a log "
                            "kept as shards with symcal.solve_partitioned (symcal solve "
                            "--data NAME=FOLDER does so by itself), and give held-out "
                            "datasets as files")
    return datasets


@blas_limited
def with_floors(result: Result) -> Result:
    """``result`` of :func:`solve_without_floors` with its noise floors: bit for bit what
    :func:`solve` gives on the same problem, data and start (the statistics are the same
    expressions evaluated once; only their floors are added)."""
    problem, datasets, theta = result.problem, dict(result.data), result.theta
    floors = floor_outcome(problem, datasets, theta,
                           stage_fit(problem, datasets, theta, result.stages[-1]), result.theta0)
    stats = tuple(replace(s, noise=floors.tests.get((s.dataset, s.name)))
                  for s in result.statistics)
    return replace(result, statistics=stats, floor_tests=floors.joint)


def _solved(problem: Problem, datasets: dict[str, Dataset],
            given: Mapping[str, Dataset | str | Path], options: SolveOptions,
            initial: Mapping[str, float], progress: Progress, bars: Bars | None,
            floors: bool) -> Result:
    """Every stage in turn from ``initial``, then the analysis (``floors``: with the
    noise floors)."""
    theta0 = _initial(problem, initial)
    theta = theta0
    stages: list[StageResult] = []
    with reporting(progress, bars, "solve", None, "it") as report:
        for stage in problem.stages:
            theta, result = run_stage(problem, stage, datasets[problem.fit_dataset], theta,
                                      options, report.callback())
            stages.append(result)
            if not result.success:
                break
    return _result(problem, datasets, given, theta0, theta, tuple(stages), floors)


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
            theta: np.ndarray, stages: tuple[StageResult, ...], all_floors: bool = True
            ) -> Result:
    last = stages[-1]
    params = parameter_table(
        ParameterResult(p.name, float(theta[i]), float(theta0[i]), p.unit, p.fixed,
                        last.uncertainty.se.get(p.name),
                        last.uncertainty.reason.get(p.name, _no_se_reason(p.name, p.fixed,
                                                                          last)),
                        p.lower, p.upper, p.doc, correlations(last.uncertainty, p.name))
        for i, p in enumerate(problem.parameters)
    )
    fit = stage_fit(problem, datasets, theta, last)
    floors = floor_outcome(problem, datasets, theta, fit, theta0) if all_floors \
        else _fit_test(problem, datasets, theta, fit, theta0)
    found, tests = floors.tests, floors.joint
    stats, skipped = series_statistics(problem, datasets, theta0, theta, floors.residuals)
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


def _fit_test(problem: Problem, datasets: dict[str, Dataset], theta: np.ndarray, fit: Fit,
              theta0: np.ndarray) -> FloorOutcome:
    """The floors as far as a solve without them needs: none, or where the weights are
    propagated, the fitted dataset's χ² (:attr:`Result.rss`; all the floors where one
    pass cannot tell it, :func:`~symcal.analysis.floors.fit_chi2`)."""
    if problem.weighting != "propagated" or fit.dataset not in datasets:
        return FloorOutcome({}, (), {})
    test = fit_chi2(problem, datasets[fit.dataset], theta, fit)
    if test is None:
        return floor_outcome(problem, datasets, theta, fit, theta0)
    return FloorOutcome({}, (test,), {})


def _hashes(problem: Problem) -> dict[str, str] | None:
    """The problem's files' hashes at solve time (None where a file cannot be read: the
    document then hashes them when it is written, and says why it cannot)."""
    try:
        return file_hashes(problem)
    except SymcalError:
        return None


def stage_fit(problem: Problem, datasets: Mapping[str, Dataset], theta: np.ndarray,
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
