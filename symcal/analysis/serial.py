"""Serial correlation of a fit's residuals on time-ordered rows, and standard errors that
allow for it.

Consecutive samples of a slow recording, or a drift, make the residuals of neighbouring
rows alike: the rows are then not independent, and standard errors computed as if they
were are too small (two halves of one recording disagree by several of them).

- **detection.** On time-ordered rows (a ``role: time`` column that never decreases),
  the lag-1 autocorrelation ρ̂ of each weighted residual c (about its mean) and its
  statistic ``z = Σ c_i c_{i-1} / sqrt(Σ c_i² c_{i-1}²)``, standard normal under
  independence whether or not the rows' variances differ; the residuals are serially
  correlated when some ``|z|`` exceeds the normal quantile at level :data:`ALPHA`
  (Bonferroni over the constraints).  (``√N·ρ̂`` is that statistic only where every row
  has the same variance: equally weighted rows whose noise differs 7-fold over a sweep
  put it beyond the 1 % threshold on 12 % of independent datasets.)
- **standard errors.** Then the covariance is the heteroscedasticity-and-autocorrelation
  consistent sandwich ``A⁺ M A⁺`` of Newey and West: ``M = Σ_{|l|≤L} (1 − |l|/(L+1)) Γ_l``,
  ``Γ_l = Σ_i s_i s_{i+l}ᵀ`` of the per-row scores ``s_i = J_iᵀ g_i`` (weighted), scaled by
  ``N/(N − rank)``; the bandwidth L is Andrews' for an AR(1) residual,
  ``1.1447 (α N)^⅓`` with ``α = 4ρ²/((1 − ρ)²(1 + ρ)²)`` (ρ the largest lag-1
  autocorrelation, at most 0.97; L at most N/4).  The scores are made chunk by chunk in
  row order, the last L kept between chunks.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from symcal.analysis.bands import normal_quantile

#: Family-wise level of the detection (over a stage's constraints).
ALPHA = 0.01
#: The largest lag-1 autocorrelation the bandwidth rule takes.
RHO_MAX = 0.97


@dataclass(frozen=True)
class SerialCorrelation:
    """What the detection found on a stage's residuals (time-ordered rows only).

    Attributes
    ----------
    constraints
        The stage's constraints, in the order of ``rho``.
    rho
        Lag-1 autocorrelation of each weighted residual.
    threshold
        ``|√N·ρ|`` above which a residual is serially correlated (level :data:`ALPHA`).
    rows
        Observations.
    lags
        The bandwidth L of the HAC standard errors (0: not used).
    z
        Each residual's statistic (see the module); empty: ``√N·ρ`` (a document
        written before it was kept).
    """

    constraints: tuple[str, ...]
    rho: tuple[float, ...]
    threshold: float
    rows: int
    lags: int = 0
    z: tuple[float, ...] = ()

    @property
    def statistics(self) -> tuple[float, ...]:
        """Each residual's ``z`` (``√N·ρ`` where none was kept)."""
        root = math.sqrt(self.rows)
        return self.z if len(self.z) == len(self.rho) else tuple(r * root for r in self.rho)

    @property
    def detected(self) -> bool:
        """Whether some residual is serially correlated."""
        return any(abs(z) > self.threshold for z in self.statistics)

    @property
    def text(self) -> str:
        """In words, for the report."""
        z = self.statistics
        worst = max(range(len(z)), key=lambda k: abs(z[k]))
        where = (f"lag-1 autocorrelation {self.rho[worst]:+.2f} of {self.constraints[worst]} "
                 f"on {self.rows} time-ordered rows, z = {z[worst]:+.2f} (independent rows: "
                 f"|z| < {self.threshold:.3g})")
        if not self.detected:
            return f"no serial correlation: {where}"
        return (f"the residuals are serially correlated ({where}): standard errors by a "
                f"heteroscedasticity-and-autocorrelation-consistent sandwich (Newey-West, "
                f"{self.lags} lags), not as if the rows were independent")

    def to_dict(self) -> dict[str, Any]:
        """Plain data (a stage's ``serial_correlation``)."""
        return {"constraints": list(self.constraints), "rho": list(self.rho),
                "z": list(self.statistics), "threshold": self.threshold, "rows": self.rows,
                "lags": self.lags, "detected": self.detected}

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> SerialCorrelation:
        """Inverse of :meth:`to_dict`."""
        return cls(tuple(doc["constraints"]), tuple(float(r) for r in doc["rho"]),
                   float(doc["threshold"]), int(doc["rows"]), int(doc.get("lags", 0)),
                   tuple(float(z) for z in doc.get("z", ())))


def lag_one(residuals: np.ndarray) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Lag-1 autocorrelation of each column of ``residuals`` (N × n_g), about its mean,
    and its statistic ``z`` (see the module)."""
    return lag_one_of([lag_sums(iter([residuals - residuals.mean(axis=0)]),
                                residuals.shape[1])])


def detect(constraints: tuple[str, ...], residuals: np.ndarray) -> SerialCorrelation:
    """Serial correlation of a fit's weighted residuals (rows in time order)."""
    rho, z = lag_one(residuals)
    return detected(constraints, rho, residuals.shape[0], residuals.shape[1], z)


def detected(constraints: tuple[str, ...], rho: tuple[float, ...], rows: int,
             n_g: int | None = None, z: tuple[float, ...] = ()) -> SerialCorrelation:
    """The detection from lag-1 autocorrelations and their statistics computed elsewhere
    (a log kept as shards reduces them shard by shard, :func:`lag_sums` and
    :func:`lag_one_of`)."""
    n = max(len(constraints) if n_g is None else n_g, 1)
    threshold = normal_quantile(1.0 - ALPHA / (2.0 * n))
    return SerialCorrelation(constraints, rho, threshold, rows, z=z)


@dataclass(frozen=True)
class LagSums:
    """A piece of time-ordered rows' share of the lag-1 autocorrelations: about the mean
    of all rows, ``Σ c²``, ``Σ c_i c_{i-1}`` and ``Σ c_i² c_{i-1}²`` within the piece, its
    first and last row."""

    squares: np.ndarray
    products: np.ndarray
    first: np.ndarray | None
    last: np.ndarray | None
    fourth: np.ndarray | None = None


def lag_sums(centred: Iterator[np.ndarray], n_g: int) -> LagSums:
    """The :class:`LagSums` of a piece's rows, given chunk by chunk in row order, already
    less the mean of all rows (each chunk ``m × n_g``)."""
    squares, products, fourth = np.zeros(n_g), np.zeros(n_g), np.zeros(n_g)
    first: np.ndarray | None = None
    last: np.ndarray | None = None
    for c in centred:
        if not len(c):
            continue
        squares += np.einsum("ma,ma->a", c, c)
        lagged = c[1:] * c[:-1]
        products += lagged.sum(axis=0)
        fourth += np.einsum("ma,ma->a", lagged, lagged)
        if last is not None:
            products += c[0] * last
            fourth += (c[0] * last) ** 2
        if first is None:
            first = c[0].copy()
        last = c[-1].copy()
    return LagSums(squares, products, first, last, fourth)


def lag_one_of(parts: Iterable[LagSums]) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The lag-1 autocorrelations of all rows and their statistics ``z`` from their
    pieces' sums, in row order (as :func:`lag_one`)."""
    squares: np.ndarray | None = None
    products: np.ndarray | None = None
    fourth: np.ndarray | None = None
    last: np.ndarray | None = None
    for p in parts:
        more = p.fourth if p.fourth is not None else np.zeros_like(p.squares)
        squares = p.squares.copy() if squares is None else squares + p.squares
        products = p.products.copy() if products is None else products + p.products
        fourth = more.copy() if fourth is None else fourth + more
        if last is not None and p.first is not None:
            products += p.first * last
            fourth += (p.first * last) ** 2
        last = p.last if p.last is not None else last
    if squares is None or products is None or fourth is None:
        return (), ()
    rho = tuple(float(b) / float(a) if a > 0 else 0.0
                for a, b in zip(squares, products, strict=True))
    z = tuple(float(b) / math.sqrt(float(f)) if f > 0 else 0.0
              for b, f in zip(products, fourth, strict=True))
    return rho, z


def bandwidth(rho: float, rows: int) -> int:
    """Andrews' Bartlett bandwidth for an AR(1) of coefficient ``rho``."""
    r = min(abs(rho), RHO_MAX)
    alpha = 4.0 * r * r / ((1.0 - r) ** 2 * (1.0 + r) ** 2)
    lags = int(math.ceil(1.1447 * (alpha * rows) ** (1.0 / 3.0)))
    return max(1, min(lags, rows // 4))


@dataclass(frozen=True)
class HacPart:
    """One piece's share of the Newey-West sum: the sum within it (:func:`hac_meat`), and
    its first and last ``lags`` rows of scores, for the pairs across pieces."""

    meat: np.ndarray
    head: np.ndarray
    tail: np.ndarray


def hac_part(scores: Iterator[np.ndarray], lags: int, n_free: int) -> HacPart:
    """The :class:`HacPart` of a piece's per-row scores, given chunk by chunk in row order."""
    head: list[np.ndarray] = []
    held = [0]
    tail = [np.zeros((0, n_free))]

    def seen() -> Iterator[np.ndarray]:
        for chunk in scores:
            if held[0] < lags:
                head.append(chunk[:lags - held[0]])
                held[0] += head[-1].shape[0]
            tail[0] = _last(np.vstack([tail[0], chunk]), lags)
            yield chunk

    meat = hac_meat(seen(), lags, n_free)
    return HacPart(meat, np.vstack(head) if head else np.zeros((0, n_free)), tail[0])


def hac_combine(parts: Iterable[HacPart], lags: int, n_free: int) -> np.ndarray:
    """:func:`hac_meat` of all rows from their pieces' parts, in row order: the sums within
    the pieces, and the pairs (at most ``lags`` apart) that straddle their boundaries."""
    meat = np.zeros((n_free, n_free))
    tail = np.zeros((0, n_free))
    for part in parts:
        meat += part.meat
        rows = np.vstack([tail, part.head])
        start = tail.shape[0]
        for lag in range(1, lags + 1):
            # pairs (i - lag, i): i in this piece's head, i - lag among the rows before it
            first, stop = max(start, lag), min(rows.shape[0], start + lag)
            if first >= stop:
                continue
            cross = rows[first - lag:stop - lag].T @ rows[first:stop]
            meat += (1.0 - lag / (lags + 1.0)) * (cross + cross.T)
        tail = _last(np.vstack([tail, part.tail]), lags)
    return meat


def _last(rows: np.ndarray, k: int) -> np.ndarray:
    """The last ``k`` rows (none for 0)."""
    return rows[max(rows.shape[0] - k, 0):] if k > 0 else rows[:0]


def hac_meat(scores: Iterator[np.ndarray], lags: int, n_free: int) -> np.ndarray:
    """``Σ_{|l|≤L} (1 − |l|/(L+1)) Γ_l`` of per-row scores given chunk by chunk in row
    order (each chunk ``m × n_free``).

    The Bartlett weights are a triangle, the correlation of two boxes of L + 1 rows, so the
    sum is ``Σ_e W_eᵀ W_e / (L + 1)`` over the sums ``W_e`` of the scores in every window
    of L + 1 consecutive rows (those that overhang either end included): one product of
    the window sums, whatever L, instead of one per lag.  The windows are differences of
    running sums within each chunk and the last L rows carried to the next."""
    width = lags + 1
    meat = np.zeros((n_free, n_free))
    tail = np.zeros((0, n_free))
    for chunk in scores:
        chunk = np.asarray(chunk, dtype=float).reshape(-1, n_free)
        if not chunk.shape[0]:
            continue
        rows = np.concatenate([tail, chunk]) if tail.shape[0] else chunk
        run = np.cumsum(rows, axis=0)
        start = tail.shape[0]
        # windows ending at each new row e: rows e - L .. e (fewer at the very start), in
        # place in the running sums (slices, not gathers: the same values)
        windows = run[start:]
        first = max(start, width)          # the first row with a full window
        if first < run.shape[0]:
            windows[first - start:] -= run[first - width:run.shape[0] - width]
        meat += windows.T @ windows
        tail = rows[-lags:] if lags else rows[:0]
    # windows overhanging the end: the sums of the last L, L - 1, ..., 1 rows; with fewer
    # than L rows in all, the L + 1 - rows windows that hold every row (and overhang both
    # ends) are all the sum of every row
    suffix = np.cumsum(tail[::-1], axis=0)
    meat += suffix.T @ suffix
    if 0 < tail.shape[0] < lags:
        total = suffix[-1]
        meat += (lags - tail.shape[0]) * np.outer(total, total)
    return meat / width
