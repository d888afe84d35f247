"""Opt-in instrumentation of the solver layer: passes over the data and solver iterations.

Code run inside :func:`counting` is counted; outside it nothing is recorded::

    from symcal.solvers.instrument import counting

    with counting() as counts:
        result = symcal.solve("problems/dual_sensor_calibration.yaml")
    counts.passes, counts.linearised_passes, counts.iterations, counts.by_method

A *pass* is one evaluation of the per-observation functions over a whole dataset, chunk
by chunk, by a method of :class:`~symcal.solvers.objective.Objective`:

* a **residual** pass evaluates residuals only (``cost``, ``cost_terms``,
  ``residual_covariance``, ``residuals``);
* a **linearised** pass evaluates residuals and their Jacobian and reduces them to the
  normal equations (``normal_equations``);
* an **R** pass evaluates residuals and Jacobian and reduces them to an R factor
  (``accumulate_r``, a TSQR).

Iterations are IPOPT iterations (``symcal.solvers.nlp.solve_ipopt``), counted like IPOPT's
``iter_count``: the callback IPOPT makes at the start point of each run is reported to
``on_iteration`` as iteration 0 but not counted.  The closed form makes no iterations.

The solver layer reports through :func:`record_pass`, :func:`record_iteration` and
:func:`record_decrement`.  When no :func:`counting` block is active each of these costs
one context-variable lookup and returns, once per pass or iteration (never per chunk or
observation).  What is active is held in a :class:`contextvars.ContextVar`, so a block
counts the code its own thread (or asyncio task) runs, and blocks may be nested: every
active block counts.
"""

from __future__ import annotations

import contextvars
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

import numpy as np

#: The kinds of pass over the data.
PassKind = Literal["residual", "linearised", "r"]

#: ``on_iteration(stage_label, iteration, cost, x)``: called after every IPOPT iteration
#: with the solve's label (the stage name under ``symcal.solve``), the iteration number
#: within that IPOPT run (0 is the start point), the unnormalised cost Σ (g/σ)² and
#: IPOPT's iterate (the free parameters divided by their scales; a copy).
IterationHook = Callable[[str, int, float, np.ndarray], None]


@dataclass
class Counters:
    """What the solver layer did inside one :func:`counting` block.

    Attributes
    ----------
    residual_passes
        Passes evaluating residuals only.
    linearised_passes
        Passes evaluating residuals and Jacobian into the normal equations.
    r_passes
        Passes evaluating residuals and Jacobian into an R factor.
    observations
        Observations evaluated, summed over all passes.
    iterations
        IPOPT iterations (as IPOPT's ``iter_count``, summed over runs).
    by_method
        Passes by the name of the ``Objective`` method that made them.
    decrements
        The Gauss-Newton decrements ``solve_ipopt`` tested for convergence, in order: the
        fraction of the cost a Gauss-Newton step would remove, one per IPOPT iteration
        callback (the start point of each IPOPT run included).
    """

    residual_passes: int = 0
    linearised_passes: int = 0
    r_passes: int = 0
    observations: int = 0
    iterations: int = 0
    by_method: dict[str, int] = field(default_factory=dict)
    decrements: list[float] = field(default_factory=list)

    @property
    def passes(self) -> int:
        """All passes over the data, of every kind."""
        return self.residual_passes + self.linearised_passes + self.r_passes

    def to_dict(self) -> dict[str, Any]:
        """The counters as plain data (JSON-ready), with the total ``passes``."""
        return {**asdict(self), "passes": self.passes}


@dataclass(frozen=True)
class _Sink:
    counters: Counters
    on_iteration: IterationHook | None


_ACTIVE: contextvars.ContextVar[tuple[_Sink, ...]] = contextvars.ContextVar(
    "symcal_instrument", default=())

_FIELD: dict[str, str] = {"residual": "residual_passes", "linearised": "linearised_passes",
                          "r": "r_passes"}


@contextmanager
def counting(on_iteration: IterationHook | None = None) -> Iterator[Counters]:
    """Count the passes over the data and the iterations of code run inside the block.

    Parameters
    ----------
    on_iteration
        Optional ``on_iteration(stage_label, iteration, cost, x)``, called after every
        IPOPT iteration inside the block (see :data:`IterationHook`).  An exception it
        raises stops that IPOPT run: CasADi prints it as a warning and the solve returns
        its last iterate, failed ("stopped by the user").

    Yields
    ------
    Counters
        Updated live while the block runs; final when it ends.
    """
    counters = Counters()
    token = _ACTIVE.set((*_ACTIVE.get(), _Sink(counters, on_iteration)))
    try:
        yield counters
    finally:
        _ACTIVE.reset(token)


def active() -> bool:
    """Whether any :func:`counting` block is active in this context."""
    return bool(_ACTIVE.get())


def record_pass(kind: PassKind, method: str, observations: int) -> None:
    """Record one pass over ``observations`` observations (called by the solver layer).

    Parameters
    ----------
    kind
        ``"residual"``, ``"linearised"`` or ``"r"``.
    method
        Name of the ``Objective`` method making the pass.
    observations
        Observations the pass evaluates.
    """
    sinks = _ACTIVE.get()
    if not sinks:
        return
    attribute = _FIELD[kind]
    for sink in sinks:
        c = sink.counters
        setattr(c, attribute, getattr(c, attribute) + 1)
        c.observations += observations
        c.by_method[method] = c.by_method.get(method, 0) + 1


def record_iteration(label: str, iteration: int, cost: float, x: np.ndarray) -> None:
    """Record one IPOPT iteration callback (called by the solver layer).

    Iteration 0, IPOPT's callback at the start point of a run, is passed to the hooks
    but not counted.  Arguments as for :data:`IterationHook`.
    """
    sinks = _ACTIVE.get()
    if not sinks:
        return
    for sink in sinks:
        if iteration > 0:
            sink.counters.iterations += 1
        if sink.on_iteration is not None:
            sink.on_iteration(label, iteration, cost, np.array(x, dtype=float))


def record_decrement(value: float) -> None:
    """Record a Gauss-Newton decrement tested for convergence (called by the solver layer)."""
    sinks = _ACTIVE.get()
    if not sinks:
        return
    for sink in sinks:
        sink.counters.decrements.append(float(value))
