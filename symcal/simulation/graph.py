"""A scenario as a CasADi graph: every column's reading as SX of the states and the time.

Names resolve lazily, once each, as in problems: constants, true values, states and the
time ``t`` are leaves (a number's and a state's value are in internal units); an
expression or an explicit column is its expression plus the terms that active effects
add to it, in file order (inside an effect's term, the target's own name is its value
before that term, and the effect's ``values`` are visible); a ``solve`` column is an
unknown of the equations the run's readings are solved from.  Units are checked once,
over the same parse (:func:`symcal.language.dimensions.unit_of`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import casadi as ca

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import SpecError, Where
from symcal.base.units import Unit, angle_power, parse_unit, size, text_of
from symcal.language import expr
from symcal.language.common import ExprSpec
from symcal.language.dimensions import DimensionError, describe, same_dimension, unit_of

#: Newton steps unrolled in the symbolic readings of ``solve`` columns (for designs).
UNROLLED_STEPS = 6
#: The built-in time state.
TIME = "t"
#: A scenario (:class:`symcal.simulation.scenario.Scenario`) and its effects; typed loosely
#: here, since the scenario module builds its graph at load.
Scenario = Any
Effect = Any


@dataclass(frozen=True, eq=False)
class Graph:
    """The readings of one observation as CasADi SX.

    Attributes
    ----------
    states
        The states (``len(scenario.states)`` × 1), in internal units.
    t
        The time (s).
    unknowns
        The ``solve`` columns' readings (internal units), in column order.
    columns
        Every column's reading (internal units), of ``states``, ``t`` and ``unknowns``.
    equations
        The equations the ``solve`` columns make vanish (one per unknown).
    starts
        Their first guesses, of ``states`` and ``t`` only.
    """

    states: ca.SX
    t: ca.SX
    unknowns: ca.SX
    columns: dict[str, ca.SX]
    equations: ca.SX
    starts: ca.SX

    @property
    def implicit(self) -> bool:
        """Whether some column is solved for."""
        return self.unknowns.numel() > 0

    def explicit_columns(self, steps: int = UNROLLED_STEPS) -> dict[str, ca.SX]:
        """Every column as SX of the states and time alone: ``solve`` columns by ``steps``
        Newton steps from their start, unrolled (exact derivatives of the iteration)."""
        if not self.implicit:
            return dict(self.columns)
        z = self.starts
        jac = ca.jacobian(self.equations, self.unknowns)
        for _ in range(steps):
            f, j = ca.substitute([self.equations, jac], [self.unknowns], [z])
            z = z - ca.solve(j, f)
        return {name: ca.substitute(sx, self.unknowns, z) for name, sx in self.columns.items()}


class _Builder:
    """Resolves the scenario's names to SX and checks their units."""

    def __init__(self, scenario: Scenario) -> None:
        self.sc = scenario
        self.states = ca.SX.sym("states", len(scenario.states))
        self.t = ca.SX.sym(TIME)
        implicit = [c for c in scenario.columns if c.solve is not None]
        self.unknowns = ca.SX.sym("readings", len(implicit))
        self.leaves: dict[str, tuple[ca.SX, Unit | None]] = {TIME: (self.t, parse_unit("s"))}
        for value in (*scenario.constants, *scenario.truth):
            self.leaves[value.name] = (ca.SX(value.internal), _unit(value.unit))
        for i, state in enumerate(scenario.states):
            self.leaves[state.name] = (self.states[i], _unit(state.unit))
        for i, column in enumerate(implicit):
            self.leaves[column.name] = (self.unknowns[i], _unit(column.unit))
        # expressions are symbols; an 'expr' column is reached only as a target of effects
        self.defined: dict[str, tuple[ExprSpec, str]] = {}
        for e in scenario.expressions:
            self.defined[e.name] = (e.spec, e.unit)
        self.readings: dict[str, tuple[ExprSpec, str]] = {
            c.name: (c.expr, c.unit) for c in scenario.columns if c.expr is not None}
        self.adds: dict[str, list[tuple[Effect, ExprSpec]]] = {}
        for effect in scenario.active_effects:
            for target, spec in effect.add:
                if target not in self.defined and target not in self.readings:
                    known = [*self.defined, *self.readings]
                    raise SpecError(spec.where, f"effect '{effect.name}' adds to "
                                                f"'{target}', which is no expression or "
                                                f"'expr' column{did_you_mean(target, known)}")
                self.adds.setdefault(target, []).append((effect, spec))
        self.done: dict[str, tuple[ca.SX, Unit | None]] = {}
        self.partial: dict[tuple[str, int], tuple[ca.SX, Unit | None]] = {}
        self.stack: list[str] = []

    # -- names ---------------------------------------------------------------------

    def known(self) -> list[str]:
        return [*self.leaves, *self.defined]

    def value(self, name: str, where: Where, reading: bool = False
              ) -> tuple[ca.SX, Unit | None]:
        """``name``'s value: a leaf or an expression (with ``reading``: the 'expr' column
        of that name)."""
        if reading:
            return self.reading(name)
        if name in self.leaves:
            return self.leaves[name]
        if name in self.done:
            return self.done[name]
        if name not in self.defined:
            hint = did_you_mean(name, self.known())
            if not hint and name in self.readings:
                hint = (f": '{name}' is a column; an expression cannot read an 'expr' column "
                         "(name its reading as an expression)")
            raise SpecError(where, f"unknown symbol '{name}'{hint}")
        if name in self.stack:
            chain = " -> ".join([*self.stack[self.stack.index(name):], name])
            raise SpecError(where, f"'{name}' refers to itself: {chain}")
        self.stack.append(name)
        try:
            got = self.upto(name, len(self.adds.get(name, ())))
        finally:
            self.stack.pop()
        self.done[name] = got
        return got

    def reading(self, name: str) -> tuple[ca.SX, Unit | None]:
        """The 'expr' column ``name``, with the terms effects add to it."""
        key = f"column {name}"
        if key not in self.done:
            self.done[key] = self.upto(name, len(self.adds.get(name, ())), column=True)
        return self.done[key]

    def upto(self, name: str, count: int, column: bool = False) -> tuple[ca.SX, Unit | None]:
        """``name``'s value with the first ``count`` effect terms added."""
        key = (("column " if column else "") + name, count)
        if key in self.partial:
            return self.partial[key]
        if count == 0:
            spec, declared = (self.readings if column else self.defined)[name]
            sx, unit = self.build(spec, self.lookup)
            got = (sx, self.declared(name, spec, declared, unit))
        else:
            base, unit = self.upto(name, count - 1, column)
            effect, spec = self.adds[name][count - 1]
            values = {v.name: (ca.SX(v.internal), _unit(v.unit)) for v in effect.values}

            def inner(n: str, where: Where) -> tuple[ca.SX, Unit | None]:
                if n in values:
                    return values[n]
                if n == name:
                    return base, unit
                return self.lookup(n, where)

            term, term_unit = self.build(spec, inner)
            if not same_dimension(unit, term_unit):
                raise SpecError(spec.where, f"effect '{effect.name}' adds {describe(term_unit)} "
                                            f"to '{name}', which is {describe(unit)}")
            got = (base + term, unit)
        self.partial[key] = got
        return got

    def lookup(self, name: str, where: Where) -> tuple[ca.SX, Unit | None]:
        return self.value(name, where)

    def declared(self, name: str, spec: ExprSpec, declared: str, unit: Unit | None
                 ) -> Unit | None:
        if not declared:
            return unit
        want = _unit(declared)
        if not same_dimension(want, unit):
            raise SpecError(spec.where, f"'{name}' is declared in {describe(want)} but its "
                                        f"expression is {describe(unit)}")
        return want

    def build(self, spec: ExprSpec, lookup: Callable[[str, Where], tuple[ca.SX, Unit | None]]
              ) -> tuple[ca.SX, Unit | None]:
        """SX and unit of an expression, its names resolved by ``lookup``."""
        units: dict[str, Unit | None] = {}

        def resolve(node: expr.Name) -> ca.SX:
            sx, unit = lookup(node.name, spec.where)
            units[node.name] = unit
            return sx

        sx = expr.to_casadi(spec.node, resolve)
        try:
            unit = unit_of(spec.node, lambda n: units.get(n))
        except DimensionError as exc:
            raise SpecError(spec.where, exc.detail) from None
        return sx, unit


def _unit(text: str) -> Unit | None:
    return parse_unit(text) if text else None


def _build(scenario: Scenario) -> Graph:
    b = _Builder(scenario)
    columns: dict[str, ca.SX] = {}
    equations, starts = [], []
    for column in scenario.columns:
        if column.expr is not None:
            columns[column.name] = b.reading(column.name)[0]
            continue
        assert column.solve is not None
        columns[column.name] = b.leaves[column.name][0]
        equations.append(b.build(column.solve, b.lookup)[0])
        if column.start is None:
            starts.append(ca.SX(0.0))
            continue
        start = b.build(column.start, b.lookup)[0]
        if ca.depends_on(start, b.unknowns):
            raise SpecError(column.start.where, "a start must not depend on the readings "
                                                "being solved for")
        starts.append(start)
    for effect in scenario.active_effects:     # every term builds (and checks) once
        for target, _ in effect.add:
            b.value(target, effect.where, reading=target not in b.defined)
    return Graph(b.states, b.t, b.unknowns, columns, ca.vertcat(*equations) if equations
                 else ca.SX(0, 1), ca.vertcat(*starts) if starts else ca.SX(0, 1))


def graph(scenario: Scenario) -> Graph:
    """The scenario's graph, built once per scenario object.

    Raises
    ------
    SpecError
        An unknown symbol (did-you-mean), a name that refers to itself, mismatched units,
        an effect adding to what is not an expression, a start that depends on the
        readings it starts.
    """
    got = getattr(scenario, "_graph", None)
    if got is None:
        got = _build(scenario)
        object.__setattr__(scenario, "_graph", got)
    return got


def check(scenario: Scenario) -> None:
    """Build the graph (and every series run's states) once, so that a bad scenario is
    refused at load."""
    graph(scenario)
    for run in scenario.runs:
        if run.motion.kind == "series":
            series_function(scenario, run.motion.exprs)


def _angle_words(name: str, state_unit: str, unit: Unit) -> str:
    """Why a series expression whose unit differs from its state's by an angle alone is
    refused: an angle is dimensionless, so ``1/s`` would be read as ``rad/s`` where a
    plain number is read in the state's own unit (a new user's ``400*(2*pi/P1)*cos(...)``
    for a rate in deg/s was 57 times too large, silently)."""
    shown = text_of(unit) or "a plain ratio"
    factor = size(text_of(unit) or "1") / size(state_unit)
    return (f"state '{name}' is in {state_unit} but its expression is in {shown}, which "
            f"has no angle in it: it would be read as radians ({factor:.4g} {state_unit} "
            f"per {shown}). Give the expression its angle (a constant with an angle "
            f"unit, e.g. A: {{value: 400, unit: deg}}), or write a plain number in "
            f"{state_unit}")


def series_function(scenario: Scenario, exprs: tuple[tuple[str, ExprSpec], ...]) -> Any:
    """The states of a ``series`` run as a CasADi function of ``t`` (internal units)."""
    b = _Builder(scenario)
    allowed = {TIME, *(v.name for v in (*scenario.constants, *scenario.truth))}

    def lookup(name: str, where: Where) -> tuple[ca.SX, Unit | None]:
        if name not in allowed:
            raise SpecError(where, f"a series gives each state as an expression of t and "
                                   f"the constants; '{name}' is neither"
                                   f"{did_you_mean(name, sorted(allowed))}")
        return b.leaves[name]

    outs = []
    for name, spec in exprs:
        sx, unit = b.build(spec, lookup)
        state = scenario.state(name)
        if unit is None or not text_of(unit) and not unit.dimensionality:
            outs.append(sx * state.size)      # plain numbers: in the state's own unit
            continue
        if state.unit and not same_dimension(parse_unit(state.unit), unit):
            raise SpecError(spec.where, f"state '{name}' is in {describe(parse_unit(state.unit))}"
                                        f" but its expression is {describe(unit)}")
        if state.unit and angle_power(parse_unit(state.unit)) > angle_power(unit) \
                and not math.isclose(size(text_of(unit) or "1") / size(state.unit), 1.0):
            raise SpecError(spec.where, _angle_words(name, state.unit, unit))
        outs.append(sx)
    return ca.Function("series", [b.t], [ca.vertcat(*outs)])
