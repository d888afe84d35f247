"""Exact order statistics (medians) of per-row values by passes, in bounded memory.

A median needs every value at once; a log kept as shards has them only one piece at a
time.  The k-th smallest value is found exactly by narrowing an interval that holds it:
one pass counts the values and their range; each further pass histograms the values
inside the interval on :data:`BINS` equal bins, and the interval becomes the bin that
holds rank k (its count known), until at most :data:`GATHER` values lie inside, which
the next pass gathers and sorts.  An interval whose values are all equal ends at once.
Each pass is a task per piece (:func:`symcal.solvers.weighed.map_pieces`) returning
counts, so memory is bounded by :data:`BINS` and :data:`GATHER` per wanted rank, and the
result is the value :func:`numpy.median` gives on all rows at once.

The values come from a :class:`Values`: per chunk of observations, an ``m × width``
array and which of its entries count (the residuals kept by a fit, say).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np

from symcal.base.numeric import chunks
from symcal.solvers.objective import Source
from symcal.solvers.weighed import map_pieces, read_piece

#: Bins of a histogram pass.
BINS = 4096
#: A rank's interval is gathered once it holds at most this many values.
GATHER = 1 << 16
#: Most passes of one selection (then the interval is gathered whatever its count).
MAX_PASSES = 40


class Values(Protocol):
    """The values of a chunk of observations (picklable)."""

    def __call__(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(values, counted)``: ``m × width`` each, the second boolean."""
        ...


@dataclass(frozen=True)
class Counted:
    """What the first pass finds per column of values: how many count (finite), their
    range, and how many values are not finite (counted or not)."""

    n: np.ndarray
    low: np.ndarray
    high: np.ndarray
    nonfinite: int
    squares: np.ndarray | None = None


@dataclass(frozen=True)
class _Range:
    """The first pass's task: per column the count, min, max; the non-finite values."""

    values: Values
    columns: tuple[str, ...]
    centre: np.ndarray | None = None     # also Σ (v - centre)² of the counted values

    def __call__(self, piece: Any) -> Counted:
        u = read_piece(piece, self.columns)
        out: Counted | None = None
        for part in chunks(u.shape[1]):
            v, keep = self.values(u[:, part])
            finite = np.isfinite(v)
            bad = int(np.sum(~finite))
            keep = keep & finite
            width = v.shape[1]
            lo = np.array([v[keep[:, k], k].min(initial=np.inf) for k in range(width)])
            hi = np.array([v[keep[:, k], k].max(initial=-np.inf) for k in range(width)])
            sq = None
            if self.centre is not None:
                d = np.where(keep, v - self.centre[None, :], 0.0)
                sq = np.sum(d * d, axis=0)
            here = Counted(keep.sum(axis=0), lo, hi, bad, sq)
            out = here if out is None else _join(out, here)
        return out if out is not None else Counted(np.zeros(0, int), np.zeros(0),
                                                   np.zeros(0), 0)


def _join(a: Counted, b: Counted) -> Counted:
    if not a.n.size:
        return b
    if not b.n.size:
        return a
    sq = None if a.squares is None or b.squares is None else a.squares + b.squares
    return Counted(a.n + b.n, np.minimum(a.low, b.low), np.maximum(a.high, b.high),
                   a.nonfinite + b.nonfinite, sq)


def count(values: Values, data: Source, columns: tuple[str, ...],
          centre: np.ndarray | None = None) -> Counted:
    """The first pass (one task per piece): counts, ranges, the non-finite values, and
    with ``centre`` each column's ``Σ (v - centre)²``."""
    parts = map_pieces(_Range(values, columns, centre), data, "order_count")
    out = parts[0]
    for p in parts[1:]:
        out = _join(out, p)
    return out


@dataclass(frozen=True)
class _Target:
    """One wanted rank of one column: the interval ``[lo, hi)`` (``hi`` included when
    ``closed``) that holds it, the values below ``lo`` and inside it."""

    column: int
    rank: int
    lo: float
    hi: float
    closed: bool
    below: int
    inside: int
    value: float | None = None

    def holds(self, v: np.ndarray) -> np.ndarray:
        """Which of ``v`` lie inside the interval."""
        upper = (v <= self.hi) if self.closed else (v < self.hi)
        return (v >= self.lo) & upper

    @property
    def gather(self) -> bool:
        """Whether the next pass gathers the interval's values."""
        return self.inside <= GATHER


@dataclass(frozen=True)
class _Narrow:
    """A pass's task: for each target, the histogram (or the values) of its interval,
    and the interval's smallest and largest value."""

    values: Values
    columns: tuple[str, ...]
    targets: tuple[_Target, ...]
    edges: tuple[np.ndarray | None, ...]

    def __call__(self, piece: Any) -> list[tuple[Any, float, float]]:
        u = read_piece(piece, self.columns)
        out: list[tuple[Any, float, float]] = [
            (None if e is None else np.zeros(BINS, dtype=np.int64), np.inf, -np.inf)
            for e in self.edges]
        gathered: list[list[np.ndarray]] = [[] for _ in self.targets]
        for part in chunks(u.shape[1]):
            v, keep = self.values(u[:, part])
            keep = keep & np.isfinite(v)
            for i, (t, e) in enumerate(zip(self.targets, self.edges, strict=True)):
                col = v[keep[:, t.column], t.column]
                inside = col[t.holds(col)]
                hist, lo, hi = out[i]
                if inside.size:
                    lo, hi = min(lo, float(inside.min())), max(hi, float(inside.max()))
                if e is None:
                    gathered[i].append(inside)
                else:
                    idx = np.clip(np.searchsorted(e, inside, side="right") - 1, 0, BINS - 1)
                    hist = hist + np.bincount(idx, minlength=BINS)
                out[i] = (hist, lo, hi)
        result = []
        for i, e in enumerate(self.edges):
            hist, lo, hi = out[i]
            if e is None:
                hist = np.concatenate(gathered[i]) if gathered[i] else np.zeros(0)
            result.append((hist, lo, hi))
        return result


def select(values: Values, data: Source, columns: tuple[str, ...], counted: Counted,
           wanted: list[tuple[int, int]]) -> list[float]:
    """The values of rank ``k`` (0-based, among the counted finite values of column
    ``c``) for each ``(c, k)`` of ``wanted``, exactly; ``counted`` from :func:`count`."""
    targets = [_Target(c, k, float(counted.low[c]), float(counted.high[c]), True, 0,
                       int(counted.n[c])) for c, k in wanted]
    targets = [t if t.lo < t.hi else replace(t, value=t.lo) for t in targets]
    for step in range(MAX_PASSES + 1):
        active = [i for i, t in enumerate(targets) if t.value is None]
        if not active:
            break
        last = step == MAX_PASSES
        chosen = tuple(targets[i] for i in active)
        edges = tuple(None if (t.gather or last) else np.linspace(t.lo, t.hi, BINS + 1)
                      for t in chosen)
        parts = map_pieces(_Narrow(values, columns, chosen, edges), data, "order_select")
        for j, i in enumerate(active):
            t, e = targets[i], edges[j]
            lo = min(p[j][1] for p in parts)
            hi = max(p[j][2] for p in parts)
            if e is None:
                inside = np.sort(np.concatenate([p[j][0] for p in parts]))
                targets[i] = replace(t, value=float(inside[t.rank - t.below]))
                continue
            if lo == hi:            # every value inside is the same: that is the rank's
                targets[i] = replace(t, value=lo)
                continue
            hist = np.sum([p[j][0] for p in parts], axis=0)
            cum = np.cumsum(hist)
            b = int(np.searchsorted(cum, t.rank - t.below, side="right"))
            targets[i] = replace(t, lo=float(e[b]), hi=float(e[b + 1]),
                                 closed=t.closed and b == BINS - 1,
                                 below=t.below + (int(cum[b - 1]) if b else 0),
                                 inside=int(hist[b]))
    return [float(t.value) for t in targets]   # type: ignore[arg-type]


def medians(values: Values, data: Source, columns: tuple[str, ...],
            counted: Counted | None = None) -> tuple[np.ndarray, Counted]:
    """Each column's median of its counted values (as :func:`numpy.median`; 0 where none
    count), and the first pass's :class:`Counted`."""
    counted = counted if counted is not None else count(values, data, columns)
    wanted: list[tuple[int, int]] = []
    for c, n in enumerate(counted.n):
        if n:
            wanted += [(c, (int(n) - 1) // 2), (c, int(n) // 2)]
    got = iter(select(values, data, columns, counted, wanted))
    out = np.zeros(len(counted.n))
    for c, n in enumerate(counted.n):
        if n:
            a, b = next(got), next(got)
            out[c] = a if int(n) % 2 else (a + b) / 2.0
    return out, counted
