"""The public entry points: load a problem's data, solve it, and analyse the estimate."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from symcal.analysis.fit import series_statistics
from symcal.analysis.identifiability import analyse
from symcal.data import Dataset, load_dataset
from symcal.errors import DataError, SolveError
from symcal.problem import Problem, load_problem
from symcal.result import DatasetInfo, ParameterResult, Result
from symcal.solve.base import SolverOutput
from symcal.solve.linear import nonlinear_constraints, solve_linear
from symcal.spec.yamlio import display_path
from symcal.suggest import did_you_mean


def needed_columns(problem: Problem) -> list[str]:
    """Columns every dataset must have: those the constraints read."""
    needed: list[str] = []
    for c in problem.constraints:
        needed += [col for col in problem.columns_of(c.sx) if col not in needed]
    return needed


def load_datasets(
    problem: Problem,
    overrides: Mapping[str, str | Path] | None = None,
    drop_invalid: bool = False,
    names: list[str] | None = None,
) -> dict[str, Dataset]:
    """Load every dataset of ``problem``, replacing those named in ``overrides``.

    Parameters
    ----------
    problem
        The problem whose ``datasets`` section says where data comes from.
    overrides
        Dataset name → CSV/NPZ path (``symcal solve --data NAME=PATH``).
    drop_invalid
        Drop rows with NaN/inf in a needed column instead of refusing the data.
    names
        Load only these datasets (default: all of them).

    Raises
    ------
    DataError
        Unknown dataset name, missing file or column, malformed cells, invalid rows.
    """
    overrides = dict(overrides or {})
    for name in overrides:
        if name not in problem.datasets:
            raise DataError(f"--data {name}=...: the problem has no dataset '{name}'"
                            f"{did_you_mean(name, problem.datasets)}; it has: "
                            f"{', '.join(problem.datasets)}")
    needed = needed_columns(problem)
    wanted = list(problem.datasets) if names is None else names
    return {name: load_dataset(problem.datasets[name], needed, overrides.get(name), drop_invalid)
            for name in wanted}


def _solve_numerics(problem: Problem, data: Dataset, theta0: np.ndarray,
                    free: np.ndarray) -> SolverOutput:
    if not free.any():
        raise SolveError("every parameter is fixed: there is nothing to calibrate")
    nonlinear = nonlinear_constraints(problem, free)
    if nonlinear:
        raise SolveError(
            f"constraint(s) {', '.join(nonlinear)} are not linear in the free parameters; "
            "this version of symcal solves only problems that are linear in their parameters"
        )
    return solve_linear(problem, data, theta0, free)


def solve(
    problem: Problem | str | Path,
    data: Mapping[str, Dataset | str | Path] | None = None,
    drop_invalid: bool = False,
) -> Result:
    """Calibrate: estimate the free parameters on the ``calibration`` dataset.

    Parameters
    ----------
    problem
        A :class:`~symcal.problem.Problem` or the path of a problem file.
    data
        Datasets by name, as :class:`~symcal.data.Dataset` objects or file paths; those not
        given come from the problem's ``datasets`` section.
    drop_invalid
        Drop rows with NaN/inf instead of refusing them.

    Returns
    -------
    Result
        Frozen: estimates with standard errors, identifiability (rank, condition number,
        named null space), and before/after statistics on every dataset.
    """
    if not isinstance(problem, Problem):
        problem = load_problem(problem)
    data = dict(data or {})
    given = {k: v for k, v in data.items() if isinstance(v, Dataset)}
    paths = {k: v for k, v in data.items() if not isinstance(v, Dataset)}
    unknown = [k for k in given if k not in problem.datasets]
    if unknown:
        raise DataError(f"the problem has no dataset '{unknown[0]}'"
                        f"{did_you_mean(unknown[0], problem.datasets)}")
    loaded = load_datasets(problem, paths, drop_invalid,
                           [k for k in problem.datasets if k not in given])
    datasets = {k: given[k] if k in given else loaded[k] for k in problem.datasets}
    theta0 = np.array([p.value for p in problem.parameters])
    free = np.array(problem.free)
    out = _solve_numerics(problem, datasets["calibration"], theta0, free)
    return _result(problem, datasets, theta0, out)


def _result(problem: Problem, datasets: dict[str, Dataset], theta0: np.ndarray,
            out: SolverOutput) -> Result:
    idx = np.flatnonzero(out.free)
    free_names = tuple(problem.parameters[i].name for i in idx)
    scales = np.array([problem.parameters[i].scale for i in idx])
    ident, unc = analyse(out.r_factor, out.rows, out.rss, free_names, scales, out.theta[idx])
    params = tuple(
        ParameterResult(p.name, float(out.theta[i]), p.value, p.unit, p.fixed,
                        unc.se.get(p.name), unc.reason.get(p.name, "fixed" if p.fixed else None),
                        p.lower, p.upper, p.doc)
        for i, p in enumerate(problem.parameters)
    )
    stats, notes = series_statistics(problem, datasets, theta0, out.theta)
    notes = list(notes)
    for p in params:
        if not p.fixed and not p.lower <= p.value <= p.upper:
            notes.append(f"parameter '{p.name}' = {p.value:.6g} lies outside its bounds "
                         f"[{p.lower:g}, {p.upper:g}]: the closed form does not apply bounds")
    infos = tuple(DatasetInfo(d.name, d.source, d.n, d.dropped) for d in datasets.values())
    return Result(problem.name, display_path(problem.path), out.method, out.success,
                  out.status, out.message, out.iterations, out.seconds, params, ident, unc,
                  stats, infos, tuple(notes))
