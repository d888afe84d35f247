"""The one home of units: display units, their size in symcal's internal units, angles.

Inside symcal lengths are in mm, angles in rad and times in s; reports show each quantity
in the display unit its declaration names (µm, mrad, ...).
"""

from __future__ import annotations

import math

#: Display units and their size in symcal's internal units (mm, rad, s).
DISPLAY_UNITS: dict[str, float] = {
    "": 1.0,
    "1": 1.0,
    "mm": 1.0,
    "um": 1e-3,
    "µm": 1e-3,
    "nm": 1e-6,
    "m": 1e3,
    "rad": 1.0,
    "mrad": 1e-3,
    "urad": 1e-6,
    "µrad": 1e-6,
    "deg": math.pi / 180.0,
    "s": 1.0,
}

#: Display units of angles.
ANGLE_UNITS: tuple[str, ...] = ("rad", "mrad", "urad", "µrad", "deg")
#: Display units of lengths.
LENGTH_UNITS: tuple[str, ...] = ("mm", "um", "µm", "nm", "m")


def internal_unit(display: str) -> str:
    """The internal unit of a quantity shown in ``display`` (``µm`` → ``mm``)."""
    if display in LENGTH_UNITS:
        return "mm"
    if display in ANGLE_UNITS:
        return "rad"
    return "" if display in ("", "1") else display
