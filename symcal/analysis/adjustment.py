"""The adjusted readings of a least-squares adjustment with condition equations.

Each observation's residuals r_i (constraints, and comparisons with a reference) are
functions of its noisy readings; with ``L_i = (∂r/∂ε)·diag(σ)`` (the derivative by the
readings' errors, exact, from the noise symbols of
:attr:`~symcal.problem.symbolic.Problem.noisy`) their covariance is ``C_i = L_i L_iᵀ``.
The adjustment attributes the misfit to the readings: ``ε̂_i = −diag(σ) L_iᵀ C_i⁺ r_i``,
the smallest correction (in the metric of the declared noise) that makes the residuals
vanish, and the adjusted readings are ``l̂_i = l_i + ε̂_i``.

What this is for: the noise left in an adjusted reading is uncorrelated with the residual
(to first order, ``Cov(l̂ − l_true, r) = Σ Bᵀ − Σ Bᵀ C⁺ B Σ Bᵀ = 0``), and, the noise being
Gaussian, independent of it.  A candidate term evaluated at the *raw* readings correlates
with the residual through the readings' own noise (errors in the variables: a term in
sensor 1's reading added to sensor 2 explains sensor 1's noise in their difference); the
same term evaluated at the adjusted readings does not, so that its test (the w-test of
the alternative hypothesis) has its nominal level on a model without the effect.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from symcal.analysis.row_noise import EXACT
from symcal.base.numeric import mapped
from symcal.data.dataset import Dataset
from symcal.problem.symbolic import Problem


@dataclass(frozen=True)
class Adjustment:
    """Per observation of one dataset: the propagated covariance of the residuals
    (``cov``, N × n × n, internal units), the readings' corrections (``corrections``,
    N × n_ε, internal units, in the order of ``readings``) and whether every residual's
    readings declare their noise (``complete``)."""

    cov: np.ndarray
    corrections: np.ndarray
    readings: tuple[str, ...]
    complete: bool


def pinv_rows(c: np.ndarray) -> np.ndarray:
    """Per row, the pseudo-inverse of a covariance (m × n × n)."""
    w, v = np.linalg.eigh(c)
    top = np.max(w, axis=1, keepdims=True)
    keep = w > EXACT * np.maximum(top, 1e-300)
    inv = np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0)
    return np.einsum("mab,mb,mcb->mac", v, inv, v)


def adjust(problem: Problem, exprs: list[ca.SX], centred: list[bool], ds: Dataset,
           theta: np.ndarray, complete: bool) -> Adjustment | None:
    """The adjustment of the residuals ``exprs`` (SX of the noisy view, one per residual)
    on ``ds`` at ``theta``; None when no reading declares its noise.  A residual whose
    zero is arbitrary (``centred``) is adjusted after its mean is removed."""
    noisy = problem.noisy
    readings = [r for r in noisy.readings if r.sigma > 0]
    if not readings or not exprs:
        return None
    eps = ca.vertcat(*(r.symbol for r in readings))
    sigma = np.array([r.sigma for r in readings])
    e = ca.vertcat(*exprs)
    exact = [r.symbol for r in noisy.readings if r.sigma <= 0]
    if exact:
        e = ca.substitute(e, ca.vertcat(*exact), ca.SX.zeros(len(exact)))
    lmat = ca.mtimes(ca.jacobian(e, eps), ca.diag(ca.DM(sigma)))
    fn = mapped(noisy.theta, ca.vertcat(noisy.u, eps), [e, lmat.T], "adjust")
    u = np.vstack([ds.matrix(noisy.columns), np.zeros((len(readings), ds.n))])
    r, lt = fn(theta, u)
    n, k = r.shape
    r = r - np.where(np.asarray(centred)[None, :], r.mean(axis=0, keepdims=True), 0.0)
    lrow = lt.reshape(n, k, len(readings))                 # vec of (n_ε × k): column-major
    cov = np.einsum("nae,nbe->nab", lrow, lrow)
    z = -np.einsum("nea,nab,nb->ne", lrow.transpose(0, 2, 1), pinv_rows(cov), r)
    return Adjustment(cov, z * sigma[None, :], tuple(r.name for r in readings), complete)


def adjusted_values(problem: Problem, named: list[tuple[str, ca.SX]], ds: Dataset,
                    theta: np.ndarray, adjustment: Adjustment) -> dict[str, np.ndarray]:
    """The quantities ``named`` (SX of the noisy view) evaluated at the adjusted readings:
    name → values (N,), internal units."""
    if not named:
        return {}
    noisy = problem.noisy
    by_name = {r.name: r for r in noisy.readings}
    eps = ca.vertcat(*(by_name[n].symbol for n in adjustment.readings))
    expr = ca.vertcat(*(sx for _, sx in named))
    exact = [r.symbol for r in noisy.readings if r.name not in adjustment.readings]
    if exact:   # readings declared exact (noise 0) are not adjusted
        expr = ca.substitute(expr, ca.vertcat(*exact), ca.SX.zeros(len(exact)))
    fn = mapped(noisy.theta, ca.vertcat(noisy.u, eps), [expr], "adjusted")
    u = np.vstack([ds.matrix(noisy.columns), adjustment.corrections.T])
    values = fn(theta, u)[0]
    return {name: values[:, k] for k, (name, _) in enumerate(named)}
