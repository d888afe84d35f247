"""What every solver path returns: the raw numerical outcome of one solve."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class SolverOutput:
    """Numerical outcome of one solve, before analysis.

    Attributes
    ----------
    theta
        Full parameter vector (fixed ones unchanged).
    free
        Boolean mask of the parameters that were free.
    method
        Short name of the path taken (``"linear"`` or ``"ipopt"``).
    success, status, message
        Whether the solve succeeded, a status word, and a sentence for people.
    r_factor
        Upper-triangular R with ``JᵀJ = RᵀR`` (weighted Jacobian of the free parameters at
        the solution); the basis of identifiability and uncertainty.
    rows
        Number of residual rows (observations × constraints).
    rss
        Weighted residual sum of squares at the solution.
    iterations, seconds
        Solver iterations (0 for closed form) and wall time.
    """

    theta: np.ndarray
    free: np.ndarray
    method: str
    success: bool
    status: str
    message: str
    r_factor: np.ndarray
    rows: int
    rss: float
    iterations: int
    seconds: float
