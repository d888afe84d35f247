"""Closed-form path: constraints linear in the free parameters (paper eq. 7–8).

With g(θ, u) = A(u)·θ_free + b(u), A and b are generated symbolically with CasADi,
evaluated over the observations in chunks, and reduced on the fly to the R factor of
``[A | g₀]`` (a TSQR), so memory does not grow with N.  The minimum-norm correction from
the initial values is taken through the SVD of R (rank-revealing): directions the data
cannot see stay at their initial values, as with the pseudo-inverse of eq. (8).
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np
import scipy.linalg

from symcal.analysis.identifiability import rank_tolerance
from symcal.data import Dataset
from symcal.numeric import chunks, mapped
from symcal.problem import Problem
from symcal.solve.base import SolverOutput


def weighted_residual(problem: Problem) -> ca.SX:
    """The stacked constraints of one observation, each divided by its sigma."""
    return ca.vertcat(*(c.sx / c.sigma for c in problem.constraints))


def nonlinear_constraints(problem: Problem, free: np.ndarray) -> list[str]:
    """Names of the constraints that are not linear in the free parameters."""
    theta_free = problem.theta[np.flatnonzero(free).tolist()]
    return [c.name for c in problem.constraints if not ca.is_linear(c.sx, theta_free)]


def accumulate_r(
    problem: Problem, dataset: Dataset, theta: np.ndarray, free: np.ndarray,
    outputs: tuple[ca.SX, ca.SX] | None = None,
) -> tuple[np.ndarray, np.ndarray, float, int]:
    """R factor of the weighted Jacobian and the reduced residual, accumulated by chunks.

    Returns
    -------
    (R, c, tail, rows)
        ``R`` (n × n) and ``c`` (n) with ``‖J δ + g‖² = ‖R δ + c‖² + tail`` for every δ,
        where J, g are the weighted Jacobian and residual at ``theta``; ``rows`` counts the
        residual rows.
    """
    idx = np.flatnonzero(free).tolist()
    g = weighted_residual(problem)
    jac = ca.jacobian(g, problem.theta[idx])
    fn = mapped(problem.theta, problem.u, [g, jac.T], "linearised")
    n, ng = len(idx), g.shape[0]
    u = dataset.matrix(problem.columns)
    r_aug = np.zeros((0, n + 1))
    rows = 0
    for part in chunks(dataset.n):
        g0, jt = fn.chunk(theta, u[:, part])
        m = g0.shape[0]
        a = jt.reshape(m, ng, n).reshape(m * ng, n)
        block = np.column_stack([a, g0.reshape(m * ng)])
        r_aug = scipy.linalg.qr(np.vstack([r_aug, block]), mode="r", check_finite=False)[0]
        r_aug = r_aug[: n + 1]
        rows += m * ng
    if r_aug.shape[0] < n + 1:
        r_aug = np.vstack([r_aug, np.zeros((n + 1 - r_aug.shape[0], n + 1))])
    return r_aug[:n, :n], r_aug[:n, n], float(r_aug[n, n] ** 2), rows


def min_norm_step(r: np.ndarray, c: np.ndarray, scales: np.ndarray, rows: int) -> np.ndarray:
    """Minimum-norm (in scaled units) δ minimising ‖R δ + c‖, via the SVD of R·D."""
    u, s, vt = np.linalg.svd(r * scales[None, :])
    rank = int(np.sum(s > rank_tolerance(s, rows)))
    z = -(vt[:rank].T @ ((u[:, :rank].T @ c) / s[:rank]))
    return scales * z


def solve_linear(
    problem: Problem, dataset: Dataset, theta0: np.ndarray, free: np.ndarray
) -> SolverOutput:
    """Solve a problem whose constraints are linear in the free parameters, in closed form.

    Parameters
    ----------
    problem
        The symbolic problem.
    dataset
        Observations to solve on.
    theta0
        Initial (and fixed) parameter values; unidentifiable directions keep these values.
    free
        Mask of the free parameters.

    Returns
    -------
    SolverOutput
        ``method == "linear"``; no iterative solver is involved.
    """
    start = time.perf_counter()
    free = np.asarray(free, dtype=bool)
    idx = np.flatnonzero(free)
    scales = np.array([problem.parameters[i].scale for i in idx])
    r, c, tail, rows = accumulate_r(problem, dataset, theta0, free)
    step = min_norm_step(r, c, scales, rows)
    theta = np.array(theta0, dtype=float)
    theta[idx] += step
    rss = float(np.sum((r @ step + c) ** 2) + tail)
    return SolverOutput(theta, free, "linear", True, "solved",
                        "closed-form least squares (QR, then SVD of R; minimum-norm step)",
                        r, rows, rss, 0, time.perf_counter() - start)
