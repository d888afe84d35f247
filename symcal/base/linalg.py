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


def information_coordinates(r_factor: np.ndarray, rows: int, scales: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray]:
    """``(P, B)`` for sums of per-row scores ``s`` (gradients in the parameters' units,
    in the row space of ``R``): ``c = s P`` are their coordinates where ``RᵀR`` is the
    identity, and ``s = c B``.  A sum ``Σ s sᵀ`` formed and cut in the parameters' units
    spans the square of their scales and of the Jacobian's conditioning (1e17 and more
    on a linear axis whose Abbe term is 4e-5 mm per µrad: a relative cut of its
    eigenvalues drops directions and understates standard errors); ``Σ c cᵀ`` is about
    the residual variance times the identity.  From the SVD of ``R·diag(scales)``, its
    rank by :func:`rank_tolerance`; ``P`` is ``n × r``, ``B`` is ``r × n``."""
    d = np.asarray(scales, dtype=float)
    _, sv, vt = np.linalg.svd(r_factor * d[None, :], full_matrices=False)
    keep = sv > rank_tolerance(sv, rows)
    v, s = vt[keep], sv[keep]
    return (d[:, None] * v.T) / s[None, :], (s[:, None] * v) / d[None, :]


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


#: Relative size below which a relation checked at random points of the parameter space
#: (the model's own, noise-free Jacobian) counts as exact: a gauge's residual there is at
#: rounding level (1e-13 and below in practice), while the flattest real directions of
#: the bundled problems are above 1e-6.
EXACT_RTOL = 1e-8


def null_basis(matrix: np.ndarray, rows: int) -> np.ndarray:
    """Orthonormal rows spanning the numerical null space of ``matrix`` (``M × n``), its
    singular values at or below :func:`rank_tolerance` (``rows`` behind it)."""
    n = matrix.shape[1]
    if n == 0:
        return np.zeros((0, 0))
    if matrix.shape[0] == 0:
        return np.eye(n)
    _, s, vt = np.linalg.svd(matrix, full_matrices=True)
    rank = int(np.sum(s > rank_tolerance(s, rows)))
    return vt[rank:]


def common_null(bases: list[np.ndarray], n: int) -> np.ndarray:
    """Orthonormal rows spanning the directions that lie in every one of ``bases`` (each
    a set of orthonormal rows in ``n`` dimensions), to :data:`EXACT_RTOL`."""
    if not bases or any(b.shape[0] == 0 for b in bases):
        return np.zeros((0, n))
    away = np.vstack([np.eye(n) - b.T @ b for b in bases])
    _, s, vt = np.linalg.svd(away, full_matrices=True)
    s = np.concatenate([s, np.zeros(n - s.size)])
    return vt[s <= EXACT_RTOL]


def known_null_svd(
    matrix: np.ndarray, rows: int, known: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int]:
    """Singular values, right singular vectors and rank of ``matrix`` (``M × n``) with
    the directions ``known`` (rows, ``k × n``, same units as the columns) counted as
    exactly null: the matrix is projected onto their orthogonal complement first, and
    its rank is at most ``n - k``.

    Such directions are gauges found at random points of the parameter space: exact
    symmetries, which noise in the data must not turn into a full rank.  Without them
    this is the plain SVD and :func:`rank_tolerance`.
    """
    n = matrix.shape[1]
    if known.size:
        q = range_basis(known.T)
        matrix = matrix - (matrix @ q) @ q.T
        limit = n - q.shape[1]
    else:
        limit = n
    _, s, vt = np.linalg.svd(matrix)
    rank = min(int(np.sum(s > rank_tolerance(s, rows))), limit)
    return s, vt, rank
