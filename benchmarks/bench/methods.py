"""The methods compared, each as ``theta0 -> Outcome`` on one problem's data.

symcal's passes over the data and its IPOPT iterations are counted with
:func:`symcal.solvers.instrument.counting`, symcal's public instrumentation hook; the
peers count their residual evaluations themselves (``bench.peers``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

from . import peers
from .problems import Columns, residual, single_stage_problem


@dataclasses.dataclass(frozen=True)
class Outcome:
    """What one run of a method gives.

    Attributes
    ----------
    theta
        The estimate (all parameters).
    iterations
        Solver iterations (None when the method was stopped before it could say).
    message
        The method's own account of how it ended.
    evaluations
        Passes over the data (symcal) or residual evaluations (peers).
    passes_by
        symcal only: passes by ``Objective`` method.
    decrements
        symcal's IPOPT path only: the Gauss-Newton decrements it tested.
    """

    theta: np.ndarray
    iterations: int | None
    message: str
    evaluations: int
    passes_by: dict[str, int] | None = None
    decrements: list[float] | None = None


Method = Callable[[np.ndarray], Outcome]


def forget_r(problem: Any) -> None:
    """Drop the R factor and the residuals each objective of ``problem`` keeps from its
    last passes, so that a repeated timed solve from the same start reduces its own (the
    linear stage would otherwise be one lookup from the second call on).  The gauge
    analysis an identical earlier solve made is kept: reusing it is what a repeated solve
    does."""
    from symcal.solvers.objective import _BUILT

    for built in _BUILT.get(problem, {}).values():
        for kept in ("last_r", "last_g"):
            last = getattr(built, kept, None)
            if isinstance(last, list):
                last.clear()


def symcal_solver(problem: str, cols: Columns, method: str = "auto") -> Method:
    """symcal's default path for the single stage: ``Objective`` and the method choice of
    ``solve()`` (``symcal.solvers.stage``: closed form when linear, else ``lm``), or the
    method given (``ipopt``: the IPOPT row)."""
    from symcal.base.options import SolveOptions
    from symcal.data.dataset import make_dataset
    from symcal.data.loading import needed_columns
    from symcal.solvers.instrument import counting
    from symcal.solvers.objective import Objective
    from symcal.solvers.stage import solve_stage

    prob = single_stage_problem(problem)
    stage = prob.stages[0]
    data = make_dataset("calibration", "benchmark", cols, needed_columns(prob))
    free = np.array([p.name in stage.free for p in prob.parameters])

    def run(theta0: np.ndarray) -> Outcome:
        forget_r(prob)
        with counting() as counts:
            objective = Objective(prob, stage.constraints, free)
            out, _ = solve_stage(objective, data, theta0, method, None, stage.name,
                                 SolveOptions())
        return Outcome(out.theta, out.iterations, f"{out.method}: {out.message}",
                       counts.passes, dict(counts.by_method), list(counts.decrements))

    return run


def symcal_analysis(problem: str, cols: Columns) -> Method:
    """``symcal.calibrate.solve.run_stage``: the solve plus the stage's analysis."""
    from symcal.calibrate.solve import run_stage
    from symcal.data.dataset import make_dataset
    from symcal.data.loading import needed_columns
    from symcal.solvers.instrument import counting

    prob = single_stage_problem(problem)
    data = make_dataset("calibration", "benchmark", cols, needed_columns(prob))

    def run(theta0: np.ndarray) -> Outcome:
        forget_r(prob)
        with counting() as counts:
            theta, result = run_stage(prob, prob.stages[0], data, theta0)
        return Outcome(theta, result.iterations, f"{result.method}: {result.message}",
                       counts.passes, dict(counts.by_method))

    return run


def symcal_public(problem: str, cols: Columns) -> Method:
    """``symcal.solve``, the public API, on the single-stage problem from the common
    start: the whole solve a user calls (gauges, the solve, the stage's analysis, the
    result's statistics), the data (calibration and fly-by) given as ``Dataset``s."""
    import symcal
    from symcal.data.dataset import make_dataset
    from symcal.data.loading import load_datasets, needed_columns
    from symcal.solvers.instrument import counting

    prob = single_stage_problem(problem)
    data = make_dataset("calibration", "benchmark", cols, needed_columns(prob))
    # the problem's other datasets (its fly-by), simulated once here as a user's files
    # would be read once: the timed call solves, it does not simulate
    given = {**load_datasets(prob, {"calibration": data}), "calibration": data}
    names = prob.parameter_names

    def run(theta0: np.ndarray) -> Outcome:
        forget_r(prob)
        with counting() as counts:
            result = symcal.solve(prob, given,
                                  initial=dict(zip(names, theta0, strict=True)))
        stage = result.stages[-1]
        return Outcome(np.asarray(result.theta), stage.iterations,
                       f"{stage.method}: {stage.message}", counts.passes,
                       dict(counts.by_method))

    return run


def exact_peer(problem: str, name: str, cols: Columns) -> Method:
    """An exact-Jacobian peer of ``bench.exact``."""
    from . import exact

    run_peer = exact.runner(problem, name, cols)

    def run(theta0: np.ndarray) -> Outcome:
        res = run_peer(theta0)
        return Outcome(res.theta, res.iterations, res.message, res.evaluations)

    return run


def peer(problem: str, method: str, cols: Columns, cap: float) -> Method:
    """A peer of ``bench.peers``: the numpy floor, least_squares or BFGS, stopped at
    ``cap`` seconds."""
    fn = residual(problem)

    def run(theta0: np.ndarray) -> Outcome:
        if method == "floor":
            res = peers.numpy_floor(theta0, cols)
        elif method == "least_squares":
            res = peers.least_squares(fn, theta0, cols, max_seconds=cap)
        else:
            res = peers.bfgs(fn, theta0, cols, max_seconds=cap)
        return Outcome(res.theta, res.iterations, res.message, res.evaluations)

    return run


def serial(run: Method) -> Method:
    """``run`` with symcal's passes on one thread and interpreted (``SYMCAL_THREADS=1``,
    ``SYMCAL_JIT=off``): symcal's default path as it was before issue 16."""
    import os

    def wrapped(theta0: np.ndarray) -> Outcome:
        saved = {k: os.environ.get(k) for k in ("SYMCAL_THREADS", "SYMCAL_JIT")}
        os.environ.update(SYMCAL_THREADS="1", SYMCAL_JIT="off")
        try:
            return run(theta0)
        finally:
            for key, value in saved.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value

    return wrapped


def method(problem: str, name: str, cols: Columns, cap: float) -> Method:
    """The method ``name`` (a key of ``bench.config.LABELS``) on ``problem``'s data."""
    if name == "symcal":
        return symcal_solver(problem, cols)
    if name == "symcal_serial":
        return serial(symcal_solver(problem, cols))
    if name == "symcal_ipopt":
        return symcal_solver(problem, cols, "ipopt")
    if name == "symcal_analysis":
        return symcal_analysis(problem, cols)
    if name == "symcal_public":
        return symcal_public(problem, cols)
    from .config import EXACT_PEERS

    if name in EXACT_PEERS:
        return exact_peer(problem, name, cols)
    return peer(problem, name, cols, cap)
