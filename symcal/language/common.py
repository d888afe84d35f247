"""Spec pieces shared by models and problems: constants, parameters, expressions, units."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from symcal.base.errors import SpecError, Where, excerpt
from symcal.base.units import check_unit
from symcal.language import expr
from symcal.language.fields import (
    check_keys,
    child_where,
    expect_bool,
    expect_map,
    expect_number,
    expect_str,
    expect_symbol,
)
from symcal.language.yamlio import YMap


def display_unit(value: Any, where: Where) -> str:
    """Validate a unit string (any unit pint knows, :func:`symcal.base.units.parse_unit`;
    ``""`` when absent), refusing an unknown one with a did-you-mean."""
    if value is None:
        return ""
    text = str(value) if isinstance(value, (int, float)) and not isinstance(value, bool) \
        else value
    if not isinstance(text, str):
        raise SpecError(where, f"a unit must be text, found '{excerpt(value)}'")
    reason = check_unit(text)
    if reason is not None:
        raise SpecError(where, f"{reason}; units are pint's (mm, um, m, rad, mrad, deg, s, "
                               "mm/s, ...)")
    return text


@dataclass(frozen=True, eq=False)
class ExprSpec:
    """An expression as written, parsed, with its provenance."""

    text: str
    node: expr.Node
    where: Where


def parse_expr(value: Any, where: Where) -> ExprSpec:
    """Parse an expression (text or a plain number) into an :class:`ExprSpec`."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = repr(expect_number(value, where))
    text = expect_str(value, where)
    try:
        node = expr.parse(text)
    except expr.ExprError as exc:
        raise SpecError(where, exc.detail) from None
    return ExprSpec(" ".join(text.split()), node, where)


@dataclass(frozen=True)
class ConstantSpec:
    """A named constant."""

    name: str
    value: float
    unit: str
    doc: str
    where: Where


@dataclass(frozen=True)
class ParameterSpec:
    """A named parameter: initial value, unit, bounds, fixed flag, nominal scale.

    ``scale`` is the parameter's nominal magnitude (None: not stated); it makes parameters
    of different units commensurate for the solver and the identifiability analysis.
    """

    name: str
    value: float
    unit: str
    lower: float
    upper: float
    fixed: bool
    scale: float | None
    doc: str
    where: Where


def _doc(entry: YMap, where: Where) -> str:
    return expect_str(entry["doc"], child_where(entry, where, "doc")) if "doc" in entry else ""


def _unit(entry: YMap, where: Where) -> str:
    if "unit" not in entry:
        return ""
    return display_unit(entry["unit"], child_where(entry, where, "unit"))


def parse_constant(name: str, value: Any, where: Where) -> ConstantSpec:
    """Parse ``name: 1.5`` or ``name: {value, unit, doc}``."""
    expect_symbol(name, where, "a constant's name")
    if not isinstance(value, dict):
        return ConstantSpec(name, expect_number(value, where), "", "", where)
    entry = check_keys(value, where, required=["value"], optional=["unit", "doc"])
    number = expect_number(entry["value"], child_where(entry, where, "value"))
    return ConstantSpec(name, number, _unit(entry, where), _doc(entry, where), where)


PARAMETER_KEYS = ["value", "unit", "lower", "upper", "fixed", "scale", "doc"]
#: Widest range of magnitudes a parameter may span, in its own unit: its
#: scale lies within [1/MAGNITUDE, MAGNITUDE] and its value within MAGNITUDE scales.
MAGNITUDE = 1e9
_WHY = ("the solver and the identifiability analysis work in units of the scale, and double "
        "precision cannot resolve a parameter across a wider range of magnitudes")


def parse_parameter(name: str, value: Any, where: Where) -> ParameterSpec:
    """Parse ``name: 0.1`` or ``name: {value, unit, lower, upper, fixed, scale, doc}``."""
    expect_symbol(name, where, "a parameter's name")
    if not isinstance(value, dict):
        number = expect_number(value, where)
        spec = ParameterSpec(name, number, "", -math.inf, math.inf, False, None, "", where)
        _check_magnitude(spec, where)
        return spec
    entry = check_keys(value, where, optional=PARAMETER_KEYS)
    return apply_parameter_overrides(
        ParameterSpec(name, 0.0, "", -math.inf, math.inf, False, None, "", where), entry, where
    )


def apply_parameter_overrides(base: ParameterSpec, entry: YMap, where: Where) -> ParameterSpec:
    """Return ``base`` with the keys of ``entry`` applied, validating bounds and value."""
    fields = dict(base.__dict__)
    for key in entry:
        at = child_where(entry, where, key)
        if key in ("value", "lower", "upper"):
            fields[key] = expect_number(entry[key], at)
        elif key == "scale":
            fields[key] = expect_number(entry[key], at)
            if fields[key] <= 0:
                raise SpecError(at, f"scale must be positive, found {entry[key]}")
        elif key == "fixed":
            fields[key] = expect_bool(entry[key], at)
        elif key == "unit":
            fields[key] = _unit(entry, where)
        elif key == "doc":
            fields[key] = _doc(entry, where)
    spec = ParameterSpec(**{**fields, "where": where})
    _check_magnitude(spec, where)
    if spec.lower > spec.upper:
        raise SpecError(where, f"lower bound {spec.lower:g} is above upper bound {spec.upper:g}")
    if not spec.lower <= spec.value <= spec.upper:
        raise SpecError(
            where,
            f"initial value {spec.value:g} is outside its bounds [{spec.lower:g}, {spec.upper:g}]",
        )
    return spec


def _check_magnitude(spec: ParameterSpec, where: Where) -> None:
    """Refuse a scale or value whose magnitude would make the solve meaningless."""
    if spec.scale is not None and not 1 / MAGNITUDE <= spec.scale <= MAGNITUDE:
        raise SpecError(where, f"scale {spec.scale:g} is outside [{1 / MAGNITUDE:g}, "
                               f"{MAGNITUDE:g}] (in the parameter's unit): {_WHY}")
    scale = spec.scale if spec.scale is not None else 1.0
    if abs(spec.value) > MAGNITUDE * scale:
        raise SpecError(where, f"initial value {spec.value:g} is more than {MAGNITUDE:g} times "
                               f"its scale {scale:g}: {_WHY}; give a scale near the value")
    if spec.scale is None and 0 < abs(spec.value) < 1 / MAGNITUDE:
        raise SpecError(where, f"initial value {spec.value:g} is below {1 / MAGNITUDE:g} and "
                               "no scale is given (the scale would be the value): give a scale "
                               "(its nominal magnitude)")


def section(doc: YMap, where: Where, key: str) -> tuple[YMap, Where]:
    """The mapping under ``key`` (empty if absent) and its provenance."""
    at = child_where(doc, where, key)
    return expect_map(doc.get(key), at), at


def check_unique(names_by_section: dict[str, list[tuple[str, Where]]]) -> None:
    """Reject a name defined in two sections (e.g. a constant and a parameter)."""
    seen: dict[str, str] = {}
    for sect, entries in names_by_section.items():
        for name, where in entries:
            if name in seen:
                raise SpecError(where, f"'{name}' is already defined in {seen[name]}")
            seen[name] = sect
