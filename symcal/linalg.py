"""The one home of symcal's rank decisions and positive semi-definite square roots.

Identifiability, the closed-form step, the sandwich covariance and the diagnosis all ask
"is this direction numerically zero?"; they ask it here, with one rule each:

- a singular value of a (scaled) Jacobian or R factor is zero below
  :func:`rank_tolerance` (the rank of identifiability, of the minimum-norm step and of the
  residual degrees of freedom);
- an eigenvalue of an estimated covariance (positive semi-definite) is zero below
  :data:`PSD_RTOL` times the largest: residuals that are exact combinations of others
  carry no information of their own, and rounding must not whiten them into noise.
"""

from __future__ import annotations

import numpy as np

#: Relative size below which an eigenvalue of a covariance counts as zero.
PSD_RTOL = 1e-9


def rank_tolerance(singular_values: np.ndarray, rows: int) -> float:
    """Threshold below which a singular value counts as zero (``s₁ · max(rows, n) · 10ε``)."""
    if singular_values.size == 0:
        return 0.0
    return float(singular_values[0]) * max(rows, singular_values.size) * np.finfo(float).eps * 10


def numerical_rank(r_factor: np.ndarray, rows: int, scales: np.ndarray) -> int:
    """Rank of ``R·diag(scales)`` under :func:`rank_tolerance` (``rows`` behind R)."""
    if r_factor.size == 0:
        return 0
    s = np.linalg.svd(r_factor * np.asarray(scales)[None, :], compute_uv=False)
    return int(np.sum(s > rank_tolerance(s, rows)))


def range_basis(matrix: np.ndarray) -> np.ndarray:
    """Orthonormal columns spanning the numerical range of ``matrix`` (``M × k``), its
    singular values above :func:`rank_tolerance`."""
    if matrix.size == 0:
        return np.zeros((matrix.shape[0], 0))
    u, s, _ = np.linalg.svd(matrix, full_matrices=False)
    return u[:, s > rank_tolerance(s, matrix.shape[0])]


def _eigen(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues above :data:`PSD_RTOL` of the largest, and their eigenvectors."""
    w, v = np.linalg.eigh((matrix + matrix.T) / 2)
    keep = w > PSD_RTOL * max(float(w.max(initial=0.0)), 1e-300)
    return w[keep], v[:, keep]


def sqrt_psd(matrix: np.ndarray) -> np.ndarray:
    """``L`` (``n × r``) with ``L Lᵀ = matrix`` on its numerical range (r its PSD rank)."""
    w, v = _eigen(matrix)
    return v * np.sqrt(w)[None, :]


def whitening(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``T`` (``r × n``) with ``T S Tᵀ = I`` and its inverse ``T⁻`` (``n × r``) for a
    covariance ``S`` of PSD rank r; directions where S vanishes are dropped."""
    w, v = _eigen(cov)
    return (v / np.sqrt(w)[None, :]).T, v * np.sqrt(w)[None, :]


def is_singular(cov: np.ndarray) -> bool:
    """Whether a covariance has a direction that :func:`whitening` would drop."""
    return _eigen(cov)[0].size < cov.shape[0]
