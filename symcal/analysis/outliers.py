"""The observations a fit treats as outliers, whatever its loss.

Each constraint's residual ``g/σ`` at the estimate, less its median, is whitened by a
robust estimate of its spread (1.4826 × the median absolute deviation from the median,
which a few gross errors do not move; the RMS where more than half of the residuals are
equal).  Where the fit weighs each row by the covariance propagated from its readings'
declared noise (``weighting: propagated``), a row's residual is first divided by its
own propagated standard deviation ``sqrt(C_i,kk)`` (*standardized*, as least-squares
adjustment standardizes its residuals for the w-test; the parameters' leverage, about
p/N, is neglected): the noise of such rows may differ by orders of magnitude (a
thermistor's 1 to 25 mK across its range), and one spread for all of them would flag
the noisiest rows of clean data.  The robust spread of the standardized residuals (near 1
where the noise is as declared) then takes the place of the residual's.  A residual row is
an outlier when its whitened residual exceeds :data:`THRESHOLD` (a Gaussian residual does
so with probability 6e-7).  The outliers *dominate* when they carry more than
:data:`DOMINATE` of the fit's influence ``Σ ψ²``, ``ψ = w g`` each row's contribution to
the gradient (``w`` the final weight of a robust loss, 1 for squared residuals; ``g`` the
standardized residual where there is one): with squared residuals that is their share of
the cost Σ (g/σ)² (of the propagated fit's cost, one constraint per row); a robust loss
that down-weights them leaves them a small share.

The remedy (:func:`remedy_yaml`) must work when applied as printed.  The squared fit's
residuals are a poor guide to the noise: the outliers pull the estimate, and the
structure they leave inflates every residual's spread (count slips of 1 % of the rows
inflate it five to ten times).  So where outliers dominate a squared fit, the fit is
repeated with the flagged residuals set aside (a weight of 0), the outliers are flagged
again against that fit, and so on until they stay the same (:data:`REFITS` at most): the
robust spread of the residuals kept then measures the noise (``clean_std``).  Outliers
beyond :data:`GROSS` such spreads are gross, and the remedy is a redescending loss
(Cauchy, whose weight falls as ``1/(1 + z)``: a gross error has almost none) at
:data:`CAUCHY_SCALE` spreads; milder ones get Huber at :data:`HUBER_SCALE` spreads (both
95 % efficient on Gaussian noise).  Measured on the platen problem with count slips of
1 % and 5 % of the rows, at worst over every parameter: the printed Cauchy loss lands
0.34-0.77 standard errors from a squared fit without the slipped rows (seeds 11 and
14-20); the former Huber at twice the squared fit's spread 3.8-89 (seeds 11-13).

Where the residuals were standardized, the outliers are flagged and refitted on the
standardized residuals (the refit keeps the propagated weights, the flagged residuals'
set to 0), but the remedy's scale is still the robust spread of the residual itself, in
its unit (``clean_std``): symcal does not combine a robust loss with the propagated
weighting, so the loss printed replaces it by equal weights, and its one scale is a
spread of the residual as written.  On heteroscedastic rows that loss is a compromise
(the noisiest rows are down-weighted with the outliers); the report says so.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

#: A whitened residual beyond this many robust standard deviations is an outlier.
THRESHOLD = 5.0
#: Outliers dominate when they carry more than this share of Σ ψ².
DOMINATE = 0.5
#: At most this many outliers are listed (the largest; all are counted).
LISTED = 20
#: The median absolute deviation of a Gaussian is this fraction of its σ (1/1.4826).
MAD_TO_SIGMA = 1.482602218505602
#: Most refits with the flagged residuals set aside (see the module docstring).
REFITS = 5
#: Outliers are gross when the median of them lies beyond this many spreads of the
#: residuals kept.
GROSS = 10.0
#: The scales of the suggested losses in spreads of the residuals kept: Cauchy and
#: Huber are 95 % efficient on Gaussian noise at 2.3849 and 1.345 σ.
CAUCHY_SCALE = 2.3849
HUBER_SCALE = 1.345
#: ``refit(aside)``: the residual rows ``g/σ`` (``N × n_g``) of the fit solved again with
#: the residuals ``aside`` (a boolean ``N × n_g`` mask) weighted 0; None if it failed.
Refit = Callable[[np.ndarray], "np.ndarray | None"]


@dataclass(frozen=True)
class Outlier:
    """One residual row beyond the threshold.

    ``row`` counts the dataset's observations from 0 (rows dropped as invalid not
    counted); ``time`` is the value of the column declared ``role: time`` (None without
    one); ``residual`` is in the constraint's display unit; ``whitened`` is the residual
    over its robust standard deviation; ``weight`` is the fit's final weight of the row
    (1 for squared residuals).
    """

    dataset: str
    row: int
    time: float | None
    constraint: str
    residual: float
    unit: str
    whitened: float
    weight: float

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form."""
        return {"dataset": self.dataset, "row": self.row, "time": self.time,
                "constraint": self.constraint, "residual": self.residual,
                "unit": self.unit or "(internal)", "whitened": self.whitened,
                "weight": self.weight}

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> Outlier:
        """Inverse of :meth:`to_dict`."""
        unit = "" if doc["unit"] == "(internal)" else doc["unit"]
        return cls(doc["dataset"], doc["row"], doc["time"], doc["constraint"],
                   doc["residual"], unit, doc["whitened"], doc["weight"])


@dataclass(frozen=True)
class Outliers:
    """What one stage's fit treats as outliers.

    Attributes
    ----------
    dataset
        The dataset fitted.
    loss
        ``"squared"`` or the robust losses in words.
    robust_std
        Each constraint's robust standard deviation of ``g`` in its display unit.
    units
        Each constraint's display unit.
    count, rows
        Outlying residual rows and all residual rows.
    by_constraint
        Outlying rows of each constraint.
    observations
        Observations with at least one outlying row.
    share
        Their share of Σ ψ² (see the module docstring).
    listed
        The largest, at most :data:`LISTED`, largest whitened residual first.
    clean_std
        Where outliers dominate a squared fit: each constraint's robust standard
        deviation (display unit) of the residuals kept once the fit is solved again
        without the outliers (see the module docstring); else None.
    gross
        Whether the outliers lie beyond :data:`GROSS` of those spreads (a redescending
        loss is then the remedy).
    standardized_std
        Where each row's residual was divided by its propagated standard deviation
        before the test (see the module docstring): each constraint's robust standard
        deviation of those standardized residuals (near 1 where the noise is as
        declared), which the threshold multiplies; else None (the threshold multiplies
        ``robust_std``).
    """

    dataset: str
    loss: str
    robust_std: dict[str, float]
    units: dict[str, str]
    count: int
    rows: int
    by_constraint: dict[str, int]
    observations: int
    share: float
    listed: tuple[Outlier, ...]
    clean_std: dict[str, float] | None = None
    gross: bool = False
    standardized_std: dict[str, float] | None = None

    @property
    def dominate(self) -> bool:
        """Whether the outliers carry more than :data:`DOMINATE` of Σ ψ²."""
        return self.share > DOMINATE

    @property
    def squared(self) -> bool:
        """Whether the fit used squared residuals only."""
        return self.loss == "squared"

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form."""
        return {"dataset": self.dataset, "loss": self.loss, "threshold": THRESHOLD,
                "robust_std": dict(self.robust_std),
                "units": {k: v or "(internal)" for k, v in self.units.items()},
                "count": self.count, "rows": self.rows,
                "by_constraint": dict(self.by_constraint), "observations": self.observations,
                "share": self.share, "dominate": self.dominate,
                "listed": [o.to_dict() for o in self.listed],
                "clean_std": None if self.clean_std is None else dict(self.clean_std),
                "gross": self.gross,
                "standardized_std": None if self.standardized_std is None
                else dict(self.standardized_std)}

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> Outliers:
        """Inverse of :meth:`to_dict`."""
        units = {k: "" if v == "(internal)" else v for k, v in doc["units"].items()}
        clean = doc.get("clean_std")
        standardized = doc.get("standardized_std")
        return cls(doc["dataset"], doc["loss"], dict(doc["robust_std"]), units,
                   doc["count"], doc["rows"], dict(doc["by_constraint"]),
                   doc["observations"], doc["share"],
                   tuple(Outlier.from_dict(o) for o in doc["listed"]),
                   None if clean is None else dict(clean), bool(doc.get("gross", False)),
                   None if standardized is None else dict(standardized))


def robust_std(values: np.ndarray) -> float:
    """1.4826 × the median absolute deviation from the median; the RMS about the median
    where that is 0 (more than half of the values equal)."""
    if values.size == 0:
        return 0.0
    centre = float(np.median(values))
    mad = MAD_TO_SIGMA * float(np.median(np.abs(values - centre)))
    if mad > 0.0:
        return mad
    return float(np.sqrt(np.mean((values - centre) ** 2)))


def standardize(g: np.ndarray, sd: np.ndarray | None) -> np.ndarray:
    """``g`` over each row's propagated standard deviation ``sd`` (0 where that is 0: a
    row its readings leave exact); ``g`` itself without ``sd``."""
    if sd is None:
        return g
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(sd > 0, g / np.where(sd > 0, sd, 1.0), 0.0)


def find_outliers(
    dataset: str,
    names: tuple[str, ...],
    units: tuple[str, ...],
    to_display: np.ndarray,
    g: np.ndarray,
    weights: np.ndarray | None,
    loss: str,
    time: np.ndarray | None = None,
    refit: Refit | None = None,
    sd: np.ndarray | None = None,
) -> Outliers:
    """The outliers of one fit.

    Parameters
    ----------
    dataset
        The dataset's name.
    names, units
        The constraints and their display units.
    to_display
        Per constraint, the factor from a row ``g/σ`` to the display unit (σ over the
        unit's size).
    g
        Residual rows ``g/σ`` at the estimate (``N × n_g``).
    weights
        The fit's final weights (``N × n_g``; None for squared residuals).
    loss
        The loss in words (``"squared"`` without a robust one).
    time
        The time of each observation (None: unknown).
    refit
        Solves the fit again with some residuals set aside (:data:`Refit`): where
        outliers dominate a squared fit, to measure the noise without them
        (``clean_std``, ``gross``).  None: not measured.
    sd
        Each row's propagated standard deviation of ``g`` (``N × n_g``, the units of
        ``g``) where the fit is weighted by it: the residuals are standardized by it
        before the test (see the module docstring).  None: one spread for all rows.

    Returns
    -------
    Outliers
    """
    n, ng = g.shape
    u = standardize(g, sd)
    raw = np.array([robust_std(g[:, k]) for k in range(ng)])
    stds = raw if sd is None else np.array([robust_std(u[:, k]) for k in range(ng)])
    centre = np.median(u, axis=0) if n else np.zeros(ng)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(stds[None, :] > 0, np.abs(u - centre[None, :]) / stds[None, :], 0.0)
    w = np.ones_like(g) if weights is None else weights
    psi2 = (w * u) ** 2
    beyond = z > THRESHOLD
    total = float(np.sum(psi2))
    share = float(np.sum(psi2[beyond])) / total if total > 0 else 0.0
    rows, cols = np.nonzero(beyond)
    order = np.argsort(-z[rows, cols], kind="stable")[:LISTED]
    listed = tuple(
        Outlier(dataset, int(rows[i]), None if time is None else float(time[rows[i]]),
                names[cols[i]], float(g[rows[i], cols[i]] * to_display[cols[i]]),
                units[cols[i]], float(z[rows[i], cols[i]]), float(w[rows[i], cols[i]]))
        for i in order)
    clean, gross = None, False
    if refit is not None and weights is None and share > DOMINATE:
        measured = _without_outliers(beyond, refit, sd)
        if measured is not None:
            clean = {nm: float(s * f)
                     for nm, s, f in zip(names, measured[0], to_display, strict=True)}
            gross = measured[1]
    return Outliers(dataset, loss,
                    {nm: float(s * f) for nm, s, f in zip(names, raw, to_display, strict=True)},
                    dict(zip(names, units, strict=True)), int(beyond.sum()), n * ng,
                    {nm: int(beyond[:, k].sum()) for k, nm in enumerate(names)},
                    int(np.any(beyond, axis=1).sum()), share, listed, clean, gross,
                    None if sd is None else {nm: float(s) for nm, s in zip(names, stds,
                                                                           strict=True)})


def _without_outliers(flagged: np.ndarray, refit: Refit, sd: np.ndarray | None = None
                      ) -> tuple[np.ndarray, bool] | None:
    """Each constraint's robust spread of ``g/σ`` once the fit is solved again without the
    flagged residuals, flagged again against that fit until they stay the same (on the
    residuals standardized by ``sd`` where given, the spread still of ``g/σ``); and
    whether the outliers are gross.  None when a refit fails."""
    flagged = flagged.copy()
    for _ in range(REFITS):
        found = refit(flagged)
        if found is None or not np.all(np.isfinite(found)):
            return None
        h = found
        kept = ~flagged
        v = standardize(h, sd)
        stds = np.array([robust_std(v[kept[:, k], k]) for k in range(h.shape[1])])
        centre = np.array([np.median(v[kept[:, k], k]) if kept[:, k].any() else 0.0
                           for k in range(h.shape[1])])
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(stds[None, :] > 0, np.abs(v - centre[None, :]) / stds[None, :], 0.0)
        again = z > THRESHOLD
        if np.array_equal(again, flagged) or not again.any():
            break
        flagged = again
    gross = bool(flagged.any() and float(np.median(z[flagged])) > GROSS)
    if sd is not None:
        stds = np.array([robust_std(h[kept[:, k], k]) for k in range(h.shape[1])])
    return stds, gross


def remedy(outliers: Outliers) -> tuple[str, float, dict[str, float]]:
    """The suggested loss: its type, its scale in spreads, and each constraint's spread
    (display unit) the scale multiplies (see the module docstring)."""
    spread = outliers.clean_std if outliers.clean_std is not None else outliers.robust_std
    if outliers.gross:
        return "cauchy", CAUCHY_SCALE, spread
    return "huber", HUBER_SCALE, spread


def remedy_yaml(outliers: Outliers) -> str:
    """The YAML that gives each constraint with outliers a robust loss that works as
    written: Cauchy at :data:`CAUCHY_SCALE` spreads of the residual when the outliers are
    gross, else Huber at :data:`HUBER_SCALE`, the spread measured without the outliers
    where it was (``clean_std``), in the constraint's unit.

    Returns
    -------
    str
        Lines to merge into the problem's ``constraints:`` (each ``loss:`` beside the
        constraint's ``expr:``); empty when no constraint has an outlier.
    """
    kind, factor, spread = remedy(outliers)
    lines = []
    for name, count in outliers.by_constraint.items():
        if count == 0:
            continue
        scale = float(f"{factor * spread[name]:.2g}")
        if not scale > 0:
            continue
        unit = outliers.units.get(name) or "internal units"
        lines += [f"  {name}:", f"    loss: {{type: {kind}, scale: {scale:g}}}"
                  f"    # beside its expr; scale in {unit}"]
    return "constraints:\n" + "\n".join(lines) + "\n" if lines else ""
