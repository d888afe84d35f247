"""Robust losses by iteratively reweighted least squares (IRLS) around any solver path.

A constraint that declares ``loss: {type: KIND, scale: c}`` contributes
``c² ρ((g/c)²)`` per residual instead of ``g²`` (g its weighted residual g/σ, c its scale
over σ), with scipy's ``ρ`` (``scipy.optimize.least_squares``; the cost here is twice
scipy's, which does not move the minimum):

========  ==========================  ======================
loss      ρ(z)                        ρ'(z), the IRLS weight
========  ==========================  ======================
huber     z if z ≤ 1, else 2√z − 1    1 if z ≤ 1, else 1/√z
soft_l1   2(√(1 + z) − 1)             1/√(1 + z)
cauchy    ln(1 + z)                   1/(1 + z)
arctan    arctan(z)                   1/(1 + z²)
========  ==========================  ======================

Every ρ is concave in z, so ``ρ(z) ≤ ρ(z₀) + ρ'(z₀)(z − z₀)``: minimising the weighted
least-squares cost ``Σ w g²`` with ``w = ρ'(z₀)`` frozen at the current iterate lowers the
robust cost (majorise–minimise), and at a fixed point the gradients agree
(``∇ c²ρ = 2 ρ'(z) g ∇g``).  Each round solves the weighted problem with an existing path
(closed form, IPOPT, trust region) on the same chunked passes (the weights are per-row
factors ``√w`` of :class:`~symcal.solvers.objective.Objective`); rounds stop when a
Gauss–Newton step of the robust cost's weighted model at the current iterate would lower
it by less than :data:`DECREMENT` of itself (a first-order test).

Uncertainty (:func:`sandwich_meat`): the covariance is the sandwich
``(JᵀWJ)⁺ (Σ_i J_iᵀ S_ψ J_i) (JᵀWJ)⁺`` with the final weights W, where ``ψ_i = W_i g_i``
is each observation's contribution to the gradient and ``S_ψ`` its covariance estimated
from the residuals (with degrees of freedom allowed for).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from symcal.base.linalg import rank_tolerance, sqrt_psd
from symcal.data.dataset import Dataset
from symcal.solvers.base import SolverOutput
from symcal.solvers.objective import Objective, Source

#: Where the weights of a robust solve live (an array in memory, a weigher in passes).
W = TypeVar("W")
#: What the robust cost's evaluation hands to the weighing (the weights, or nothing).
S = TypeVar("S")

#: Converged when a Gauss–Newton step of the reweighted model would lower the cost by
#: less than this fraction of itself (the trust-region path's test).
DECREMENT = 1e-20
#: Converged to rounding when the inner solve moves no parameter by more than this many
#: of its scales and the decrement is below :data:`ROUNDING_DECREMENT`.
STILL = 1e-13
ROUNDING_DECREMENT = 1e-10
#: Most reweighting rounds.
MAX_ROUNDS = 200


def rho(kind: str, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``ρ(z)`` and ``ρ'(z)`` of a loss at ``z = (g/c)²`` (scipy's definitions).

    Parameters
    ----------
    kind
        ``huber``, ``soft_l1``, ``cauchy`` or ``arctan``.
    z
        Squared scaled residuals (≥ 0).

    Returns
    -------
    (rho, weight)
        Arrays shaped like ``z``; ``weight = ρ'(z)`` lies in (0, 1].
    """
    z = np.asarray(z, dtype=float)
    if kind == "huber":
        root = np.sqrt(np.maximum(z, 1.0))
        return np.where(z <= 1.0, z, 2.0 * root - 1.0), np.where(z <= 1.0, 1.0, 1.0 / root)
    if kind == "soft_l1":
        t = np.sqrt(1.0 + z)
        return 2.0 * (t - 1.0), 1.0 / t
    if kind == "cauchy":
        return np.log1p(z), 1.0 / (1.0 + z)
    if kind == "arctan":
        return np.arctan(z), 1.0 / (1.0 + z * z)
    raise ValueError(f"unknown loss '{kind}'")


@dataclass(frozen=True)
class RowLosses:
    """The loss of each residual row of an objective (its constraints, in order).

    ``kinds[k]`` is None for squared residuals; ``scales[k]`` is the loss scale in the
    row's own units (the declared scale over the constraint's σ).
    """

    kinds: tuple[str | None, ...]
    scales: np.ndarray
    texts: tuple[str, ...]

    def weights(self, g: np.ndarray) -> np.ndarray:
        """IRLS weights ``ρ'((g/c)²)`` of residual rows ``g`` (``N × n_g``); 1 for squared."""
        w = np.ones_like(g, dtype=float)
        for k, kind in enumerate(self.kinds):
            if kind is not None:
                w[:, k] = rho(kind, (g[:, k] / self.scales[k]) ** 2)[1]
        return w

    def cost(self, g: np.ndarray) -> float:
        """The robust cost ``Σ c² ρ((g/c)²)`` (``Σ g²`` on squared rows)."""
        total = 0.0
        for k, kind in enumerate(self.kinds):
            if kind is None:
                total += float(np.sum(g[:, k] ** 2))
            else:
                c = float(self.scales[k])
                total += c * c * float(np.sum(rho(kind, (g[:, k] / c) ** 2)[0]))
        return total


def row_losses(objective: Objective) -> RowLosses | None:
    """The losses of an objective's constraints; None when every one is squared (or the
    objective is whitened, where rows mix constraints)."""
    quantities = [objective.problem.constraint(n) for n in objective.constraints]
    if all(q.loss is None for q in quantities):
        return None
    if objective.whiten is not None:
        raise ValueError("robust losses apply to unwhitened objectives only")
    kinds = tuple(None if q.loss is None else q.loss.kind for q in quantities)
    scales = np.array([1.0 if q.loss is None else q.loss.internal_scale / q.sigma
                       for q in quantities])
    texts = tuple(f"{q.name}: {q.loss.text}" for q in quantities if q.loss is not None)
    return RowLosses(kinds, scales, texts)


@dataclass(frozen=True, eq=False)
class RobustOutput(Generic[W]):
    """A robust solve: the solver output at the final iterate and its final weights.

    ``output.r_factor`` and ``output.rss`` are those of the reweighted residuals
    (``JᵀWJ = RᵀR``, ``Σ w g²``) at ``output.theta``; ``weights`` are the IRLS weights
    there (in memory an ``N × n_g`` array, in passes the weigher that computes them);
    ``cost`` the robust cost; ``rounds`` the reweighting rounds.
    """

    output: SolverOutput
    weights: W
    cost: float
    rounds: int


def _decrement(r: np.ndarray, c: np.ndarray, tail: float, rows: int,
               scales: np.ndarray) -> float:
    """Fraction of ``‖c‖² + tail`` a (minimum-norm) Gauss–Newton step would remove."""
    total = float(c @ c + tail)
    if total <= 0.0 or r.size == 0:
        return 0.0
    u, s, _ = np.linalg.svd(r * scales[None, :])
    rank = int(np.sum(s > rank_tolerance(s, rows)))
    a = u[:, :rank].T @ c
    return float(a @ a) / total


def solve_robust(
    objective: Objective,
    dataset: Dataset,
    theta0: np.ndarray,
    losses: RowLosses,
    inner: Callable[[Objective, np.ndarray], SolverOutput],
    progress: Callable[[str], None] | None = None,
    label: str = "robust",
    max_rounds: int = MAX_ROUNDS,
) -> RobustOutput[np.ndarray]:
    """Minimise the robust cost by iteratively reweighted least squares from ``theta0``.

    Parameters
    ----------
    objective
        The unweighted objective (constraints and free parameters).
    dataset
        Observations to solve on.
    theta0
        Initial values of all parameters.
    losses
        The loss of each constraint (:func:`row_losses`).
    inner
        Solves a weighted objective from a parameter vector (a closed-form, IPOPT or
        trust-region path); called once per round.
    progress
        Called with one line per round (None: silent).
    label
        Name shown in progress lines.
    max_rounds
        Most reweighting rounds.

    Returns
    -------
    RobustOutput
        ``output.success`` only when the first-order test holds; a failed round or the
        round limit keeps the iterate of lowest robust cost, with the reason.
    """
    def cost(theta: np.ndarray) -> tuple[float, bool, np.ndarray]:
        g = objective.residuals(dataset, theta)
        w = losses.weights(g)
        return losses.cost(g), bool(np.all(np.isfinite(w))), w

    def weigh(theta: np.ndarray, w: np.ndarray) -> tuple[Objective, np.ndarray]:
        return objective.with_row_weights(np.sqrt(w)), w

    return irls(objective, dataset, theta0, losses, cost, weigh, inner, progress, label,
                max_rounds)


def irls(
    objective: Objective,
    data: Source,
    theta0: np.ndarray,
    losses: RowLosses,
    cost: Callable[[np.ndarray], tuple[float, bool, S]],
    weigh: Callable[[np.ndarray, S], tuple[Objective, W]],
    inner: Callable[[Objective, np.ndarray], SolverOutput],
    progress: Callable[[str], None] | None,
    label: str,
    max_rounds: int,
) -> RobustOutput[W]:
    """The reweighting rounds of :func:`solve_robust`, wherever the weights live.

    ``cost(theta)`` gives the robust cost at ``theta``, whether every IRLS weight there is
    finite, and what ``weigh`` needs of that evaluation; ``weigh(theta, that)`` gives
    ``objective`` weighted by the IRLS weights frozen at ``theta`` (their square roots as
    per-row factors) and those weights (an array held in memory, or the weigher that
    computes them in the passes).  The other parameters as for :func:`solve_robust`,
    ``data`` in memory or kept as shards.
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
        value, finite, that = cost(theta)
        if not finite or not np.isfinite(value):
            status, words = "invalid_number", "a residual is NaN or inf"
            break
        if best is None or value < best[0]:
            best = (value, theta.copy())
        reweighted, _ = weigh(theta, that)
        r, c, tail, rows = reweighted.accumulate_r(data, theta)
        decrement = _decrement(r, c, tail, rows, scales)
        if progress is not None:
            progress(f"  {label}: reweighting round {rounds:3d}  robust cost {value:.6e}  "
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
        out = inner(reweighted, theta)
        rounds += 1
        iterations += out.iterations
        method, inner_words = out.method, out.message
        if not out.success:
            status, words = out.status, f"round {rounds} failed: {out.message}"
            break
        moved = float(np.max(np.abs(out.theta - theta)[objective.index] / scales,
                             initial=0.0))
        theta = out.theta
    if not ok and best is not None and best[0] < cost(theta)[0]:
        theta = best[1]
        words += "; the estimate is the iterate of lowest robust cost"
    value, _, that = cost(theta)
    reweighted, w = weigh(theta, that)
    r, c, tail, rows = reweighted.accumulate_r(data, theta)
    message = (f"{inner_words}; robust loss ({'; '.join(losses.texts)}) by iteratively "
               f"reweighted least squares, {rounds} rounds: {words}")
    output = SolverOutput(theta, objective.free.copy(), method, ok, status, message, r, rows,
                          float(c @ c + tail), iterations, time.perf_counter() - start)
    return RobustOutput(output, w, value, rounds)


def sandwich_meat(objective: Objective, dataset: Dataset, theta: np.ndarray,
                  weights: np.ndarray, rank: int) -> np.ndarray:
    """``M`` with ``MᵀM = Σ_i J_iᵀ S_ψ J_i``: the meat of the robust sandwich.

    Parameters
    ----------
    objective
        The unweighted objective (J its Jacobian).
    dataset, theta
        Where the estimate is.
    weights
        The final IRLS weights (``N × n_g``).
    rank
        Identifiable parameters (degrees of freedom used).

    Returns
    -------
    numpy.ndarray
        ``n × n``; with ``R`` of ``JᵀWJ`` it gives the covariance
        ``(JᵀWJ)⁺ MᵀM (JᵀWJ)⁺`` (:func:`symcal.analysis.identifiability.analyse`).
    """
    psi = weights * objective.residuals(dataset, theta)
    rows = psi.size
    cov = (psi.T @ psi) / max(dataset.n, 1) * rows / max(rows - rank, 1)
    return meat_of(objective, dataset, theta, cov)


def meat_of(objective: Objective, data: Source, theta: np.ndarray,
            cov: np.ndarray) -> np.ndarray:
    """``M`` with ``MᵀM = Σ_i J_iᵀ S_ψ J_i`` from ``S_ψ`` (``cov``, ``n_g × n_g``), ``J``
    the Jacobian of ``objective`` at ``theta`` on ``data``."""
    half = sqrt_psd(cov).T
    if half.shape[0] < cov.shape[0]:     # a vanishing direction: pad with zero rows
        half = np.vstack([half, np.zeros((cov.shape[0] - half.shape[0], cov.shape[0]))])
    return objective.accumulate_r(data, theta, half)[0]
