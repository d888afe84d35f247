"""Where the model fails: structure of a residual along candidate variables.

For a residual series r and a variable v (a data column, a sensor input or output, a
named expression, or the phase of a periodic quantity modulo its period), the binned
means of r over v show where r departs from zero, and the correlation ratio
η² = (variance of the bin means, weighted) / (variance of r) says how much of r the
variable explains.  For periodic quantities a Lomb–Scargle periodogram (the sampling is
uneven) names the dominant frequency in cycles per period.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.signal

from symcal.base.units import DISPLAY_UNITS


@dataclass(frozen=True)
class Variable:
    """A candidate variable evaluated on one dataset.

    ``period`` is set for periodic quantities (e.g. a platen reading, period one tooth
    pitch); ``role`` is a data column's declared role (``time``, ``axis`` or "").
    """

    name: str
    values: np.ndarray
    unit: str = ""
    period: float | None = None
    kind: str = "column"
    role: str = ""


@dataclass(frozen=True)
class Binned:
    """Binned means of a residual along one variable."""

    variable: str
    centers: np.ndarray
    mean: np.ndarray
    sem: np.ndarray
    eta2: float

    def to_dict(self, scale: float = 1.0) -> dict:
        """Plain-data form; residual values divided by ``scale`` (display unit)."""
        return {"variable": self.variable, "centers": self.centers.tolist(),
                "mean": (self.mean / scale).tolist(), "sem": (self.sem / scale).tolist(),
                "eta2": self.eta2}


@dataclass(frozen=True)
class Periodogram:
    """Lomb–Scargle power of a residual against a periodic variable."""

    variable: str
    period: float
    frequency: np.ndarray
    power: np.ndarray
    peak_frequency: float
    unit_text: str

    @property
    def peak_text(self) -> str:
        """E.g. ``"3 cycles per tooth pitch of s2.p"``."""
        f = self.peak_frequency
        shown = f"{f:.0f}" if abs(f - round(f)) < 0.05 else f"{f:.2f}"
        return f"{shown} {'cycle' if shown == '1' else 'cycles'} {self.unit_text}"

    def to_dict(self) -> dict:
        """Plain-data form."""
        return {"variable": self.variable, "period": self.period, "unit_text": self.unit_text,
                "frequency": self.frequency.tolist(), "power": self.power.tolist(),
                "peak": {"frequency": self.peak_frequency, "text": self.peak_text}}


def binned(r: np.ndarray, v: np.ndarray, name: str, bins: int = 20) -> Binned | None:
    """Binned means of ``r`` along ``v`` (equal-count bins); None if ``v`` is constant."""
    if np.ptp(v) <= 1e-12 * max(1.0, float(np.max(np.abs(v)))) or len(v) < 2 * bins:
        return None
    edges = np.quantile(v, np.linspace(0, 1, bins + 1))
    edges = np.unique(edges)
    if len(edges) < 4:
        return None
    index = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, len(edges) - 2)
    count = np.bincount(index, minlength=len(edges) - 1).astype(float)
    keep = count > 1
    total = np.bincount(index, weights=r, minlength=len(edges) - 1)
    squares = np.bincount(index, weights=r * r, minlength=len(edges) - 1)
    mean = np.where(keep, total / np.maximum(count, 1), np.nan)
    var = np.where(keep, squares / np.maximum(count, 1) - mean**2, np.nan)
    sem = np.sqrt(np.clip(var, 0, None) / np.maximum(count - 1, 1))
    centers = np.bincount(index, weights=v, minlength=len(edges) - 1) / np.maximum(count, 1)
    spread = float(np.var(r))
    explained = float(np.nansum(count * (mean - r.mean()) ** 2) / len(r))
    eta2 = explained / spread if spread > 0 else 0.0
    return Binned(name, centers[keep], mean[keep], sem[keep], eta2)


@dataclass(frozen=True)
class Left:
    """What a residual above its noise floor does along one variable or a pair of them:
    the variance its binned means explain beyond what bins explain by chance
    (``explained``, internal units²), as a share of the residual's excess over its floor
    (``share``), and its correlation ratio ``eta2``."""

    variables: tuple[str, ...]
    explained: float
    share: float
    eta2: float

    @property
    def text(self) -> str:
        """E.g. ``62 % along phase of s2.p (mod 1.016 mm)`` or ``18 % along (p2, t)``."""
        where = self.variables[0] if len(self.variables) == 1 else \
            f"({', '.join(self.variables)}) together"
        return f"{self.share:.0%} along {where}"

    def to_dict(self, scale: float = 1.0) -> dict:
        """Plain data; the explained standard deviation in a unit of size ``scale``."""
        return {"variables": list(self.variables), "share": self.share, "eta2": self.eta2,
                "explained_std": float(np.sqrt(max(self.explained, 0.0))) / scale}


def _cells(r: np.ndarray, index: np.ndarray, cells: int) -> tuple[float, int]:
    """Variance of ``r`` its cell means explain (weighted by count), and the cells used."""
    count = np.bincount(index, minlength=cells).astype(float)
    total = np.bincount(index, weights=r, minlength=cells)
    used = count > 0
    mean = total[used] / count[used]
    return float(np.sum(count[used] * (mean - r.mean()) ** 2) / len(r)), int(np.sum(used))


def _bin_index(v: np.ndarray, bins: int) -> np.ndarray | None:
    """Equal-count bin of each value (None: too few distinct values)."""
    edges = np.unique(np.quantile(v, np.linspace(0, 1, bins + 1)))
    if len(edges) < 3:
        return None
    return np.clip(np.searchsorted(edges, v, side="right") - 1, 0, len(edges) - 2)


def what_is_left(r: np.ndarray, variables: list[Variable], floor_variance: float,
                 top: int = 3, bins: int = 20, pair_bins: int = 6,
                 pairs_of: int = 6) -> list[Left]:
    """The variables and pairs of variables along which a residual's excess over its noise
    floor lies, non-parametrically: the variance of its binned means (equal-count bins,
    ``bins`` along one variable, ``pair_bins`` × ``pair_bins`` along a pair of the
    ``pairs_of`` strongest variables) less what as many bins explain by chance
    (``(bins - 1)/N`` of its variance), as a share of ``var(r) - floor_variance``; best
    first.  Empty when the residual is not above its floor."""
    n = len(r)
    spread = float(np.var(r))
    excess = spread - floor_variance
    if n < 4 * bins or excess <= 0 or spread <= 0:
        return []
    singles: list[tuple[Left, np.ndarray]] = []
    for var in variables:
        for cand in [var] + ([phase_variable(var)] if var.period else []):
            index = _bin_index(cand.values, bins)
            if index is None:
                continue
            explained, used = _cells(r, index, bins)
            beyond = explained - (used - 1) / n * spread
            singles.append((Left((cand.name,), beyond, beyond / excess, explained / spread),
                            cand.values))
    singles.sort(key=lambda item: -item[0].share)
    found = [left for left, _ in singles]
    strongest = singles[:pairs_of]
    for i, (a, va) in enumerate(strongest):
        ia = _bin_index(va, pair_bins)
        for b, vb in strongest[i + 1:]:
            ib = _bin_index(vb, pair_bins)
            if ia is None or ib is None:
                continue
            if _affine_in(r, va, vb):
                continue        # the residual is written with them: trivially "along"
            explained, used = _cells(r, ia * pair_bins + ib, pair_bins * pair_bins)
            beyond = explained - (used - 1) / n * spread
            found.append(Left((*a.variables, *b.variables), beyond, beyond / excess,
                              explained / spread))
    found = [f for f in found if f.share > 0]
    found.sort(key=lambda f: -f.share)
    return found[:top]


#: A residual is written with a set of variables where their affine fit leaves at most
#: this share of its norm: rounding, not structure (a count of 1e7 less its nominal value
#: cancels 8 digits; a residual at its floor leaves its noise, about all of it).
AFFINE = 1e-3


def _affine_in(r: np.ndarray, *columns: np.ndarray) -> bool:
    """Whether ``r`` is an affine combination of ``columns`` to rounding: a residual
    ``nA/(f0·tau) − 1 − A.y`` (tau a constant column) is, of the reading nA and the output
    A.y; binned along the pair it is "10970 % of its excess along (nA, A.y) together"
    (a new user's clock lab), which says nothing."""
    a = np.column_stack([np.ones_like(r), *columns])
    if not np.all(np.isfinite(a)):
        return False
    scale = np.linalg.norm(a, axis=0)
    scale[scale == 0] = 1.0
    coef, *_ = np.linalg.lstsq(a / scale, r, rcond=None)
    return float(np.linalg.norm(r - (a / scale) @ coef)) <= AFFINE * float(np.linalg.norm(r))


def phase_variable(var: Variable) -> Variable:
    """The phase ``v mod period`` of a periodic variable."""
    assert var.period is not None
    shown = var.period / DISPLAY_UNITS[var.unit]   # values are internal; shown as declared
    return Variable(f"phase of {var.name} (mod {shown:g} {var.unit})".replace(" )", ")"),
                    np.mod(var.values, var.period), var.unit, None, "phase")


def structure(r: np.ndarray, variables: list[Variable], top: int = 3) -> list[Binned]:
    """The variables along which ``r`` shows most structure, by η², best first.

    η² of a variable with B bins is about (B - 1)/N by chance alone; variables are ranked
    by η² above that level.
    """
    found = []
    for var in variables:
        candidates = [var] + ([phase_variable(var)] if var.period else [])
        for cand in candidates:
            b = binned(r, cand.values, cand.name)
            if b is not None:
                found.append(b)
    found.sort(key=lambda b: -b.eta2)
    return found[:top]


def periodogram(r: np.ndarray, var: Variable, max_cycles: float = 12.0,
                unit_text: str | None = None) -> Periodogram | None:
    """Lomb–Scargle periodogram of ``r`` against periodic ``var``, in cycles per period."""
    if var.period is None or np.ptp(var.values) < 2 * var.period:
        return None
    steps = np.diff(np.unique(var.values))
    if steps.size and np.std(steps) < 0.1 * np.mean(steps):  # evenly spaced: alias beyond
        max_cycles = min(max_cycles, 0.9 * var.period / (2 * float(np.mean(steps))))
    if max_cycles <= 0.5:
        return None
    cycles = np.linspace(0.25, max_cycles, int(max_cycles * 40))
    angular = 2 * np.pi * cycles / var.period
    power = scipy.signal.lombscargle(var.values, r - r.mean(), angular, normalize=True)
    peak = float(cycles[int(np.argmax(power))])
    text = unit_text or (f"per period ({var.period / DISPLAY_UNITS[var.unit]:g} {var.unit}) "
                         f"of {var.name}")
    return Periodogram(var.name, var.period, cycles, power, peak, text)
