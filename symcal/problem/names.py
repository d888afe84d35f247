"""Name resolution of the problem compiler: a :class:`Scope` resolves the names of one
model instance or of the problem to CasADi SX, lazily and memoised, with cycle detection
and the unit of every name (checked once, at the build).

A scope knows its own :class:`Symbols` (ready values, definitions, declared units); names
it does not know go to its :class:`Outside` (columns, dotted signals, parameters: the
compiler; nothing: a model instance, which sees only its own symbols).  A name declared
implicit (``x = F(x)``) resolves to a placeholder whose start and map are recorded in
:class:`Implicits`; a hooked name gets its hook symbol added to its definition.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Protocol

import casadi as ca

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import SpecError, Where
from symcal.base.units import Unit, parse_unit, size, text_of
from symcal.language import expr
from symcal.language.common import ExprSpec
from symcal.language.dimensions import DimensionError, describe, same_dimension, unit_of
from symcal.language.model_file import ImplicitSpec
from symcal.language.problem_file import InstanceSpec


def declared(text: str) -> Unit | None:
    """The unit a declaration names, or None when it names none (not checked)."""
    return parse_unit(text) if text else None


def unit_text(written: str, found: Unit | None) -> str:
    """The unit a quantity is shown in: as declared, else the unit its expression has."""
    return written or (text_of(found) if found is not None else "")


def scaled(sx: ca.SX, unit: str) -> ca.SX:
    """A symbol's value in internal units (mm, rad, s): ``sx`` times the size of its
    declared unit (unchanged when that is 1)."""
    factor = size(unit)
    return sx if factor == 1.0 else sx * factor


def check_declared(where: Where, what: str, want: Unit | None, found: Unit | None) -> None:
    """Refuse a declared unit of another dimension than the expression's."""
    if not same_dimension(want, found):
        raise SpecError(where, f"{what} is declared in {describe(want)}, but its "
                               f"expression is in {describe(found)}")


def enter(stack: list[str], key: str, where: Where) -> None:
    """Push ``key`` on the resolution stack, or report the cycle it would close."""
    if key in stack:
        cycle = stack[stack.index(key):] + [key]
        raise SpecError(where, f"cyclic definition: {' -> '.join(cycle)}")
    stack.append(key)


@dataclass
class OpenDefinition:
    """An implicit definition left open by the build: x = F(x), from ``start``."""

    key: str
    symbol: ca.SX
    start: ca.SX
    fmap: ca.SX
    steps: int
    where: Where


@dataclass
class Implicits:
    """A scope's implicit definitions and the list where opened ones are recorded (shared
    by every instance scope of a build)."""

    specs: Mapping[str, ImplicitSpec]
    opened: list[OpenDefinition]


@dataclass
class Symbols:
    """What a scope knows itself: ready ``values`` and their ``units``; ``defs`` built on
    first use, in their ``declared`` unit when one is declared."""

    values: dict[str, ca.SX]
    units: dict[str, Unit | None]
    defs: Mapping[str, ExprSpec]
    declared: Mapping[str, Unit | None] = field(default_factory=dict)


class Outside(Protocol):
    """How a scope resolves the names it does not know."""

    def resolve(self, name: str, where: Where) -> ca.SX | None:
        """The SX of ``name``, or None when it is unknown here too."""

    def unit(self, name: str) -> Unit | None:
        """The unit of a name :meth:`resolve` resolved."""

    def known(self) -> list[str]:
        """Names to suggest for a typo."""

    def hint(self, name: str) -> str:
        """More help for an unknown ``name`` (or "")."""


class Scope:
    """Lazy, memoised resolution of names to SX with cycle detection (module doc)."""

    def __init__(self, label: str, symbols: Symbols, outside: Outside, stack: list[str],
                 implicits: Implicits, hooked: Mapping[str, ca.SX] | None = None) -> None:
        self.label = label
        self.values = dict(symbols.values)
        self.units: dict[str, Unit | None] = dict(symbols.units)
        self.defs = symbols.defs
        self.declared = symbols.declared
        self.outside = outside
        self.stack = stack
        self.implicits = implicits
        self.hooked = dict(hooked or {})

    def build(self, spec: ExprSpec) -> ca.SX:
        """Build one expression, reporting errors at its provenance."""
        return expr.to_casadi(spec.node, lambda node: self.lookup(node.name, spec.where))

    def unit(self, spec: ExprSpec) -> Unit | None:
        """The unit of an expression :meth:`build` has built (its names are resolved),
        checked; a mismatch is reported at the expression's provenance."""
        try:
            return unit_of(spec.node, self.unit_lookup)
        except DimensionError as exc:
            raise SpecError(spec.where, exc.detail) from None

    def unit_lookup(self, name: str) -> Unit | None:
        """The unit of a resolved name (None: no unit declared)."""
        if name in self.units:
            return self.units[name]
        return self.outside.unit(name)

    def known(self) -> list[str]:
        """Every name this scope can resolve."""
        return [*self.values, *self.defs, *self.outside.known()]

    def _def_unit(self, name: str) -> Unit | None:
        """The unit of definition ``name``: as declared (checked against its expression's),
        else its expression's."""
        spec = self.defs[name]
        found = self.unit(spec)
        want = self.declared.get(name)
        check_declared(spec.where, f"'{name}'", want, found)
        return want if want is not None else found

    def lookup(self, name: str, where: Where) -> ca.SX:
        """The SX of ``name``, built on first use."""
        if name in self.values:
            return self.values[name]
        if name in self.implicits.specs and name in self.defs:
            return self._open_implicit(name, where)
        if name in self.defs:
            enter(self.stack, f"{self.label}{name}", where)
            try:
                value = self.build(self.defs[name])
            finally:
                self.stack.pop()
            if name in self.hooked:
                value = value + self.hooked[name]
            self.values[name] = value
            self.units[name] = self._def_unit(name)
            return value
        found = self.outside.resolve(name, where)
        if found is not None:
            return found
        pool = [k for k in self.known() if k != "pi"]  # pi is never what a typo meant
        raise SpecError(where, f"unknown symbol '{name}'{did_you_mean(name, pool)}"
                               f"{self.outside.hint(name)}")

    def _open_implicit(self, name: str, where: Where) -> ca.SX:
        """A placeholder for ``name``; its start and its map are built and recorded."""
        spec = self.implicits.specs[name]
        key = f"{self.label}{name}"
        enter(self.stack, key, where)  # a start that needs the name itself is a cycle
        try:
            start = self.build(spec.start)
        finally:
            self.stack.pop()
        symbol = ca.SX.sym(key)
        self.values[name] = symbol
        start_unit = self.unit(spec.start)
        want = self.declared.get(name)
        check_declared(spec.start.where, f"the start of '{name}'", want, start_unit)
        self.units[name] = want if want is not None else start_unit
        outer, self.stack = self.stack, [key]  # definitions in progress outside are built
        try:                                   # again here, in terms of the placeholder
            fmap = self.build(self.defs[name])
        finally:
            self.stack = outer
        map_unit = self.unit(self.defs[name])
        if not same_dimension(self.units[name], map_unit):
            raise SpecError(self.defs[name].where,
                            f"'{name}' starts in {describe(self.units[name])} but its "
                            f"definition is in {describe(map_unit)}")
        if not ca.depends_on(fmap, symbol):
            raise SpecError(spec.where, f"'{name}' is declared implicit but its definition "
                                        "does not refer to itself")
        self.implicits.opened.append(OpenDefinition(key, symbol, start, fmap, spec.steps,
                                                    spec.where))
        return symbol


class _ModelOutside:
    """Outside a model instance there is nothing: dotted names belong in problem files."""

    def __init__(self, model_name: str) -> None:
        self.model_name = model_name

    def resolve(self, name: str, where: Where) -> ca.SX | None:
        if name.startswith("base."):
            raise SpecError(where, f"'{name}': model '{self.model_name}' does not redefine "
                                   f"'{name[5:]}' of a model it extends")
        if "." in name:
            raise SpecError(where, f"'{name}': a model refers only to its own symbols; dotted "
                                   "names (instance.output) belong in problem files")
        return None

    def unit(self, name: str) -> Unit | None:
        return None

    def known(self) -> list[str]:
        return []

    def hint(self, name: str) -> str:
        return ""


def instance_scope(inst: InstanceSpec, inputs: dict[str, ca.SX], params: dict[str, ca.SX],
                   input_units: Mapping[str, Unit | None], stack: list[str],
                   opened: list[OpenDefinition], hooked: Mapping[str, ca.SX],
                   constants: Mapping[str, ca.SX] | None = None) -> Scope:
    """The scope of one model instance: its constants (``constants``: their values in
    internal units, by default as declared), inputs (bound), parameters, expressions and
    outputs; ``hooked`` error expressions get their hook added."""
    model = inst.model
    values: dict[str, ca.SX] = dict(constants) if constants is not None else {
        k: ca.SX(c.value * size(c.unit)) for k, c in model.constants.items()}
    values.update(inputs)
    values.update(params)
    values["pi"] = ca.SX(ca.pi)
    units: dict[str, Unit | None] = {k: declared(c.unit) for k, c in model.constants.items()}
    units.update(input_units)
    units.update({k: declared(p.unit) for k, p in model.parameters.items()})
    units["pi"] = declared("1")
    defs = dict(model.expressions)
    defs.update({k: o.expr for k, o in model.outputs.items()})
    outputs = {k: declared(u) for k, u in model.expression_units.items() if k in defs}
    outputs.update({k: declared(o.unit) for k, o in model.outputs.items()})
    return Scope(f"{inst.name}.", Symbols(values, units, defs, outputs),
                 _ModelOutside(model.name), stack, Implicits(model.implicit, opened), hooked)
