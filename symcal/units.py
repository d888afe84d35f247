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


#: How a person reads each unit string: ASCII spellings become their symbols. Machine
#: documents (JSON) keep the strings as declared; only human-facing text uses these.
SYMBOLS: dict[str, str] = {
    "": "(internal)",
    "(internal)": "(internal)",
    "um": "µm",
    "urad": "µrad",
}


def symbol(unit: str | None) -> str:
    """The unit as a person reads it: ``"um"`` → ``"µm"``, ``"urad"`` → ``"µrad"``,
    ``""`` (no declared unit: symcal's internal units) → ``"(internal)"``; any other
    string unchanged.

    Parameters
    ----------
    unit
        A display unit as declared (``None`` is read as ``""``).

    Returns
    -------
    str
        The text to print beside a value.
    """
    unit = unit or ""
    return SYMBOLS.get(unit, unit)


def axis_unit(unit: str | None) -> str:
    """The display unit to draw a variable in, from the unit it was declared with.

    Values of a variable are in symcal's internal units (mm, rad, s); its declaration
    names a display unit (``mrad``) or an internal one (``rad`` for a data column).
    Angles declared in ``rad`` are drawn in ``mrad``, since the courier's angles are a
    few mrad; every other unit is drawn as declared, and an unknown one (or none) is
    left as it is (the values are then drawn unscaled).

    Parameters
    ----------
    unit
        The variable's declared unit (``None`` or ``""`` when unknown).

    Returns
    -------
    str
        A key of :data:`DISPLAY_UNITS`, or ``""`` when the values are drawn unscaled.
    """
    unit = unit or ""
    if unit == "rad":
        return "mrad"
    return unit if unit in DISPLAY_UNITS else ""
