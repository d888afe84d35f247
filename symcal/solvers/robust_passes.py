"""Robust losses by IRLS in passes: :func:`symcal.solvers.robust.solve_robust` on a log
kept as shards, its weights never held.

The rounds are those of :mod:`symcal.solvers.robust`, the same tests in the same order:
each round freezes the IRLS weights ``ρ'(z)`` at the current iterate, solves the
reweighted least-squares problem with an existing path, and stops on the same
first-order test.  Only where the weights live differs: in memory they are an
``N × n_g`` array, here a :class:`~symcal.solvers.weighed.LossWeights` that every pass
evaluates from the rows it reads at the frozen point (one more residual evaluation per
chunk).  The robust cost and the finiteness of the weights are one pass
(:class:`~symcal.solvers.weighed.LossCost`).  The sandwich's meat is the same
``Σ_i J_iᵀ S_ψ J_i``, ``S_ψ`` from the Gram matrix of ``ψ = w g`` (a pass of weights to
the power one).  So the estimate and its standard errors equal the in-memory ones to
rounding (the passes reduce in another grouping).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from symcal.base.linalg import sqrt_psd
from symcal.solvers.base import SolverOutput
from symcal.solvers.objective import Objective, Source
from symcal.solvers.robust import (
    DECREMENT,
    MAX_ROUNDS,
    ROUNDING_DECREMENT,
    STILL,
    RowLosses,
    _decrement,
)
from symcal.solvers.weighed import LossCost, LossWeights, Weighed, loss_weights, map_pieces


def robust_cost(objective: Objective, data: Source, theta: np.ndarray,
                losses: RowLosses) -> tuple[float, bool]:
    """The robust cost ``Σ c² ρ((g/c)²)`` at ``theta`` and whether every IRLS weight
    there is finite: one residual pass."""
    task = LossCost(loss_weights(objective, theta, losses, observations=data.n).rows, losses,
                    tuple(objective.problem.columns))
    parts = map_pieces(task, data, "robust_cost", executor=objective.executor)
    return float(sum(c for c, _ in parts)), all(f for _, f in parts)


@dataclass(frozen=True, eq=False)
class RobustPasses:
    """A robust solve on passes: the solver output at the final iterate (``r_factor`` and
    ``rss`` of the reweighted rows there) and the weigher of its final weights (the
    IRLS weights at ``output.theta``, power ½)."""

    output: SolverOutput
    weights: LossWeights
    cost: float
    rounds: int


def solve_robust_passes(
    objective: Objective,
    data: Source,
    theta0: np.ndarray,
    losses: RowLosses,
    inner: Callable[[Objective, np.ndarray], SolverOutput],
    progress: Callable[[str], None] | None = None,
    label: str = "robust",
    max_rounds: int = MAX_ROUNDS,
) -> RobustPasses:
    """Minimise the robust cost by IRLS from ``theta0``, the weights computed in the passes.

    Parameters and the outcome as for :func:`symcal.solvers.robust.solve_robust`, on a
    dataset in memory or a log kept as shards; ``inner`` solves the reweighted objective
    (a :class:`~symcal.solvers.weighed.Weighed`) from a parameter vector.
    """
    start = time.perf_counter()
    scales = objective.scales
    theta = np.array(theta0, dtype=float)
    best: tuple[float, np.ndarray] | None = None
    iterations, rounds = 0, 0
    method, inner_words = "linear", ""
    ok, status, words = False, "iteration_limit", ""
    moved = np.inf
    while True:
        cost, finite = robust_cost(objective, data, theta, losses)
        if not finite or not np.isfinite(cost):
            status, words = "invalid_number", "a residual is NaN or inf"
            break
        if best is None or cost < best[0]:
            best = (cost, theta.copy())
        weighted = Weighed.of(objective, loss_weights(objective, theta, losses,
                                                      observations=data.n))
        r, c, tail, rows = weighted.accumulate_r(data, theta)
        decrement = _decrement(r, c, tail, rows, scales)
        if progress is not None:
            progress(f"  {label}: reweighting round {rounds:3d}  robust cost {cost:.6e}  "
                     f"decrement {decrement:.2g}")
        if decrement < DECREMENT:
            ok, status = True, "converged"
            words = (f"converged: a Gauss-Newton step of the reweighted cost would lower it "
                     f"by less than {DECREMENT:g} of itself")
            break
        if moved <= STILL and decrement < ROUNDING_DECREMENT:
            ok, status = True, "converged_to_rounding"
            words = (f"converged to rounding: the last round moved no parameter by more "
                     f"than {STILL:g} of its scale (decrement {decrement:.2g})")
            break
        if moved <= STILL:
            status, words = "stalled", (f"stalled: the rounds stopped moving although a "
                                        f"Gauss-Newton step would lower the cost by "
                                        f"{decrement:.2g} of itself")
            break
        if rounds >= max_rounds:
            status, words = "iteration_limit", (f"stopped: {max_rounds} rounds reached "
                                                f"(decrement {decrement:.2g})")
            break
        out = inner(weighted, theta)
        rounds += 1
        iterations += out.iterations
        method, inner_words = out.method, out.message
        if not out.success:
            status, words = out.status, f"round {rounds} failed: {out.message}"
            break
        moved = float(np.max(np.abs(out.theta - theta)[objective.index] / scales,
                             initial=0.0))
        theta = out.theta
    if not ok and best is not None and best[0] < robust_cost(objective, data, theta,
                                                             losses)[0]:
        theta = best[1]
        words += "; the estimate is the iterate of lowest robust cost"
    final = loss_weights(objective, theta, losses, observations=data.n)
    r, c, tail, rows = Weighed.of(objective, final).accumulate_r(data, theta)
    message = (f"{inner_words}; robust loss ({'; '.join(losses.texts)}) by iteratively "
               f"reweighted least squares, {rounds} rounds: {words}")
    output = SolverOutput(theta, objective.free.copy(), method, ok, status, message, r, rows,
                          float(c @ c + tail), iterations, time.perf_counter() - start)
    return RobustPasses(output, final, robust_cost(objective, data, theta, losses)[0], rounds)


def sandwich_meat_passes(objective: Objective, data: Source, theta: np.ndarray,
                         losses: RowLosses, rank: int) -> np.ndarray:
    """``M`` with ``MᵀM = Σ_i J_iᵀ S_ψ J_i`` (as :func:`symcal.solvers.robust.sandwich_meat`),
    ``ψ = w g`` with the IRLS weights at ``theta`` computed in the passes."""
    psi = Weighed.of(objective, loss_weights(objective, theta, losses, power=1.0,
                                             observations=data.n))
    cov = psi.residual_covariance(data, theta, rank)   # ψᵀψ/N · rows/(rows - rank)
    half = sqrt_psd(cov).T
    if half.shape[0] < cov.shape[0]:     # a vanishing direction: pad with zero rows
        half = np.vstack([half, np.zeros((cov.shape[0] - half.shape[0], cov.shape[0]))])
    return objective.accumulate_r(data, theta, half)[0]
