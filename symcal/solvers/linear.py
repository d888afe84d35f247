"""Closed-form path: constraints linear in the free parameters (paper eq. 7–8).

With g(θ, u) = A(u)·θ_free + b(u), A and b are generated symbolically with CasADi,
evaluated over the observations in chunks, and reduced on the fly to the R factor of
``[A | g₀]`` (a TSQR), so memory does not grow with N.  The minimum-norm correction from
the initial values is taken through the SVD of R·D, D the parameters' nominal scales
(rank-revealing): directions the data cannot see keep their initial values, as with the
pseudo-inverse of eq. (8).
"""

from __future__ import annotations

import time

import numpy as np

from symcal.base.linalg import rank_tolerance
from symcal.solvers.base import SolverOutput
from symcal.solvers.objective import Objective, Source


def min_norm_step(r: np.ndarray, c: np.ndarray, scales: np.ndarray, rows: int) -> np.ndarray:
    """Minimum-norm (in scaled units) δ minimising ‖R δ + c‖, via the SVD of R·D."""
    u, s, vt = np.linalg.svd(r * scales[None, :])
    rank = int(np.sum(s > rank_tolerance(s, rows)))
    z = -(vt[:rank].T @ ((u[:, :rank].T @ c) / s[:rank]))
    return scales * z


def solve_linear(objective: Objective, dataset: Source, theta0: np.ndarray) -> SolverOutput:
    """Minimise an objective that is linear in its free parameters, in closed form.

    Parameters
    ----------
    objective
        Constraints and free parameters; every constraint must be linear in them.
    dataset
        Observations to solve on.
    theta0
        Initial (and fixed) parameter values; unidentifiable directions keep these values.

    Returns
    -------
    SolverOutput
        ``method == "linear"``; no iterative solver is involved.
    """
    start = time.perf_counter()
    idx = objective.index
    r, c, tail, rows = objective.accumulate_r(dataset, theta0)
    step = min_norm_step(r, c, objective.scales, rows)
    theta = np.array(theta0, dtype=float)
    theta[idx] += step
    rss = float(np.sum((r @ step + c) ** 2) + tail)
    return SolverOutput(theta, objective.free.copy(), "linear", True, "solved",
                        "closed-form least squares (QR, then SVD of R; minimum-norm step)",
                        r, rows, rss, 0, time.perf_counter() - start)
