"""A constraint's robust loss in problem files: ``loss: {type: huber, scale: 5}``.

The loss names are scipy's (``scipy.optimize.least_squares(loss=...)``) and Ceres'
(``HuberLoss``, ``SoftLOneLoss``, ``CauchyLoss``, ``ArctanLoss``); the scale is scipy's
``f_scale`` (Ceres' ``a``), written in the constraint's own unit (its ``unit:``, or
symcal's internal units when it declares none).  The numbers behind each loss live in
:mod:`symcal.solvers.robust`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import SpecError, Where, excerpt
from symcal.base.units import DISPLAY_UNITS, symbol
from symcal.language.fields import check_keys, child_where, expect_map, expect_number

#: The robust losses a constraint may declare (squared residuals when none is).
LOSSES: tuple[str, ...] = ("huber", "soft_l1", "cauchy", "arctan")


@dataclass(frozen=True)
class LossSpec:
    """A robust loss of one constraint.

    Attributes
    ----------
    kind
        One of :data:`LOSSES`.
    scale
        Where the loss turns from quadratic to robust, as written: in ``unit``.
    unit
        The constraint's display unit (``""``: internal units).
    """

    kind: str
    scale: float
    unit: str
    where: Where

    @property
    def internal_scale(self) -> float:
        """The scale in symcal's internal units (mm, rad, s)."""
        return self.scale * DISPLAY_UNITS[self.unit]

    @property
    def text(self) -> str:
        """E.g. ``huber, scale 5 µm``."""
        return f"{self.kind}, scale {self.scale:g} {symbol(self.unit)}"

    def yaml(self) -> str:
        """The flow-style YAML that declares it: ``{type: huber, scale: 5}``."""
        return f"{{type: {self.kind}, scale: {self.scale:.3g}}}"


def parse_loss(value: Any, where: Where, unit: str) -> LossSpec:
    """Parse a constraint's ``loss: {type: NAME, scale: NUMBER}``.

    Parameters
    ----------
    value
        The loaded YAML value of ``loss``.
    where
        Its provenance.
    unit
        The constraint's display unit, the unit of ``scale``.

    Raises
    ------
    SpecError
        A bare loss name (a scale is needed), an unknown loss (with a did-you-mean), a
        missing or unknown key, or a scale that is not a positive number.
    """
    if isinstance(value, str):
        hint = value if value in LOSSES else "huber"
        raise SpecError(where, f"a robust loss needs a scale in the constraint's unit "
                               f"({symbol(unit)}): write loss: {{type: {excerpt(hint)}, "
                               "scale: NUMBER}")
    entry = check_keys(expect_map(value, where), where, required=["type", "scale"])
    type_at = child_where(entry, where, "type")
    kind = entry["type"]
    if not isinstance(kind, str) or kind not in LOSSES:
        raise SpecError(type_at, f"unknown loss '{excerpt(kind)}'"
                                 f"{did_you_mean(str(kind), LOSSES)}; losses: "
                                 f"{', '.join(LOSSES)} (squared residuals without 'loss')")
    scale_at = child_where(entry, where, "scale")
    scale = expect_number(entry["scale"], scale_at)
    if scale <= 0:
        raise SpecError(scale_at, f"the scale of a robust loss must be positive, found "
                                  f"{entry['scale']} (it is where the loss stops being "
                                  f"quadratic, in {symbol(unit)})")
    return LossSpec(kind, scale, unit, where)
