"""Declared sensor noise: the key ``noise`` of a model input, a problem column, an instance
(per input) and a problem's ``noise:`` section.

A noise is the standard deviation of one reading's random error, written with a unit
(``noise: 0.5 um``) or as a plain number in the reading's own unit (``noise: 0.0005`` on
a reading in mm).  Its unit must measure what the reading measures (a length for a
length); ``0`` declares a reading exact.  Readings are independent of one another: the
covariance of a problem's readings is diagonal.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

from symcal.base.errors import SpecError, Where, excerpt
from symcal.base.units import UnitError, parse_unit, size
from symcal.language.common import display_unit
from symcal.language.dimensions import describe, same_dimension

#: ``NUMBER UNIT`` (the unit may be absent).
NUMBER_UNIT = re.compile(r"^\s*([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)\s*(.*?)\s*$")


@dataclass(frozen=True)
class NoiseSpec:
    """A declared noise: ``value`` in ``unit`` (``""``: the reading's own unit), as
    written (``text``), with its provenance."""

    value: float
    unit: str
    text: str
    where: Where

    def sigma(self, reading_unit: str) -> float:
        """The standard deviation in internal units (mm, rad, s, ...), for a reading
        declared in ``reading_unit``."""
        return self.value * size(self.unit or reading_unit)


def parse_noise(value: Any, where: Where, reading_unit: str | None = None) -> NoiseSpec:
    """Parse ``noise: 0.5 um`` (or a plain number in the reading's unit).

    Parameters
    ----------
    value
        What the file holds under ``noise``.
    where
        Its provenance (file, line, key path).
    reading_unit
        The unit of the reading it belongs to, when known here: the noise's unit must
        measure the same thing (checked again where the reading's unit is known).

    Raises
    ------
    SpecError
        For text that is not a number with a unit, a negative or infinite number, an
        unknown unit, or a unit of another dimension than the reading's.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise SpecError(where, f"a noise is a standard deviation with its unit (e.g. "
                               f"'noise: 0.5 um'), found '{excerpt(value)}'")
    if isinstance(value, str):
        match = NUMBER_UNIT.match(value)
        if match is None:
            raise SpecError(where, f"'{excerpt(value)}' is not a noise: write a standard "
                                   "deviation with its unit, e.g. 'noise: 0.5 um'")
        rest = match.group(2)
        if "+" in rest or rest[:1] in ("*", "/"):     # never a unit: an expression
            raise SpecError(where, f"'{excerpt(value)}' is not one standard deviation: a "
                                   "noise that depends on the reading (a share of it, or a "
                                   "sum of terms) cannot be declared; a noise is one number "
                                   "with its unit for every row (e.g. 'noise: 0.5 um'): "
                                   "write its value at the readings' typical size (the "
                                   "floor test then holds on average over the rows, not "
                                   "row by row)")
        number, unit = float(match.group(1)), display_unit(rest, where)
    else:
        number, unit = float(value), ""
    if not math.isfinite(number) or number < 0:
        raise SpecError(where, f"a noise must be a finite standard deviation >= 0, found "
                               f"'{excerpt(value)}'")
    spec = NoiseSpec(number, unit, str(value).strip(), where)
    if reading_unit is not None:
        check_noise_unit(spec, reading_unit, "the reading")
    return spec


def check_noise_unit(spec: NoiseSpec, reading_unit: str, what: str) -> None:
    """Refuse a noise whose unit measures something else than its reading's.

    Raises
    ------
    SpecError
        At the noise's provenance, naming both units.
    """
    if not spec.unit or not reading_unit:
        return
    try:
        mine, theirs = parse_unit(spec.unit), parse_unit(reading_unit)
    except UnitError:
        return    # an unknown unit was refused where it was written
    if not same_dimension(mine, theirs):
        raise SpecError(spec.where, f"the noise '{spec.text}' is in {describe(mine)}, but "
                                    f"{what} is in {describe(theirs)}")


def in_unit_of(value: Any, reading_unit: str, where: Where, what: str) -> Any:
    """``value`` written as a number with its unit (``360 deg``, as a noise is) as the
    same quantity in ``reading_unit``, a plain number's text; anything else unchanged.

    Raises
    ------
    SpecError
        For a unit that measures something else than ``reading_unit``, naming ``what``.
    """
    match = NUMBER_UNIT.match(value) if isinstance(value, str) else None
    if match is None or not match.group(2)[:1].isalpha():
        return value        # a plain number, or an expression ('2*pi', 'rho/2')
    number, unit = float(match.group(1)), display_unit(match.group(2), where)
    if reading_unit and not same_dimension(parse_unit(unit), parse_unit(reading_unit)):
        raise SpecError(where, f"{what} '{value}' is in {describe(parse_unit(unit))}, but "
                               f"the input is in {describe(parse_unit(reading_unit))}")
    return repr(number * size(unit) / size(reading_unit))
