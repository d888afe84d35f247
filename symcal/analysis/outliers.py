"""The observations a fit treats as outliers, whatever its loss.

Each constraint's residual ``g/σ`` at the estimate, less its median, is whitened by a
robust estimate of its spread (1.4826 × the median absolute deviation from the median,
which a few gross errors do not move; the RMS where more than half of the residuals are
equal).  A residual row is
an outlier when its whitened residual exceeds :data:`THRESHOLD` (a Gaussian residual does
so with probability 6e-7).  The outliers *dominate* when they carry more than
:data:`DOMINATE` of the fit's influence ``Σ ψ²``, ``ψ = w g`` each row's contribution to
the gradient (``w`` the final weight of a robust loss, 1 for squared residuals): with
squared residuals that is their share of the cost Σ (g/σ)²; a robust loss that
down-weights them leaves them a small share.
"""

from __future__ import annotations

from collections.abc import Mapping
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
                "listed": [o.to_dict() for o in self.listed]}

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> Outliers:
        """Inverse of :meth:`to_dict`."""
        units = {k: "" if v == "(internal)" else v for k, v in doc["units"].items()}
        return cls(doc["dataset"], doc["loss"], dict(doc["robust_std"]), units,
                   doc["count"], doc["rows"], dict(doc["by_constraint"]),
                   doc["observations"], doc["share"],
                   tuple(Outlier.from_dict(o) for o in doc["listed"]))


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


def find_outliers(
    dataset: str,
    names: tuple[str, ...],
    units: tuple[str, ...],
    to_display: np.ndarray,
    g: np.ndarray,
    weights: np.ndarray | None,
    loss: str,
    time: np.ndarray | None = None,
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

    Returns
    -------
    Outliers
    """
    n, ng = g.shape
    stds = np.array([robust_std(g[:, k]) for k in range(ng)])
    centre = np.median(g, axis=0) if n else np.zeros(ng)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(stds[None, :] > 0, np.abs(g - centre[None, :]) / stds[None, :], 0.0)
    w = np.ones_like(g) if weights is None else weights
    psi2 = (w * g) ** 2
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
    return Outliers(dataset, loss,
                    {nm: float(s * f) for nm, s, f in zip(names, stds, to_display, strict=True)},
                    dict(zip(names, units, strict=True)), int(beyond.sum()), n * ng,
                    {nm: int(beyond[:, k].sum()) for k, nm in enumerate(names)},
                    int(np.any(beyond, axis=1).sum()), share, listed)


#: The robust loss suggested where outliers dominate, and its scale in robust standard
#: deviations of the residual.
REMEDY_LOSS = "huber"
REMEDY_SCALE = 2.0


def remedy_yaml(outliers: Outliers) -> str:
    """The YAML that gives each constraint with outliers a robust loss: Huber, its scale
    :data:`REMEDY_SCALE` robust standard deviations of the residual (in its unit).

    Returns
    -------
    str
        Lines to merge into the problem's ``constraints:`` (each ``loss:`` beside the
        constraint's ``expr:``); empty when no constraint has an outlier.
    """
    lines = []
    for name, count in outliers.by_constraint.items():
        if count == 0:
            continue
        scale = float(f"{REMEDY_SCALE * outliers.robust_std[name]:.2g}")
        if not scale > 0:
            continue
        unit = outliers.units.get(name) or "internal units"
        lines += [f"  {name}:", f"    loss: {{type: {REMEDY_LOSS}, scale: {scale:g}}}"
                  f"    # beside its expr; scale in {unit}"]
    return "constraints:\n" + "\n".join(lines) + "\n" if lines else ""
