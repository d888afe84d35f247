"""The one home of units: parsing unit strings with pint, their size in symcal's internal
units, angles, and how a person reads them.

**Internal units.** Inside symcal every computed value (an expression, an output, a
constraint, a comparison) is in *internal units*: lengths in mm, angles in rad, times in s,
and pint's root units for any other dimension (g, K, A, mol, cd).  A symbol declared in
another unit (a parameter in m, a constant in deg, a data column in ms) keeps its value in
that unit, and the build multiplies it by :func:`size` of its unit where it enters an
expression, so a model written in m, deg or furlongs is solved consistently; nothing is
converted when the unit is already internal (mm, rad, s), so such models give the same
numbers as before units were checked.  Reports divide by :func:`size` of the unit each
quantity is shown in.

**Angles.** As in pint, an angle is dimensionless: ``rad`` and ``deg`` are named,
scaled dimensionless units (``mm/mm`` may be shown in ``mrad``, ``sin`` takes any
dimensionless argument).  :func:`is_angle` tells an angle (a unit built on ``radian``)
from a plain ratio, for display and for candidate effects.

**Cost.** pint is imported, and its registry built (about 0.3 s), on the first unit that
is not trivial (``""``, ``"1"``), never by ``import symcal``.
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Iterator, Mapping
from typing import TYPE_CHECKING, Any

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import SymcalError, excerpt

if TYPE_CHECKING:
    import pint

#: A pint unit (pint's own annotations tell its plain and registry units apart; symcal
#: uses only what both have).
Unit = Any

#: Unit strings people write most, offered first by did-you-mean (any pint unit is valid).
COMMON_UNITS: tuple[str, ...] = (
    "mm", "um", "µm", "nm", "m", "cm", "km", "rad", "mrad", "urad", "µrad", "deg", "s",
    "ms", "us", "min", "h", "Hz", "kg", "g", "N", "K", "V", "A", "1",
)
#: Longest unit string accepted.
MAX_UNIT_CHARS = 100
#: Highest power of a base unit a unit may hold.
MAX_POWER = 12
#: The internal unit of each base dimension pint knows (others: pint's base unit).
_INTERNAL = {"meter": "mm", "radian": "rad", "second": "s"}
#: The size of a millimetre in metres, pint's base unit of length.
_MM = 1e-3
#: Texts that mean "dimensionless" without needing pint.
_TRIVIAL = ("", "1")


class UnitError(SymcalError, ValueError):
    """A unit string that is not a unit (the message says why, with a suggestion)."""


@functools.cache
def registry() -> pint.UnitRegistry:
    """The one pint registry of symcal (built on first use).

    pint imports dask when it is installed, for dask arrays symcal never gives it: dask is
    kept out of that import (0.08 s), and importable afterwards as before.  The registry's
    parsed definitions are cached in the user's cache folder by pint (0.15 s saved per
    process); where that folder cannot be used, the registry is built without it."""
    import sys

    blocked = [] if "dask" in sys.modules else ["dask"]
    for name in blocked:
        sys.modules[name] = None  # type: ignore[assignment]
    try:
        import pint
    finally:
        for name in blocked:
            sys.modules.pop(name, None)
    try:
        reg: pint.UnitRegistry = pint.UnitRegistry(cache_folder=":auto:")
    except Exception:  # noqa: BLE001 - an unusable cache folder: build without it
        reg = pint.UnitRegistry()
    reg.define("ppb = 1e-9")      # a clock's ns/s, beside pint's ppm
    return reg


def _known_names() -> list[str]:
    reg = registry()
    return [*COMMON_UNITS, *reg._units]  # noqa: SLF001 - pint's table of unit names


@functools.lru_cache(maxsize=4096)
def parse_unit(text: str) -> Unit:
    """The pint unit a unit string names.

    Parameters
    ----------
    text
        A unit as written in a file: ``"mm"``, ``"um"``, ``"mm/s"``, ``"deg"``,
        ``"furlong"``; ``""`` and ``"1"`` are dimensionless.

    Returns
    -------
    Unit

    Raises
    ------
    UnitError
        For a string pint does not know (with a did-you-mean), a magnitude inside it
        (``"1000 mm"``), or an offset unit (``degC``), which cannot be scaled
        (:func:`offset_refusal` says why and what to use: ``kelvin``, ``delta_degC``).
    """
    if not isinstance(text, str):
        raise UnitError(f"a unit must be text, found {type(text).__name__}")
    if len(text) > MAX_UNIT_CHARS:
        raise UnitError(f"unit '{excerpt(text)}' is longer than {MAX_UNIT_CHARS} characters")
    reg = registry()
    if text.strip() in _TRIVIAL:
        return reg.dimensionless
    if "ppt" in re.split(r"[^A-Za-z_]+", text):
        raise UnitError(f"unit '{excerpt(text)}': 'ppt' is ambiguous (parts per thousand, "
                        "or per trillion; pint reads it as a picopint): write 'permille' "
                        "for parts per thousand, or 'ppb' with values 1000 times smaller "
                        "for parts per trillion (percent, permille, ppm and ppb are known)")
    try:
        quantity = reg.Quantity(1.0, text)
    except Exception as exc:  # noqa: BLE001 - pint raises several kinds on bad text
        name = getattr(exc, "unit_names", None) or getattr(exc, "args", [""])[:1]
        bad = str(name[0]) if isinstance(name, (list, tuple)) and name else text
        hint = did_you_mean(bad if bad in text else text, _known_names())
        what = "is not a unit (it holds a number)" if text.strip()[:1].isdigit() else ""
        raise UnitError(f"'{excerpt(text)}' {what}" if what
                        else f"unknown unit '{excerpt(text)}'{hint}") from None
    if not quantity._ok_for_muldiv():  # noqa: SLF001 - pint's test for offset units
        raise UnitError(offset_refusal(text, quantity))
    unit = quantity.units
    if not math.isclose(quantity.magnitude, 1.0):
        raise UnitError(f"'{excerpt(text)}' is not a unit (it holds a number)")
    magnitude, exps = _root(unit)
    if not all(math.isfinite(p) and abs(p) <= MAX_POWER for p in exps.values()) \
            or not 0 < magnitude < math.inf:
        raise UnitError(f"unit '{excerpt(text)}' is out of range (powers up to {MAX_POWER})")
    return unit


def offset_refusal(text: str, quantity: Any) -> str:
    """Why an offset unit (``degC``, ``degF``) is refused, and what to write instead.

    symcal converts a unit by its size alone (a value enters its expressions multiplied
    by it), which cannot carry an offset: 20 degC is 293.15 K, but a difference of 20
    degC is 20 K.  pint names the two readings ``kelvin`` (or the offset unit's absolute
    twin) and ``delta_degC``."""
    reg = registry()
    try:
        zero = reg.Quantity(0.0, text).to("kelvin").magnitude
        at_zero = f" (0 {excerpt(text)} is {zero:g} K)"
    except Exception:  # noqa: BLE001 - any pint failure: leave the example out
        at_zero = ""
    delta = f"delta_{text.strip()}"
    try:
        reg.Quantity(1.0, delta)
        twin = f"'{excerpt(delta)}' for a temperature difference"
    except Exception:  # noqa: BLE001 - not every offset unit has a delta twin
        twin = "a difference unit"
    return (f"unit '{excerpt(text)}' has an offset{at_zero}: symcal converts units by "
            f"scaling alone, which cannot carry an offset; use 'kelvin' for a temperature, "
            f"or {twin}")


def check_unit(text: str) -> str | None:
    """Why ``text`` is not a unit, or None when it is (see :func:`parse_unit`)."""
    if text in _TRIVIAL:
        return None
    try:
        parse_unit(text)
    except UnitError as exc:
        return exc.message
    return None


def _snap(value: float) -> float:
    """``value`` as the nearest short decimal when it is one but for rounding (so that
    ``um`` is exactly ``1e-3`` mm), else unchanged."""
    if value == 0 or not math.isfinite(value):
        return value
    short = float(f"{value:.12g}")
    return short if abs(short - value) <= 4 * math.ulp(value) else value


def _root(unit: Unit) -> tuple[float, dict[str, float]]:
    """(magnitude, root-unit exponents) of one ``unit`` in pint's root units."""
    root = registry().Quantity(1.0, unit).to_root_units()
    return float(root.magnitude), {str(k): float(v)  # type: ignore[arg-type]
                                    for k, v in root.unit_items()}


def angle_power(unit: Unit) -> float:
    """The power of the radian in ``unit`` (``deg/s``: 1; ``1/s``: 0): two units of one
    dimension whose powers differ are told apart only by an angle, which is
    dimensionless (``1/s`` reads as ``rad/s``)."""
    return _root(unit)[1].get("radian", 0.0)


@functools.lru_cache(maxsize=4096)
def size_of(unit: Unit) -> float:
    """How many internal units (mm, rad, s, ...) one ``unit`` is."""
    magnitude, exps = _root(unit)
    return _snap(magnitude * (1.0 / _MM) ** exps.get("meter", 0.0))


def size(text: str | None) -> float:
    """How many internal units one ``text`` is: ``size("um") == 1e-3`` (mm),
    ``size("deg") == pi/180`` (rad), ``size("m") == 1e3``; ``""`` and ``"(internal)"`` are 1.

    Raises
    ------
    UnitError
        For a string that is not a unit.
    """
    if text is None or text in (*_TRIVIAL, "(internal)"):
        return 1.0
    return size_of(parse_unit(text))


def is_angle(text: str | None) -> bool:
    """Whether ``text`` is an angle unit (rad, mrad, deg, turn, ...): built on radian
    alone.  False for anything that is not a unit."""
    if not text or text in _TRIVIAL:
        return False
    try:
        _, exps = _root(parse_unit(text))
    except UnitError:
        return False
    return exps == {"radian": 1.0}


@functools.lru_cache(maxsize=4096)
def internal_of(unit: Unit) -> str:
    """The internal unit of ``unit``'s dimension as text (``m/s`` → ``mm/s``); ``""``
    for a dimensionless ratio."""
    _, exps = _root(unit)
    num: list[str] = []
    den: list[str] = []
    for name, power in exps.items():
        symbol_text = _INTERNAL.get(name) or f"{registry().Unit(name):~C}"
        p = abs(power)
        shown = symbol_text if p == 1 else f"{symbol_text}^{p:g}"
        (num if power > 0 else den).append(shown)
    if not num and not den:
        return ""
    text = "*".join(num) or "1"
    if den:
        text += "/" + ("/".join(den))
    return text


def internal_unit(display: str) -> str:
    """The internal unit of a quantity shown in ``display`` (``µm`` → ``mm``,
    ``deg`` → ``rad``, ``m/s`` → ``mm/s``); ``""`` for no unit or a plain ratio, and an
    unknown string unchanged."""
    if display in (*_TRIVIAL, "(internal)"):
        return ""
    try:
        return internal_of(parse_unit(display))
    except UnitError:
        return display


def text_of(unit: Unit) -> str:
    """A unit as short text pint reads back (``mm/s``, ``m^2``); ``""`` if dimensionless
    and unnamed."""
    text = f"{unit:~C}"
    return text.replace("**", "^") if text not in ("", "dimensionless") else ""


class _Sizes(Mapping[str, float]):
    """``DISPLAY_UNITS[u]``: the size of unit ``u`` in internal units, for any unit pint
    knows (``u in DISPLAY_UNITS`` tests that); iterating gives the common units."""

    def __getitem__(self, key: str) -> float:
        try:
            return size(key)
        except UnitError:
            raise KeyError(key) from None

    def __contains__(self, key: object) -> bool:
        return isinstance(key, str) and (key in (*_TRIVIAL, "(internal)")
                                         or check_unit(key) is None)

    def __iter__(self) -> Iterator[str]:
        return iter(("", *COMMON_UNITS))

    def __len__(self) -> int:
        return len(COMMON_UNITS) + 1


class _Angles:
    """``u in ANGLE_UNITS``: whether ``u`` is an angle unit (:func:`is_angle`)."""

    def __contains__(self, key: object) -> bool:
        return isinstance(key, str) and is_angle(key)

    def __iter__(self) -> Iterator[str]:
        return iter(("rad", "mrad", "urad", "µrad", "deg"))


#: Size of a unit in symcal's internal units (mm, rad, s, ...), for any unit pint knows.
DISPLAY_UNITS: Mapping[str, float] = _Sizes()
#: Membership test for angle units.
ANGLE_UNITS: Any = _Angles()

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
    few mrad; every other unit is drawn as declared, and a string that is not a unit (or
    none) is left as it is (the values are then drawn unscaled).

    Parameters
    ----------
    unit
        The variable's declared unit (``None`` or ``""`` when unknown).

    Returns
    -------
    str
        A unit :func:`size` accepts, or ``""`` when the values are drawn unscaled.
    """
    unit = unit or ""
    if unit == "rad":
        return "mrad"
    return unit if unit and unit in DISPLAY_UNITS else ""
