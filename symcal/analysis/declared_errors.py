"""Standard errors of a fit that does not weight its rows by their declared noise.

A fit with ``weighting: equal`` (or ``estimated``: one whitening for every row) gives each
observation the same weights ``W``, but where the readings' noise reaches the
constraints through the readings themselves (a ratio of two noisy readings, an angle's
noise through a lever that changes with the pose) each observation's residuals have their
own covariance ``C_i``.  To first order the estimate's covariance is then the sandwich
(the law of propagation of variance through the normal equations)::

    Cov = σ̂₀² A⁺ B A⁺,   A = Σ J_iᵀ W J_i,   B = Σ J_iᵀ W C_i W J_i,

the sums of the noise floors' *estimate's share* (:class:`~symcal.analysis.floors.SharePlan`:
the same pass, kept for the floors of the same fit), scaled, as the propagated
weighting's standard errors are, by the variance factor
``σ̂₀² = RSS / E[RSS]``, ``E[RSS] = Σ tr(W C_i) − tr(A⁺B)`` (the residuals' weighted sum of
squares over what the declared noise predicts for it): about 1 where the noise is declared
right and the model is at its floor, larger above it.  The pooled ``s² A⁺`` is the same
where every ``C_i`` is (one constraint), and too small or too large by up to the spread of
the ``C_i`` where they differ (a resistance from a voltage over a current: the voltmeter
offset's standard error 1.5 times too small).

Taken only where every reading the stage's constraints read declares its noise and some
noise is not zero; a robust loss keeps its own sandwich, serially correlated rows the
Newey–West one (:mod:`symcal.analysis.serial`), and ``weighting: propagated`` weighs each
row by its own ``C_i`` already.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from symcal.analysis.floor_passes import ShareSums
from symcal.analysis.floors import kept_sums, share_finish, share_plan
from symcal.analysis.row_noise import Fit
from symcal.base.linalg import sqrt_psd
from symcal.data.dataset import Dataset
from symcal.problem.symbolic import Problem
from symcal.solvers.objective import Objective, Source
from symcal.solvers.weighed import map_pieces

#: How a stage's note on these standard errors begins (the report's header reads it).
NOTE = "standard errors: the sandwich"


@dataclass(frozen=True)
class DeclaredErrors:
    """The sandwich's meat and its variance factor.

    Attributes
    ----------
    meat
        ``M`` (``r × n_free``) with ``MᵀM = σ̂₀² B`` (the ``meat`` of
        :func:`~symcal.analysis.identifiability.analyse`).
    factor
        ``σ̂₀²``: the weighted residual sum of squares over what the declared noise
        predicts for it.
    spread
        How far the pooled ``rss/(rows − rank) A⁺`` would be from it: the largest ratio,
        either way, of the two standard errors of a parameter (1 where they agree).
    """

    meat: np.ndarray
    factor: float
    spread: float

    def note(self) -> str:
        """The stage's note on how its standard errors were taken."""
        return (f"{NOTE} of the fit's weights with each observation's "
                "covariance propagated from the readings' declared noise, scaled by the "
                "residuals' sum of squares over what that noise predicts for it "
                f"(σ̂₀² = {self.factor:.3g}); with one pooled residual variance they would "
                f"be off by up to a factor {self.spread:.2g}")


def declared_errors(problem: Problem, objective: Objective, data: Source,
                    theta: np.ndarray, rss: float, rows: int) -> DeclaredErrors | None:
    """The sandwich of a stage solved with ``objective`` (equal weights, or one
    whitening) at ``theta``, or None where it does not apply (see the module): a reading
    of undeclared noise, no noise at all, per-row weights, or no residual degrees of
    freedom.

    Parameters
    ----------
    problem
        The problem (its noisy view carries the declared noise).
    objective
        The stage's objective as solved (its constraints, free parameters and whitening).
    data
        The fitted dataset, in memory or kept as shards.
    theta
        The estimate.
    rss
        The objective's weighted residual sum of squares at ``theta``.
    rows
        Residual rows (observations × constraints): the pooled variance's ``rss/(rows −
        rank)`` the spread compares with.
    """
    if objective.row_weights is not None or getattr(objective, "weigher", None) is not None:
        return None
    if any(problem.undeclared(problem.constraint(n).sx) for n in objective.constraints):
        return None
    whiten = objective.whiten
    fit = Fit(problem.fit_dataset, tuple(objective.constraints), objective.free,
              "estimated" if whiten is not None else "equal", whiten)
    plan = share_plan(problem, fit, cached=isinstance(data, Dataset))
    if plan is None or not np.any(objective.free):
        return None
    if isinstance(data, Dataset):
        a, b, t = kept_sums(problem, plan, data, theta)
    else:
        parts = map_pieces(ShareSums(plan, np.array(theta, dtype=float), data.name), data,
                           "declared_errors")
        a = np.sum([p[0] for p in parts], axis=0)
        b = np.sum([p[1] for p in parts], axis=0)
        t = float(sum(p[2] for p in parts))
    share = share_finish(a, b, plan.scales)
    expected = t - float(np.trace(share.a_pinv @ b))
    rank = int(round(float(np.trace(share.a_pinv @ a))))
    if not (np.isfinite(expected) and expected > 0 and rss >= 0 and rows > rank):
        return None
    factor = float(rss / expected)
    cov = factor * share.cov
    pooled = rss / (rows - rank) * share.a_pinv
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.sqrt(np.diag(pooled) / np.diag(cov))
    ratio = ratio[np.isfinite(ratio) & (ratio > 0)]
    spread = float(max(np.max(ratio), 1.0 / np.min(ratio))) if ratio.size else 1.0
    return DeclaredErrors(np.sqrt(factor) * sqrt_psd(b).T, factor, spread)
