"""Dimensional analysis of an expression: the unit of every node of a parsed expression,
checked once when a problem is built (the CasADi expressions stay plain SX).

The walk runs over the same AST :func:`symcal.language.expr.parse` returns, beside the SX build,
with the unit of each name supplied by the caller (``None``: the name declares no unit,
and is not checked).  The rules:

- a number is dimensionless, except ``0``, which has every unit (``x - 0``);
Errors quote both sides (and give the column of a call); the caller adds the file, line
and key.

- ``+`` and ``-`` need operands of one dimension (``mm + m`` is fine: values are in
  internal units; the result keeps the left unit's name); an operand without a unit takes
  the other's;
- ``*`` and ``/`` multiply and divide units; ``x**n`` needs a dimensionless exponent, and
  a number (an expression of numbers) when ``x`` has a unit: ``x**2``, ``x**0.5``;
- ``sin cos tan sinh cosh tanh exp log`` take a dimensionless argument (an angle is
  dimensionless: ``rad``, ``deg``); ``asin acos atan atan2`` return ``rad`` (``atan2``'s
  two arguments share a dimension); ``sqrt`` halves every power; ``abs`` keeps the unit.

An unit of ``None`` propagates (a product with an unchecked factor is unchecked), so a
model without units works as before.
"""

from __future__ import annotations

from collections.abc import Callable

from symcal.base.errors import SymcalError, excerpt
from symcal.base.units import MAX_POWER, Unit, is_angle, registry, text_of
from symcal.language import expr

_DIMENSIONLESS_FUNCS = frozenset({"sin", "cos", "tan", "sinh", "cosh", "tanh", "exp", "log"})
_ANGLE_FUNCS = frozenset({"asin", "acos", "atan"})
_VERBS = {"+": ("add", "and"), "-": ("subtract", "from")}


class DimensionError(SymcalError):
    """Two units that cannot meet, or a function given the wrong unit.

    Parameters
    ----------
    detail
        The message; ``str(err) == detail``.
    column
        0-based column in the expression of the operator or call, or None.
    """

    def __init__(self, detail: str, column: int | None = None) -> None:
        super().__init__(detail)
        self.detail = detail
        self.column = column


def describe(unit: Unit | None) -> str:
    """A unit as a person reads it with its dimension: ``"mm, a length"``,
    ``"rad, an angle"``, ``"mm/s, [length] / [time]"``, ``"dimensionless"``."""
    if unit is None:
        return "no unit"
    text = text_of(unit)
    dims = unit.dimensionality
    if not dims:
        kind = "an angle" if text and is_angle(text) else "dimensionless"
    else:
        names = {"[length]": "a length", "[time]": "a time", "[mass]": "a mass",
                 "[temperature]": "a temperature", "[current]": "a current"}
        kind = names.get(str(dims), str(dims))
    return f"{text}, {kind}" if text else kind


def same_dimension(a: Unit | None, b: Unit | None) -> bool:
    """Whether two units measure the same thing (always, if either is None)."""
    return a is None or b is None or a.dimensionality == b.dimensionality


def _named(unit: Unit) -> bool:
    """Whether a unit has a name (``rad``, ``mm``), unlike a plain number's."""
    return bool(text_of(unit))


def _side(node: expr.Node) -> str:
    return f"'{excerpt(expr.render(node))}'"


def _constant(node: expr.Node) -> float | None:
    """The value of an expression of numbers, or None if it has names."""
    if expr.names(node):
        return None
    return expr.evaluate(node, {})


def unit_of(node: expr.Node, lookup: Callable[[str], Unit | None]) -> Unit | None:
    """The unit of an expression, checking every operator and call on the way.

    Parameters
    ----------
    node
        The AST (from :func:`symcal.language.expr.parse`).
    lookup
        The unit of a name (``None``: not declared, not checked); called once per
        occurrence (the caller memoises).

    Returns
    -------
    Unit or None
        The expression's unit, or None where a name without a unit makes it unknown.

    Raises
    ------
    DimensionError
        Naming both sides of a mismatch, their units and the column.
    """
    reg = registry()
    if isinstance(node, expr.Num):
        return None if node.value == 0 else reg.dimensionless
    if isinstance(node, expr.Name):
        return lookup(node.name)
    if isinstance(node, expr.Unary):
        return unit_of(node.operand, lookup)
    if isinstance(node, expr.Binary):
        return _binary(node, lookup)
    return _call(node, lookup)


def _binary(node: expr.Binary, lookup: Callable[[str], Unit | None]) -> Unit | None:
    left, right = unit_of(node.left, lookup), unit_of(node.right, lookup)
    if node.op in "+-":
        if left is None or right is None:
            return left if right is None else right
        if left.dimensionality != right.dimensionality:
            verb, joint = _VERBS[node.op]
            a, b = (node.right, node.left) if node.op == "-" else (node.left, node.right)
            ua, ub = (right, left) if node.op == "-" else (left, right)
            raise DimensionError(
                f"cannot {verb} {_side(a)} ({describe(ua)}) {joint} {_side(b)} "
                f"({describe(ub)})", node.col)
        return left if _named(left) or not _named(right) else right
    if node.op in "*/":
        if left is None or right is None:
            return None
        return left * right if node.op == "*" else left / right
    return _power(node, left, right)


def _power(node: expr.Binary, base: Unit | None,
           exponent: Unit | None) -> Unit | None:
    if exponent is not None and exponent.dimensionality:
        raise DimensionError(f"the exponent {_side(node.right)} of {_side(node.left)} must be "
                             f"dimensionless, found {describe(exponent)}", node.col)
    if base is None or not _named(base):
        return base
    value = _constant(node.right)
    if value is None:
        raise DimensionError(f"{_side(node.left)} has a unit ({describe(base)}): its exponent "
                             f"{_side(node.right)} must be a number", node.col)
    if not abs(value) <= MAX_POWER:
        raise DimensionError(f"exponent {value:g} of {_side(node.left)} ({describe(base)}) is "
                             f"out of range (at most {MAX_POWER})", node.col)
    return base ** value


def _call(node: expr.Call, lookup: Callable[[str], Unit | None]) -> Unit | None:
    reg = registry()
    args = [unit_of(a, lookup) for a in node.args]
    name = node.func
    if name in _DIMENSIONLESS_FUNCS or name in _ANGLE_FUNCS:
        (arg,) = args
        if arg is not None and arg.dimensionality:
            need = "an angle or a dimensionless ratio" if name in ("sin", "cos", "tan") \
                else "a dimensionless argument"
            raise DimensionError(f"{name}() needs {need}, but {_side(node.args[0])} is in "
                                 f"{describe(arg)} (at column {node.col + 1})", node.col)
        return reg.radian if name in _ANGLE_FUNCS else reg.dimensionless
    if name == "atan2":
        y, x = args
        if not same_dimension(y, x):
            raise DimensionError(f"atan2() needs two arguments of one dimension, but "
                                 f"{_side(node.args[0])} is in {describe(y)} and "
                                 f"{_side(node.args[1])} in {describe(x)} (at column "
                                 f"{node.col + 1})", node.col)
        return reg.radian
    (arg,) = args
    if name == "sqrt":
        return None if arg is None else arg ** 0.5
    return arg  # abs
