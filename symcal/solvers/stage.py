"""Which solver runs a stage: the one home of the method choice.

``auto`` solves a stage in closed form when its constraints are linear in its free
parameters, else with ``lm`` (an implicit problem started from its explicit twin's closed
form); IPOPT runs when asked and when a closed-form estimate lands outside a parameter's
bounds.  :func:`symcal.solve` and :func:`symcal.solve_partitioned` both choose here, on a
dataset in memory or on a partitioned log (any :class:`~symcal.solvers.objective.Source`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, cast

import numpy as np

from symcal.base.errors import SolveError
from symcal.base.options import SolveOptions
from symcal.solvers.base import SolverOutput
from symcal.solvers.executor import blas_limit
from symcal.solvers.linear import solve_linear
from symcal.solvers.nlp import solve_ipopt
from symcal.solvers.objective import Objective, Source
from symcal.solvers.trust_region import solve_trust_region

Progress = Callable[[str], None] | None


def out_of_bounds(objective: Objective, theta: np.ndarray) -> list[str]:
    """Free parameters of ``objective`` outside their bounds at ``theta``."""
    return [p.name for p, v, f in zip(objective.problem.parameters, theta, objective.free,
                                      strict=True)
            if f and not p.lower <= v <= p.upper]


def ipopt(objective: Objective, data: Source, theta: np.ndarray, progress: Progress,
          label: str, options: SolveOptions) -> SolverOutput:
    """The IPOPT path with the options' iteration limit, tolerance and IPOPT options."""
    return solve_ipopt(objective, data, theta, progress, options.max_iter, options.tol,
                       label=label, extra=options.ipopt)


def lm(objective: Objective, data: Source, theta: np.ndarray, progress: Progress,
       label: str, options: SolveOptions) -> SolverOutput:
    """The trust-region Levenberg–Marquardt path (it reads the data through passes only)."""
    return solve_trust_region(objective, cast(Any, data), theta, progress, options.max_iter,
                              label=label)


def solve_stage(
    objective: Objective, data: Source, theta: np.ndarray, method: str,
    progress: Progress, label: str, options: SolveOptions,
) -> tuple[SolverOutput, list[str]]:
    """Solve one stage with ``method`` (``auto``, ``linear``, ``lm`` or ``ipopt``).

    Parameters
    ----------
    objective
        The stage's constraints and free parameters.
    data
        A dataset in memory or a partitioned log.
    theta
        Initial values of all parameters.
    method
        The stage's method (see the module).
    progress
        Called with one line per iteration (None: silent).
    label
        The stage's name, for messages.
    options
        Iteration limit, tolerance, IPOPT options.

    Returns
    -------
    tuple
        The solver's output and the notes on the path taken.

    Raises
    ------
    SolveError
        If ``linear`` is asked for a stage that is not linear in its free parameters.
    """
    with blas_limit():
        return _solve_stage(objective, data, theta, method, progress, label, options)


def _solve_stage(
    objective: Objective, data: Source, theta: np.ndarray, method: str,
    progress: Progress, label: str, options: SolveOptions,
) -> tuple[SolverOutput, list[str]]:
    nonlinear = objective.nonlinear()
    notes: list[str] = []
    if method == "linear" and nonlinear:
        raise SolveError(f"stage '{label}': method 'linear' was asked for, but constraint(s) "
                         f"{', '.join(nonlinear)} are not linear in its free parameters")
    if nonlinear and method == "auto":
        twin = objective.problem.explicit
        if twin is not None:
            explicit = Objective(twin, objective.constraints, objective.free)
            if not explicit.nonlinear():
                theta = solve_linear(explicit, data, theta).theta
                notes.append("started from the explicit model's closed-form estimate")
        method = "lm"
    if method == "lm":
        return lm(objective, data, theta, progress, label, options), notes
    if method == "ipopt":
        return ipopt(objective, data, theta, progress, label, options), notes
    out = solve_linear(objective, data, theta)
    outside = out_of_bounds(objective, out.theta)
    if outside and method == "auto":
        notes.append(f"the closed-form estimate put {', '.join(outside)} outside its bounds; "
                     "solved again with IPOPT, which respects them")
        return ipopt(objective, data, theta, progress, label, options), notes
    if outside:
        notes.append(f"{', '.join(outside)} lie(s) outside the bounds: the closed form "
                     "does not apply bounds")
    return out, notes
