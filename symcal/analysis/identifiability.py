"""Identifiability and uncertainty from the (scaled) Jacobian of the weighted residuals.

Everything is computed from the SVD of ``J·D`` where ``D = diag(scale)`` makes the
parameters commensurate.  Unidentifiable directions are never inverted: they are reported
as named parameter combinations, and standard errors are given on the identifiable
subspace only, with a reason where a value cannot be given.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from symcal.base.linalg import known_null_svd

_ZERO = 1e-9  # relative size below which a coefficient counts as zero


@dataclass(frozen=True)
class Combination:
    """A linear combination of parameters, e.g. ``s1.k0 - s2.k0 - s3.k0 + s4.k0``."""

    coefficients: dict[str, float]
    text: str
    value: float | None = None
    se: float | None = None

    def to_dict(self) -> dict:
        """Plain-data form."""
        return {"combination": self.text, "coefficients": dict(self.coefficients),
                "value": self.value, "se": self.se}

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> Combination:
        """Inverse of :meth:`to_dict`."""
        return cls(dict(doc["coefficients"]), doc["combination"], doc.get("value"),
                   doc.get("se"))


@dataclass(frozen=True)
class Identifiability:
    """What the data can and cannot determine.

    Attributes
    ----------
    rank
        Numerical rank of the scaled Jacobian.
    singular_values
        All singular values of the scaled Jacobian, largest first.
    condition_number
        Ratio of the largest to the smallest singular value of the identifiable part.
    null_space
        Directions (in parameter names) along which no residual changes.
    identifiable_combinations
        Within each group of parameters touched by the null space, the combinations the
        data does determine, with value and standard error.
    """

    n_free: int
    rank: int
    singular_values: tuple[float, ...]
    condition_number: float
    null_space: tuple[Combination, ...]
    identifiable_combinations: tuple[Combination, ...]

    @property
    def deficiency(self) -> int:
        """Number of unidentifiable directions."""
        return self.n_free - self.rank

    def to_dict(self) -> dict:
        """Plain-data form."""
        return {
            "n_free": self.n_free, "rank": self.rank,
            "condition_number": self.condition_number,
            "singular_values": list(self.singular_values),
            "null_space": [c.text for c in self.null_space],
            "null_space_coefficients": [dict(c.coefficients) for c in self.null_space],
            "identifiable_combinations": [c.to_dict() for c in self.identifiable_combinations],
        }

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> Identifiability:
        """Inverse of :meth:`to_dict`."""
        null = tuple(Combination(dict(c), t) for t, c in
                     zip(doc["null_space"], doc["null_space_coefficients"], strict=True))
        return cls(doc["n_free"], doc["rank"], tuple(doc["singular_values"]),
                   _float(doc["condition_number"]), null,
                   tuple(Combination.from_dict(c) for c in doc["identifiable_combinations"]))


@dataclass(frozen=True)
class Uncertainty:
    """Standard errors and correlations of the free parameters.

    ``se[name]`` is None where the parameter is not identifiable; ``reason[name]`` says why.
    The covariance is ``s² (JᵀJ)⁺`` on the identifiable subspace, with ``s²`` the residual
    variance (weighted RSS over degrees of freedom).
    """

    residual_variance: float
    dof: int
    names: tuple[str, ...]
    se: dict[str, float | None]
    reason: dict[str, str]
    covariance: np.ndarray
    correlation: np.ndarray

    def to_dict(self) -> dict:
        """Plain-data form (correlation with None where undefined)."""
        corr, cov = _rows(self.correlation), _rows(self.covariance)
        return {"residual_variance": self.residual_variance, "dof": self.dof,
                "se": dict(self.se), "reason": dict(self.reason),
                "correlation": {"names": list(self.names), "matrix": corr},
                "covariance": cov}

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> Uncertainty:
        """Inverse of :meth:`to_dict`."""
        names = tuple(doc["correlation"]["names"])

        def matrix(rows: list) -> np.ndarray:     # None (not finite) becomes NaN
            return np.array(rows, dtype=float).reshape(len(names), len(names))

        return cls(_float(doc["residual_variance"]), doc["dof"], names, dict(doc["se"]),
                   dict(doc["reason"]), matrix(doc["covariance"]),
                   matrix(doc["correlation"]["matrix"]))


def _rows(matrix: np.ndarray) -> list[list[float | None]]:
    """A matrix as lists of floats, None where it is not finite (converted in numpy: a
    fleet's document holds one per unit)."""
    values = np.asarray(matrix, dtype=float)
    out = values.astype(object)
    out[~np.isfinite(values)] = None
    rows: list[list[float | None]] = out.tolist()
    return rows


def _float(value: float | None) -> float:
    """A JSON number back to float (null was a non-finite value)."""
    return float("nan") if value is None else float(value)


def format_combination(coefficients: dict[str, float]) -> str:
    """Render ``{a: 1, b: -1, c: 0.5}`` as ``a - b + 0.5*c``."""
    parts: list[str] = []
    for name, coef in coefficients.items():
        sign = "-" if coef < 0 else "+"
        mag = abs(coef)
        term = name if abs(mag - 1) < 1e-6 else f"{mag:.3g}*{name}"
        parts.append(f"{sign} {term}" if parts else (f"-{term}" if sign == "-" else term))
    return " ".join(parts)


def _named(vector: np.ndarray, names: tuple[str, ...]) -> dict[str, float]:
    vector = vector / np.max(np.abs(vector))
    rounded = np.where(np.abs(vector - np.round(vector)) < 1e-6, np.round(vector), vector)
    return {names[i]: float(rounded[i]) for i in np.flatnonzero(np.abs(rounded) > _ZERO)}


def _rref_rows(basis: np.ndarray) -> np.ndarray:
    """Reduced row echelon form of the rows of ``basis`` (readable null directions)."""
    m = basis.copy()
    rows, cols = m.shape
    pivot_row = 0
    for col in range(cols):
        if pivot_row >= rows:
            break
        best = pivot_row + int(np.argmax(np.abs(m[pivot_row:, col])))
        if abs(m[best, col]) < 1e-8:
            continue
        m[[pivot_row, best]] = m[[best, pivot_row]]
        m[pivot_row] /= m[pivot_row, col]
        for r in range(rows):
            if r != pivot_row:
                m[r] -= m[r, col] * m[pivot_row]
        pivot_row += 1
    m[np.abs(m) < 1e-10] = 0.0
    return m[:pivot_row]


def null_groups(null_rows: np.ndarray) -> list[np.ndarray]:
    """Connected groups of parameters (column indices) that share a null direction (a
    row of ``null_rows``), in the order of their first parameter."""
    n = null_rows.shape[1]
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for row in null_rows:
        idx = [int(i) for i in np.flatnonzero(row)]
        for j in idx[1:]:
            parent[find(j)] = find(idx[0])
    involved = np.flatnonzero(np.any(null_rows != 0, axis=0))
    groups: dict[int, list[int]] = {}
    for i in involved:
        groups.setdefault(find(int(i)), []).append(int(i))
    return [np.array(g) for g in groups.values()]


def analyse(
    r_factor: np.ndarray,
    rows: int,
    rss: float,
    names: tuple[str, ...],
    scales: np.ndarray,
    values: np.ndarray,
    meat: np.ndarray | None = None,
    gauges: np.ndarray | None = None,
) -> tuple[Identifiability, Uncertainty]:
    """Identifiability and uncertainty from the R factor of the weighted Jacobian.

    Parameters
    ----------
    r_factor
        Upper-triangular ``R`` (``n × n``) with ``JᵀJ = RᵀR`` for the free parameters.
    rows
        Number of residual rows behind ``R`` (observations × constraints).
    rss
        Weighted residual sum of squares at the estimate.
    names, scales, values
        Free parameters' names, nominal scales and estimated values.
    meat
        For several constraints: ``M`` with ``MᵀM = Σ_i J_iᵀ S J_i``, S the estimated
        covariance between the constraints of one observation.  The covariance is then
        the sandwich ``(JᵀJ)⁺ MᵀM (JᵀJ)⁺``, right when the constraints have different
        noise levels or are correlated; without it, ``s² (JᵀJ)⁺`` with one pooled s².
    gauges
        Directions (rows, ``k × n``, parameter units) known to be exactly undeterminable
        (:mod:`symcal.analysis.gauges`): counted as null whatever the noise, so that an
        exact symmetry on noisy data is named rather than inverted; the covariance is then
        the minimum-norm one, orthogonal to them (in units of the scales).
    """
    n = len(names)
    d = np.asarray(scales, dtype=float)
    known = (np.asarray(gauges, dtype=float) / d[None, :] if gauges is not None and n
             else np.zeros((0, n)))
    if n:
        s, vt, rank = known_null_svd(r_factor * d[None, :], rows, known)
    else:
        s, vt, rank = np.zeros(0), np.zeros((0, 0)), 0
    cond = float(s[0] / s[rank - 1]) if rank else float("inf")
    v = vt.T
    null_theta = (d[:, None] * v[:, rank:]).T  # rows: null directions in parameter space
    null_rows = _rref_rows(null_theta) if rank < n else np.zeros((0, n))
    null_space = tuple(Combination(_named(r, names), format_combination(_named(r, names)))
                       for r in null_rows)
    dof = rows - rank
    variance = rss / dof if dof > 0 else float("nan")
    vr = v[:, :rank] / s[:rank][None, :]
    pinv = (d[:, None] * vr) @ (d[:, None] * vr).T  # (JᵀJ)⁺ in parameter units
    if meat is None:
        cov = variance * pinv
    else:
        half = meat @ pinv
        cov = half.T @ half
    in_null = np.any(null_rows != 0, axis=0) if rank < n else np.zeros(n, dtype=bool)
    se: dict[str, float | None] = {}
    reason: dict[str, str] = {}
    for i, name in enumerate(names):
        if in_null[i]:
            se[name] = None
            reason[name] = ("not identifiable on its own: the data determine it only in a "
                            "combination (see identifiability)")
        elif dof <= 0:
            se[name] = None
            reason[name] = "no degrees of freedom left to estimate the residual variance"
        else:
            se[name] = float(np.sqrt(max(cov[i, i], 0.0)))
    combos: list[Combination] = []
    for group in null_groups(null_rows):
        _, sg, vtg = np.linalg.svd(null_rows[:, group])
        k = int(np.sum(sg > 1e-9 * max(1.0, sg[0] if sg.size else 1.0)))
        for c in _rref_rows(vtg[k:]):
            full = np.zeros(n)
            full[group] = c
            coeffs = _named(full, names)
            vec = np.array([coeffs.get(nm, 0.0) for nm in names])
            var = float(vec @ cov @ vec)
            combos.append(Combination(coeffs, format_combination(coeffs),
                                      float(vec @ values),
                                      float(np.sqrt(max(var, 0.0))) if dof > 0 else None))
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sd, sd)
    corr[in_null, :] = np.nan
    corr[:, in_null] = np.nan
    ident = Identifiability(n, rank, tuple(float(x) for x in s), cond, null_space, tuple(combos))
    unc = Uncertainty(variance, dof, names, se, reason, cov, corr)
    return ident, unc


@dataclass(frozen=True)
class Conditioning:
    """How well-conditioned the cost's (Gauss-Newton) Hessian 2·JᵀJ is at one point.

    ``condition_number`` is over the identifiable subspace, with parameters measured in
    units of their nominal scale (exact null directions are reported by
    :class:`Identifiability`).  ``near_null`` names the flattest directions that make it
    large, in the parameters' own units (moving each parameter by its coefficient), each
    with its singular value relative to the largest.
    """

    condition_number: float
    deficiency: int
    near_null: tuple[tuple[Combination, float], ...]

    def to_dict(self) -> dict:
        """Plain-data form."""
        return {"condition_number": self.condition_number, "null_directions": self.deficiency,
                "near_null": [{"direction": c.text, "coefficients": c.coefficients,
                               "relative_singular_value": s} for c, s in self.near_null]}

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> Conditioning:
        """Inverse of :meth:`to_dict`."""
        near = tuple((Combination(dict(d["coefficients"]), d["direction"]),
                      d["relative_singular_value"]) for d in doc["near_null"])
        return cls(_float(doc["condition_number"]), doc["null_directions"], near)


def conditioning(
    r_factor: np.ndarray, rows: int, names: tuple[str, ...], scales: np.ndarray,
    count: int = 3, threshold: float = 1e-3, terms: int = 6,
    gauges: np.ndarray | None = None,
) -> Conditioning:
    """Condition number of the Hessian from R (``JᵀJ = RᵀR``) and its near-null directions.

    Parameters
    ----------
    count
        At most this many near-null directions are named.
    threshold
        A direction is near-null when its singular value is below ``threshold`` times the
        largest (its Hessian eigenvalue below ``threshold²``).
    terms
        At most this many parameters are named per direction (the largest coefficients;
        ``+ ...`` marks the rest).
    gauges
        Directions known to be exactly undeterminable (as in :func:`analyse`), left out.
    """
    if not names:
        return Conditioning(float("nan"), 0, ())
    known = (np.asarray(gauges, dtype=float) / np.asarray(scales)[None, :]
             if gauges is not None else np.zeros((0, len(names))))
    s, vt, rank = known_null_svd(r_factor * np.asarray(scales)[None, :], rows, known)
    if rank == 0:
        return Conditioning(float("inf"), len(names), ())
    cond = float((s[0] / s[rank - 1]) ** 2)
    near = []
    for k in range(rank - 1, max(rank - 1 - count, -1), -1):
        rel = float(s[k] / s[0])
        if rel >= threshold:
            break
        v = np.asarray(scales) * vt[k]
        v = v / np.max(np.abs(v))
        order = [i for i in np.argsort(-np.abs(v)) if abs(v[i]) >= 0.01][:terms]
        coeffs = {names[i]: float(f"{v[i]:.2g}") for i in order}
        text = format_combination(coeffs)
        if np.sum(np.abs(v) >= 0.01) > terms:
            text += " + ..."
        near.append((Combination(coeffs, text), rel))
    return Conditioning(cond, len(names) - rank, tuple(near))
