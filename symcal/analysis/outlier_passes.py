"""The outliers of a fit on a log kept as shards: :func:`symcal.analysis.outliers.find_outliers`
by passes.

The same rule as in memory (:mod:`symcal.analysis.outliers`), on the same numbers: each
constraint's median and median absolute deviation are exact order statistics found in
passes (:mod:`symcal.analysis.order`), a residual is an outlier beyond
:data:`~symcal.analysis.outliers.THRESHOLD` robust spreads, and one more pass counts them,
sums their share of ``Σ ψ²`` and keeps the :data:`~symcal.analysis.outliers.LISTED`
largest of each piece (the largest of all are among them; rows numbered over the whole
log).  Where outliers dominate a squared fit, the fit is solved again with them set
aside: the flagged residuals are weighted 0 by a :class:`~symcal.solvers.weighed.Aside`
that every pass evaluates from the rows it reads, so no mask of N rows is held either.
Where the fit is weighted by the propagated covariances, the residuals are standardized
by each row's propagated standard deviation, computed in the passes from the rows read
(:class:`Standardized`), and the refit weighs the rows by their ``C_i^-½`` with the
flagged residuals' rows set to 0 (:class:`KeptWeights`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from symcal.analysis.order import Counted, count, medians
from symcal.analysis.outliers import (
    DOMINATE,
    GROSS,
    LISTED,
    MAD_TO_SIGMA,
    REFITS,
    THRESHOLD,
    Outlier,
    Outliers,
)
from symcal.analysis.propagated import Covariances
from symcal.base.numeric import chunks
from symcal.solvers.objective import Source
from symcal.solvers.weighed import (
    Flags,
    LossWeights,
    Residuals,
    RowWeigher,
    map_pieces,
    read_both,
    read_piece,
)

#: ``refit(flags)``: the estimate of the fit solved again with the residuals ``flags``
#: flags weighted 0 (None if it failed).
Refit = Callable[[Flags], "np.ndarray | None"]


@dataclass(frozen=True)
class Standardized:
    """The residual rows ``g/σ`` of a chunk over each row's propagated standard deviation
    ``sqrt(C_i,kk)`` (the covariances at the estimate; 0 where that is 0), as
    :func:`symcal.analysis.outliers.standardize`."""

    rows: Residuals
    covariances: Covariances

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """``m × n_g``."""
        g = self.rows(u)
        sd = np.sqrt(np.diagonal(self.covariances(u), axis1=1, axis2=2))
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(sd > 0, g / np.where(sd > 0, sd, 1.0), 0.0)

    def at(self, theta: np.ndarray) -> Standardized:
        """The residuals at another point, standardized as here."""
        return Standardized(Residuals(self.rows.fn, np.array(theta, dtype=float)),
                            self.covariances)


@dataclass(frozen=True)
class KeptWeights:
    """The fit's row factors (``m × n_g × n_g``) with the rows of the residuals
    ``flags`` flags set to 0: the propagated fit solved again without them."""

    weigher: RowWeigher
    flags: Flags

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """``m × n_g × n_g`` factors."""
        keep = (~self.flags(u)).astype(float)
        return keep[:, :, None] * self.weigher(u)


def _at(rows: Residuals | Standardized, theta: np.ndarray) -> Residuals | Standardized:
    """``rows`` at another point."""
    if isinstance(rows, Standardized):
        return rows.at(theta)
    return Residuals(rows.fn, np.array(theta, dtype=float))


def _raw(rows: Residuals | Standardized) -> Residuals:
    """The residual rows ``g/σ`` themselves."""
    return rows.rows if isinstance(rows, Standardized) else rows


@dataclass(frozen=True)
class Deviations:
    """Residual values of a chunk: ``g`` (or ``|g - centre|``), counted where ``kept`` does
    not flag them (all without it)."""

    rows: Residuals | Standardized
    centre: np.ndarray | None = None
    kept: Flags | None = None

    def __call__(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(values, counted)``."""
        g = self.rows(u)
        v = g if self.centre is None else np.abs(g - self.centre[None, :])
        keep = np.ones(g.shape, dtype=bool) if self.kept is None else ~self.kept(u)
        return v, keep


@dataclass(frozen=True)
class FlaggedZ:
    """The whitened residuals of ``z`` where ``flags`` flags them, as one column."""

    z: Flags
    flags: Flags

    def __call__(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(values, counted)``, ``m·n_g × 1``."""
        return self.z.z(u).reshape(-1, 1), self.flags(u).reshape(-1, 1)


def _spreads(rows: Residuals | Standardized, data: Source, columns: tuple[str, ...],
             kept: Flags | None = None) -> tuple[np.ndarray, np.ndarray, Counted]:
    """Each constraint's median and robust spread (as :func:`~symcal.analysis.outliers.robust_std`:
    1.4826 × the median absolute deviation, the RMS about the median where that is 0; 0
    where no value counts) of the counted residuals."""
    counted = count(Deviations(rows, None, kept), data, columns)
    if counted.nonfinite:
        return np.zeros(counted.n.size), np.zeros(counted.n.size), counted
    centre, _ = medians(Deviations(rows, None, kept), data, columns, counted)
    deviations = Deviations(rows, centre, kept)
    mad, _ = medians(deviations, data, columns, counted)
    spread = MAD_TO_SIGMA * mad
    flat = [k for k, n in enumerate(counted.n) if n and not spread[k] > 0.0]
    if flat:                        # more than half of the values equal: the RMS
        squares = count(Deviations(rows, None, kept), data, columns, centre).squares
        assert squares is not None
        for k in flat:
            spread[k] = float(np.sqrt(squares[k] / counted.n[k]))
    return centre, spread, counted


@dataclass(frozen=True)
class _Listing:
    """A piece's outliers: ``(Σ ψ², Σ ψ² beyond, count per constraint, observations,
    the largest, rows)``, the largest as ``(z, row, constraint, g, weight, time)``."""

    flags: Flags
    weights: LossWeights | None
    columns: tuple[str, ...]
    time: str | None

    def __call__(self, piece: Any) -> tuple[float, float, np.ndarray, int, list[tuple], int]:
        if self.time is None:
            u, t = read_piece(piece, self.columns), None
        else:
            u, times = read_both(piece, self.columns, (self.time,))
            t = times[0]
        total = share = 0.0
        by = np.zeros(self.flags.centre.size, dtype=np.int64)
        observations = 0
        top: list[tuple] = []
        for part in chunks(u.shape[1]):
            block = u[:, part]
            v = self.flags.rows(block)
            g = _raw(self.flags.rows)(block) if isinstance(self.flags.rows, Standardized) \
                else v
            z = self.flags.z(block)
            w = np.ones_like(g) if self.weights is None else self.weights(block)
            psi2 = (w * v) ** 2
            beyond = z > THRESHOLD
            total += float(np.sum(psi2))
            share += float(np.sum(psi2[beyond]))
            by += beyond.sum(axis=0)
            observations += int(np.any(beyond, axis=1).sum())
            rows, cols = np.nonzero(beyond)
            order = np.argsort(-z[rows, cols], kind="stable")[:LISTED]
            top += [(float(z[rows[i], cols[i]]), int(rows[i]) + part.start, int(cols[i]),
                     float(g[rows[i], cols[i]]), float(w[rows[i], cols[i]]),
                     None if t is None else float(t[part][rows[i]]))
                    for i in order]
            top = sorted(top, key=lambda o: (-o[0], o[1], o[2]))[:LISTED]
        return total, share, by, observations, top, u.shape[1]


def find_outliers_passes(
    dataset: str,
    names: tuple[str, ...],
    units: tuple[str, ...],
    to_display: np.ndarray,
    rows: Residuals,
    data: Source,
    columns: tuple[str, ...],
    weights: LossWeights | None,
    loss: str,
    time: str | None = None,
    refit: Refit | None = None,
    covariances: Covariances | None = None,
) -> Outliers | None:
    """The outliers of one fit, by passes (see the module): as
    :func:`~symcal.analysis.outliers.find_outliers` on the residual rows ``rows`` of
    ``data`` (the problem's ``columns``), ``weights`` the fit's final IRLS weights (power
    1; None for squared residuals), ``time`` the time column's name, ``covariances`` the
    propagated covariances at the estimate where the fit is weighted by them (the
    residuals standardized by their rows' standard deviations).  None where a residual
    is not finite."""
    raw_centre, raw_spread, counted = _spreads(rows, data, columns)
    if counted.nonfinite:
        return None
    tested: Residuals | Standardized = rows
    centre, spread = raw_centre, raw_spread
    if covariances is not None:
        tested = Standardized(rows, covariances)
        centre, spread, counted = _spreads(tested, data, columns)
        if counted.nonfinite:
            return None
    flags = Flags(tested, centre, spread, THRESHOLD)  # type: ignore[arg-type]
    parts = map_pieces(_Listing(flags, weights, columns, time), data, "outliers")
    total = sum(p[0] for p in parts)
    inside = sum(p[1] for p in parts)
    share = inside / total if total > 0 else 0.0
    by = np.sum([p[2] for p in parts], axis=0)
    top: list[tuple] = []
    offset = 0
    for p in parts:
        top += [(z, row + offset, *rest) for z, row, *rest in p[4]]
        offset += p[5]
    top = sorted(top, key=lambda o: (-o[0], o[1], o[2]))[:LISTED]
    listed = tuple(Outlier(dataset, row, tm, names[k], g * float(to_display[k]), units[k], z,
                           w)
                   for z, row, k, g, w, tm in top)
    clean, gross = None, False
    if refit is not None and weights is None and share > DOMINATE:
        measured = _without_outliers(flags, data, columns, refit)
        if measured is not None:
            clean = {nm: float(s * f)
                     for nm, s, f in zip(names, measured[0], to_display, strict=True)}
            gross = measured[1]
    n = int(offset)
    return Outliers(dataset, loss,
                    {nm: float(s * f) for nm, s, f in zip(names, raw_spread, to_display,
                                                         strict=True)},
                    dict(zip(names, units, strict=True)), int(by.sum()), n * len(names),
                    {nm: int(by[k]) for k, nm in enumerate(names)},
                    int(sum(p[3] for p in parts)), share, listed, clean, gross,
                    None if covariances is None
                    else {nm: float(s) for nm, s in zip(names, spread, strict=True)})


@dataclass(frozen=True)
class _Changed:
    """A piece's ``(residuals flagged differently by a and b, flagged by b)``."""

    a: Flags
    b: Flags
    columns: tuple[str, ...]

    def __call__(self, piece: Any) -> tuple[int, int]:
        u = read_piece(piece, self.columns)
        changed = flagged = 0
        for part in chunks(u.shape[1]):
            fb = self.b(u[:, part])
            changed += int(np.sum(self.a(u[:, part]) != fb))
            flagged += int(np.sum(fb))
        return changed, flagged


def _without_outliers(flags: Flags, data: Source, columns: tuple[str, ...], refit: Refit
                      ) -> tuple[np.ndarray, bool] | None:
    """As :func:`symcal.analysis.outliers._without_outliers`, the masks :class:`Flags`
    evaluated in the passes: each constraint's robust spread of the residuals kept once
    the fit is solved again without the flagged ones, flagged again until they stay the
    same; and whether the outliers are gross."""
    flagged = flags
    again = used = flags
    for _ in range(REFITS):
        used = flagged                    # the residuals set aside by this refit
        theta = refit(flagged)
        if theta is None:
            return None
        rows = _at(flags.rows, theta)
        centre, spread, counted = _spreads(rows, data, columns, kept=flagged)
        if counted.nonfinite:
            return None
        centre = np.where(counted.n > 0, centre, 0.0)
        again = Flags(rows, centre, spread, THRESHOLD)  # type: ignore[arg-type]
        parts = map_pieces(_Changed(flagged, again, columns), data, "outliers_again")
        if sum(p[0] for p in parts) == 0 or sum(p[1] for p in parts) == 0:
            break
        flagged = again
    mask = count(FlaggedZ(again, flagged), data, columns)
    gross = False
    if int(mask.n[0]):
        median, _ = medians(FlaggedZ(again, flagged), data, columns, mask)
        gross = float(median[0]) > GROSS
    if isinstance(again.rows, Standardized):     # the spread of the residuals themselves
        spread = _spreads(_raw(again.rows), data, columns, kept=used)[1]
        return spread, gross
    return again.spread, gross
