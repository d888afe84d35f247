"""Robust losses by IRLS in passes: :func:`symcal.solvers.robust.solve_robust` on a log
kept as shards, its weights never held.

The rounds are those of :mod:`symcal.solvers.robust` (its :func:`~symcal.solvers.robust.irls`):
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

from collections.abc import Callable

import numpy as np

from symcal.solvers.base import SolverOutput
from symcal.solvers.objective import Objective, Source
from symcal.solvers.robust import MAX_ROUNDS, RobustOutput, RowLosses, irls, meat_of
from symcal.solvers.weighed import LossCost, LossWeights, Weighed, loss_weights, map_pieces


def robust_cost(objective: Objective, data: Source, theta: np.ndarray,
                losses: RowLosses) -> tuple[float, bool]:
    """The robust cost ``Σ c² ρ((g/c)²)`` at ``theta`` and whether every IRLS weight
    there is finite: one residual pass."""
    task = LossCost(loss_weights(objective, theta, losses, observations=data.n).rows, losses,
                    tuple(objective.problem.columns))
    parts = map_pieces(task, data, "robust_cost", executor=objective.executor)
    return float(sum(c for c, _ in parts)), all(f for _, f in parts)


#: A robust solve on passes: the solver output at the final iterate (``r_factor`` and
#: ``rss`` of the reweighted rows there) and the weigher of its final weights (the IRLS
#: weights at ``output.theta``, power ½).
RobustPasses = RobustOutput[LossWeights]


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
    def cost(theta: np.ndarray) -> tuple[float, bool, None]:
        return (*robust_cost(objective, data, theta, losses), None)

    def weigh(theta: np.ndarray, _: None) -> tuple[Objective, LossWeights]:
        weights = loss_weights(objective, theta, losses, observations=data.n)
        return Weighed.of(objective, weights), weights

    return irls(objective, data, theta0, losses, cost, weigh, inner, progress, label,
                max_rounds)


def sandwich_meat_passes(objective: Objective, data: Source, theta: np.ndarray,
                         losses: RowLosses, rank: int) -> np.ndarray:
    """``M`` with ``MᵀM = Σ_i J_iᵀ S_ψ J_i`` (as :func:`symcal.solvers.robust.sandwich_meat`),
    ``ψ = w g`` with the IRLS weights at ``theta`` computed in the passes."""
    psi = Weighed.of(objective, loss_weights(objective, theta, losses, power=1.0,
                                             observations=data.n))
    cov = psi.residual_covariance(data, theta, rank)   # ψᵀψ/N · rows/(rows - rank)
    return meat_of(objective, data, theta, cov)
