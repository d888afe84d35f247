"""Scenario files: any system's true states over its runs, its readings, its truth.

A scenario says what a simulated experiment is, for any system, in the expression
grammar of models and problems (:mod:`symcal.language.expr`; never ``eval``):

- **states**: the true quantities that change over a run (a pose, an orientation, a
  speed, a temperature), each with its unit; the time ``t`` (s) is always a state;
- **runs**: how the states move over each run: a random ``scatter`` within ranges, a
  ``line`` from one point to another, ``dwells`` (random points held for some samples
  each), or a ``series`` (each state an expression of ``t``);
- **columns**: each data column's raw reading, as an expression of the states (or, with
  ``solve:``, the value that makes an equation vanish: a reading defined by the model it
  must satisfy), with its declared noise (Gaussian ``noise``, ``quantization``);
- **truth**: the models' parameters at their true values, named as the problem names
  them (``s1.k0``, ``l_x``);
- **effects**: hidden effects, each a named set of values and of terms added to
  expressions or columns (``add``), or glitches of some readings (``slips``); an overlay
  removes one with ``NAME: ~`` or switches it off with ``on: false``;
- **design**: which motion parameters ``symcal design`` may change, within what limits.

Schema (``*`` marks a required key)::

    scenario*: NAME
    doc: TEXT
    extends: BASE.yaml                  # merged as in language/overlay.py
    constants:                          # NAME: number | {value*, unit, doc}
    truth:                              # NAME (dotted: s1.k0): number | {value*, unit, doc}
    states*:                            # NAME: {unit, doc, value}   (value: held default)
    expressions:                        # NAME: EXPR | {expr*, unit, doc}
    columns*:                           # NAME: EXPR | {expr | solve, start, unit, noise,
                                        #               quantization, stream, doc}
    effects:                            # NAME: {doc, on, values, add, slips}
      NAME:
        values: {NAME: number | {value*, unit, doc}}   # seen by this effect's terms
        add: {TARGET: EXPR}             # TARGET (an expression or column) gains EXPR;
                                        # TARGET inside EXPR is its value before
        slips: {COLUMN: {fraction*, size*}}  # a share of the rows reads off by +-size
    runs*:
      NAME:
        dt: 0.1                         # s between samples
        t0: 0                           # time of the first sample (s)
        doc: TEXT
        scatter: {n*, STATE: [lo, hi] | value, dwell: 0, dwell_at: [STATE, ...]}
        line: {n*, from*: {STATE: value}, to*: {STATE: value}, jitter: {STATE: sigma},
               STATE: value}
        dwells: {count*, samples*, STATE: [lo, hi] | value}
        series: {n*, STATE: EXPR of t}
    design:
      run*: NAME                        # a scatter or dwells run
      doc: TEXT
      limits*: {STATE: [lo, hi], dwell: [lo, hi], n: [lo, hi]}

Units.  Every number is in the unit its entry declares (a state's range in the state's
unit, a column's noise in the column's unit); inside, as in problems, every expression is
in internal units (mm, rad, s, pint's root units otherwise), and each symbol enters
multiplied by the size of its declared unit, so expressions of states, constants and
truth are unit-consistent (checked once, at load, by :mod:`symcal.language.dimensions`).
A column's reading is written in its declared unit.  ``noise`` and ``quantization`` are
a number in the column's unit, a quantity (``0.5 um``) or an expression of constants.

Random streams.  ``default_rng(SeedSequence(seed, spawn_key=(run_index, key)))``: key 0
draws the states of a run, 4 which scatter draws dwell at the ends of their ranges, 5 the
slips, and the noise of the columns is drawn per ``stream`` (default: the column's own
name, for a column that declares ``noise``), the streams numbered in the order they first
appear among the columns as 1, 2, 3, 6, 7, ...; a stream draws its columns' noise
together, row by row, so a run with fewer samples is a prefix of one with more.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import SpecError, Where, excerpt
from symcal.base.units import UnitError, size
from symcal.language import expr
from symcal.language.common import ExprSpec, display_unit, parse_expr
from symcal.language.fields import (
    MAX_SAMPLES,
    check_keys,
    child_where,
    expect_bool,
    expect_int,
    expect_list,
    expect_map,
    expect_name,
    expect_number,
    expect_str,
    expect_symbol,
)
from symcal.language.overlay import load_with_extends, merge_scenario, new_list, new_map
from symcal.language.yamlio import YList, YMap
from symcal.simulation.graph import TIME, check

#: The motions a run may have.
MOTIONS: tuple[str, ...] = ("scatter", "line", "dwells", "series")
#: Motions whose ranges ``symcal design`` may change.
DESIGNABLE: tuple[str, ...] = ("scatter", "dwells")
#: Names a state may not have (keys of motions and design limits).
RESERVED_STATES = frozenset({TIME, "n", "dwell", "dwell_at", "from", "to", "jitter", "count",
                             "samples"})
#: Stream keys of the states, the dwell draws and the slips; noise streams take the rest.
POSE_STREAM, DWELL_STREAM, SLIP_STREAM = 0, 4, 5
DEFAULT_DT = 0.1
_DOTTED = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)?$")
_QUANTITY = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s+(\S.*?)\s*$")


# --------------------------------------------------------------------------- dataclasses


@dataclass(frozen=True)
class Value:
    """A named number as declared: ``value`` in ``unit`` (``""``: internal units)."""

    name: str
    value: float
    unit: str = ""
    doc: str = ""
    where: Where = field(default=Where("<scenario>"), compare=False)

    @property
    def internal(self) -> float:
        """The value in internal units (mm, rad, s, ...)."""
        factor = size(self.unit)
        return self.value if factor == 1.0 else self.value * factor


@dataclass(frozen=True)
class State:
    """A true quantity that changes over a run (values are kept in internal units)."""

    name: str
    unit: str = ""
    doc: str = ""
    default: float | None = None      # held value (internal units) when a run omits it
    where: Where = field(default=Where("<scenario>"), compare=False)

    @property
    def size(self) -> float:
        """Internal units per one of the state's unit."""
        return size(self.unit)


@dataclass(frozen=True)
class Expression:
    """A named expression (or an explicit column's reading)."""

    name: str
    spec: ExprSpec
    unit: str = ""
    doc: str = ""


@dataclass(frozen=True)
class Column:
    """A data column: its reading (``expr``) or the equation it solves (``solve``), its
    unit and noise (in that unit)."""

    name: str
    expr: ExprSpec | None
    solve: ExprSpec | None = None
    start: ExprSpec | None = None
    unit: str = ""
    noise: float = 0.0
    quantization: float = 0.0
    stream: str = ""          # its noise stream ("": declares no noise)
    doc: str = ""
    where: Where = field(default=Where("<scenario>"), compare=False)

    @property
    def sigma(self) -> float:
        """Standard deviation of the column's noise (its unit): Gaussian and quantization
        (uniform error, ``q^2 / 12``)."""
        return math.sqrt(self.noise**2 + self.quantization**2 / 12.0)


@dataclass(frozen=True)
class Slip:
    """Glitches of one column: on a share ``fraction`` of the rows (drawn at random) the
    reading is off by ``+-size`` (its unit)."""

    column: str
    fraction: float
    size: float


@dataclass(frozen=True)
class Effect:
    """A hidden effect: its values, the terms it adds, the slips it causes."""

    name: str
    values: tuple[Value, ...] = ()
    add: tuple[tuple[str, ExprSpec], ...] = ()
    slips: tuple[Slip, ...] = ()
    on: bool = True
    doc: str = ""
    where: Where = field(default=Where("<scenario>"), compare=False)


@dataclass(frozen=True)
class Scatter:
    """``n`` draws, each ranged state uniform within its range (internal units); a share
    ``dwell`` of them holds the ``dwell_at`` states at an end of their ranges instead."""

    n: int
    ranges: tuple[tuple[str, tuple[float, float]], ...]
    held: tuple[tuple[str, float], ...] = ()
    dwell: float = 0.0
    dwell_at: tuple[str, ...] = ()
    kind: str = "scatter"

    @property
    def samples(self) -> int:
        """Observations per draw."""
        return 1


@dataclass(frozen=True)
class Dwells:
    """``count`` random points (each ranged state uniform within its range), each held
    for ``samples`` observations."""

    count: int
    samples: int
    ranges: tuple[tuple[str, tuple[float, float]], ...]
    held: tuple[tuple[str, float], ...] = ()
    kind: str = "dwells"

    @property
    def n(self) -> int:
        """Observations of the run."""
        return self.count * self.samples

    @property
    def dwell(self) -> float:
        """No draw sits at the ends of its ranges."""
        return 0.0

    @property
    def dwell_at(self) -> tuple[str, ...]:
        """No state dwells at its ends."""
        return ()


@dataclass(frozen=True)
class Line:
    """``n`` samples evenly from ``start`` to ``end`` (internal units), with Gaussian
    ``jitter`` on some states."""

    n: int
    start: tuple[tuple[str, float], ...]
    end: tuple[tuple[str, float], ...]
    jitter: tuple[tuple[str, float], ...] = ()
    kind: str = "line"


@dataclass(frozen=True)
class Series:
    """``n`` samples, each state an expression of ``t``."""

    n: int
    exprs: tuple[tuple[str, ExprSpec], ...]
    kind: str = "series"


Motion = Scatter | Dwells | Line | Series


@dataclass(frozen=True)
class Run:
    """One named motion and its clock."""

    name: str
    motion: Motion
    dt: float = DEFAULT_DT
    t0: float = 0.0
    doc: str = ""
    where: Where = field(default=Where("<scenario>"), compare=False)


@dataclass(frozen=True)
class DesignSpace:
    """What ``symcal design`` may change: the ranges of some states of one scatter or
    dwells run, the share that dwells at the range ends, and ``n``, each within limits
    (in the state's unit; ``dwell`` a share; ``n`` whole observations)."""

    run: str
    limits: tuple[tuple[str, tuple[float, float]], ...]
    doc: str = ""
    where: Where = field(default=Where("<scenario>"), compare=False)

    @property
    def bounds(self) -> dict[str, tuple[float, float]]:
        """The limits by key, in file order."""
        return dict(self.limits)

    def limit_where(self, key: str) -> Where:
        """Provenance of the limit of ``key``."""
        return self.where.child("limits").child(key)


@dataclass(frozen=True, eq=False)
class Scenario:
    """A validated scenario (see the module docstring for the YAML schema)."""

    name: str
    states: tuple[State, ...]
    columns: tuple[Column, ...]
    runs: tuple[Run, ...]
    constants: tuple[Value, ...] = ()
    truth: tuple[Value, ...] = ()
    expressions: tuple[Expression, ...] = ()
    effects: tuple[Effect, ...] = ()
    design: DesignSpace | None = None
    doc: str = ""
    source: str = "<scenario>"
    # why a ``design`` section inherited from a file this one extends does not apply to
    # it (its run is no longer a scatter or dwells run, say): simulating needs no design
    inherited_design: str = ""
    runs_where: Where = field(default=Where("<scenario>"), compare=False)
    document: YMap | None = field(default=None, repr=False)
    where: Where = field(default=Where("<scenario>"), compare=False)

    @property
    def run_names(self) -> tuple[str, ...]:
        """Names of the runs, in file order."""
        return tuple(run.name for run in self.runs)

    @property
    def column_names(self) -> tuple[str, ...]:
        """The columns a run writes, in file order."""
        return tuple(c.name for c in self.columns)

    @property
    def active_effects(self) -> tuple[Effect, ...]:
        """The effects that are on."""
        return tuple(e for e in self.effects if e.on)

    def state(self, name: str) -> State:
        """The state called ``name``."""
        return next(s for s in self.states if s.name == name)

    def column(self, name: str) -> Column:
        """The column called ``name``."""
        return next(c for c in self.columns if c.name == name)

    def run_index(self, name: str) -> int:
        """Position of run ``name`` (it seeds the run's random streams).

        Raises
        ------
        SpecError
            If the scenario has no such run (with a did-you-mean).
        """
        for index, run in enumerate(self.runs):
            if run.name == name:
                return index
        raise SpecError(
            self.runs_where,
            f"no run named '{name}'{did_you_mean(str(name), self.run_names)}"
            f"; runs: {', '.join(self.run_names)}",
        )

    def overlay(self, changes: Mapping[str, Any]) -> Scenario:
        """This scenario with ``changes`` merged as an ``extends:`` overlay would be
        (mappings merge at every depth, lists and values replace, ``None`` removes).

        Parameters
        ----------
        changes
            A plain mapping in the file's schema, e.g. ``{"effects": {"drift": None}}``
            or ``{"columns": {"p1": {"noise": 0.001}}}``.

        Returns
        -------
        Scenario
            The validated new scenario (named as this one unless ``changes`` names it).

        Raises
        ------
        SpecError
            If the merged document is not a valid scenario.
        """
        assert self.document is not None, "a scenario built in Python has no document"
        doc = _to_yaml(dict(changes))
        base = merge_scenario(_without(self.document, ("scenario",)), doc, Path(self.source))
        if "scenario" not in base:
            base["scenario"] = self.name
        return replace(parse_scenario(base, self.where), source=self.source)


def _to_yaml(value: Any) -> Any:
    """A plain value as YAML nodes (for :meth:`Scenario.overlay`; no lines to name)."""
    if isinstance(value, Mapping):
        out = new_map(None)
        for key, item in value.items():
            out[key] = _to_yaml(item)
        return out
    if isinstance(value, (list, tuple)):
        items = new_list(None)
        items.extend(_to_yaml(item) for item in value)
        return items
    return value


def _without(doc: YMap, keys: tuple[str, ...]) -> YMap:
    out = new_map(doc.line)
    for key in doc:
        if key not in keys:
            out[key] = doc[key]
            if key in doc.key_lines:
                out.key_lines[key] = doc.key_lines[key]
            if key in getattr(doc, "key_files", {}):
                out.key_files[key] = doc.key_files[key]
    return out


# --------------------------------------------------------------------------- small parts


def _doc(entry: YMap, where: Where) -> str:
    if entry.get("doc") is None:
        return ""
    return " ".join(expect_str(entry["doc"], child_where(entry, where, "doc")).split())


def _unit(entry: YMap, where: Where) -> str:
    if entry.get("unit") is None:
        return ""
    return display_unit(entry["unit"], child_where(entry, where, "unit"))


def _value(name: str, value: Any, where: Where) -> Value:
    """``NAME: number`` or ``NAME: {value, unit, doc}``."""
    if not isinstance(value, dict):
        return Value(name, expect_number(value, where), "", "", where)
    entry = check_keys(value, where, required=("value",), optional=("unit", "doc"))
    return Value(name, expect_number(entry["value"], child_where(entry, where, "value")),
                 _unit(entry, where), _doc(entry, where), where)


def _dotted(key: Any, where: Where, what: str) -> str:
    if not isinstance(key, str) or not _DOTTED.match(key):
        raise SpecError(where, f"{what} must be a name with at most one dot (s1.k0), found "
                               f"{excerpt(repr(key))}")
    expect_symbol(key.split(".")[0], where, f"{what}'s name")   # abs.k: abs is reserved
    return key


def _values(value: Any, where: Where, what: str) -> tuple[Value, ...]:
    mapping = expect_map(value, where)
    return tuple(_value(_dotted(k, child_where(mapping, where, k), what), v,
                        child_where(mapping, where, k)) for k, v in mapping.items())


def _constants(value: Any, where: Where) -> tuple[Value, ...]:
    mapping = expect_map(value, where)
    out = []
    for key, item in mapping.items():
        at = child_where(mapping, where, key)
        out.append(_value(expect_symbol(key, at, "a constant's name"), item, at))
    return tuple(out)


def _states(value: Any, where: Where) -> tuple[State, ...]:
    mapping = expect_map(value, where)
    if not mapping:
        raise SpecError(where, "a scenario needs at least one state (what changes over a run)")
    out = []
    for key, item in mapping.items():
        at = child_where(mapping, where, key)
        name = expect_symbol(key, at, "a state's name")
        if name in RESERVED_STATES:
            why = ("the time of each sample is the built-in state 't'" if name == TIME
                   else f"'{name}' is a key of runs and design limits")
            raise SpecError(at, f"'{name}' cannot name a state: {why}")
        entry = check_keys(item, at, optional=("unit", "doc", "value"))
        unit = _unit(entry, at)
        default = None
        if entry.get("value") is not None:
            default = expect_number(entry["value"], child_where(entry, at, "value")) * size(unit)
        out.append(State(name, unit, _doc(entry, at), default, at))
    return tuple(out)


def _expressions(value: Any, where: Where) -> tuple[Expression, ...]:
    mapping = expect_map(value, where)
    out = []
    for key, item in mapping.items():
        at = child_where(mapping, where, key)
        name = expect_symbol(key, at, "an expression's name")
        if isinstance(item, dict):
            entry = check_keys(item, at, required=("expr",), optional=("unit", "doc"))
            out.append(Expression(name, parse_expr(entry["expr"], child_where(entry, at, "expr")),
                                  _unit(entry, at), _doc(entry, at)))
        else:
            out.append(Expression(name, parse_expr(item, at)))
    return tuple(out)


def _amount(value: Any, where: Where, unit: str, constants: Mapping[str, float],
            what: str) -> float:
    """A non-negative amount in ``unit``: a number in that unit, a quantity with its own
    unit (``0.5 um``), or an expression of constants (internal units)."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        number = expect_number(value, where)
    else:
        text = expect_str(value, where)
        match = _QUANTITY.match(text)
        factor = size(unit)
        if match is not None:
            try:
                number = float(match.group(1)) * size(match.group(2)) / factor
            except UnitError as exc:
                raise SpecError(where, f"{what}: {exc.message}") from None
            _check_same_kind(match.group(2), unit, where, f"{what}: '{text.strip()}'")
        else:
            spec = parse_expr(text, where)
            env = dict(constants)
            try:
                number = expr.evaluate(spec.node, env) / factor
            except expr.ExprError as exc:
                known = ", ".join(constants) or "none"
                raise SpecError(where, f"{what}: {exc.detail} (a number in the column's unit, "
                                       f"a quantity such as '0.5 um', or an expression of "
                                       f"the constants: {known})") from None
    if not math.isfinite(number) or number < 0:
        raise SpecError(where, f"{what} must be a number of at least 0, found {number:g}")
    return number


def _check_same_kind(given: str, unit: str, where: Where, what: str) -> None:
    from symcal.base.units import internal_unit

    if unit and internal_unit(given) != internal_unit(unit):
        raise SpecError(where, f"{what} is not in a unit of the column, which is in "
                               f"'{unit}'")


COLUMN_KEYS = ("expr", "solve", "start", "unit", "noise", "quantization", "stream", "doc")


def _columns(value: Any, where: Where, constants: Mapping[str, float]) -> tuple[Column, ...]:
    mapping = expect_map(value, where)
    if not mapping:
        raise SpecError(where, "a scenario needs at least one column (a reading to write)")
    out = []
    for key, item in mapping.items():
        at = child_where(mapping, where, key)
        name = expect_symbol(key, at, "a column's name")
        if not isinstance(item, dict):
            out.append(Column(name, parse_expr(item, at), where=at))
            continue
        entry = check_keys(item, at, optional=COLUMN_KEYS)
        kinds = [k for k in ("expr", "solve") if entry.get(k) is not None]
        if len(kinds) != 1:
            found = " and ".join(f"'{k}'" for k in kinds) or "neither"
            raise SpecError(at, f"a column needs exactly one of 'expr' (its reading) or "
                                f"'solve' (an equation its reading makes vanish); found {found}")
        unit = _unit(entry, at)

        def spec(k: str, entry: YMap = entry, at: Where = at) -> ExprSpec | None:
            return None if entry.get(k) is None else parse_expr(entry[k],
                                                                child_where(entry, at, k))

        if entry.get("start") is not None and kinds[0] != "solve":
            raise SpecError(child_where(entry, at, "start"),
                            "'start' is the first guess of a 'solve' column; this column "
                            "has an 'expr'")
        amounts = {k: 0.0 if entry.get(k) is None else _amount(
            entry[k], child_where(entry, at, k), unit, constants, k)
            for k in ("noise", "quantization")}
        stream = name if entry.get("noise") is not None else ""
        if entry.get("stream") is not None:
            stream = expect_name(entry["stream"], child_where(entry, at, "stream"),
                                 "a stream's name")
        out.append(Column(name, spec("expr"), spec("solve"), spec("start"), unit,
                          amounts["noise"], amounts["quantization"], stream,
                          _doc(entry, at), at))
    return tuple(out)


def _effects(value: Any, where: Where, columns: tuple[Column, ...],
             constants: Mapping[str, float]) -> tuple[Effect, ...]:
    mapping = expect_map(value, where)
    units = {c.name: c.unit for c in columns}
    out = []
    for key, item in mapping.items():
        at = child_where(mapping, where, key)
        name = expect_name(key, at, "an effect's name")
        if item is None:
            continue
        entry = check_keys(item, at, optional=("doc", "on", "values", "add", "slips"))
        on = True if entry.get("on") is None else expect_bool(entry["on"],
                                                              child_where(entry, at, "on"))
        values = _values(entry.get("values"), child_where(entry, at, "values"),
                         "an effect's value")
        add_at = child_where(entry, at, "add")
        adds = expect_map(entry.get("add"), add_at)
        add = tuple((expect_name(k, child_where(adds, add_at, k), "a target"),
                     parse_expr(v, child_where(adds, add_at, k))) for k, v in adds.items())
        slips_at = child_where(entry, at, "slips")
        slip_map = expect_map(entry.get("slips"), slips_at)
        slips = []
        for col, spec in slip_map.items():
            sw = child_where(slip_map, slips_at, col)
            if col not in units:
                raise SpecError(sw, f"no column '{excerpt(str(col))}'"
                                    f"{did_you_mean(str(col), units)} to slip; columns: "
                                    f"{', '.join(units)}")
            sm = check_keys(spec, sw, required=("fraction", "size"))
            fw = child_where(sm, sw, "fraction")
            fraction = expect_number(sm["fraction"], fw)
            if not 0.0 <= fraction <= 1.0:
                raise SpecError(fw, f"fraction is a share of the observations: expected a "
                                    f"number from 0 to 1, found {fraction:g}")
            slips.append(Slip(col, fraction, _amount(sm["size"], child_where(sm, sw, "size"),
                                                      units[col], constants, "size")))
        if not (values or add or slips):
            raise SpecError(at, "an effect needs 'add' (terms it adds) or 'slips'; remove "
                                "it with ~ or switch it off with 'on: false'")
        out.append(Effect(name, values, add, tuple(slips), on, _doc(entry, at), at))
    return tuple(out)


# --------------------------------------------------------------------------- runs


def _range(value: Any, where: Where, factor: float) -> tuple[float, float]:
    items = expect_list(value, where)
    if len(items) != 2:
        raise SpecError(where, f"expected [lo, hi], a list of 2 numbers, found {len(items)}")
    lo, hi = (expect_number(v, child_where(items, where, i)) for i, v in enumerate(items))
    if lo > hi:
        raise SpecError(where, f"expected lo <= hi, found [{lo:g}, {hi:g}]")
    return lo * factor, hi * factor


def _state_entries(mapping: YMap, where: Where, states: tuple[State, ...], motion_keys:
                   tuple[str, ...], what: str) -> dict[str, tuple[str, Any, Where]]:
    """The states a motion names, checked: ``{state: (kind, value, where)}``."""
    names = {s.name: s for s in states}
    out: dict[str, tuple[str, Any, Where]] = {}
    for key, item in mapping.items():
        if key in motion_keys:
            continue
        kw = child_where(mapping, where, key)
        if key not in names:
            raise SpecError(kw, f"unknown key '{excerpt(str(key))}'"
                                f"{did_you_mean(str(key), [*motion_keys, *names])}; {what} "
                                f"takes {', '.join(motion_keys)} and the states "
                                f"({', '.join(names)})")
        out[key] = ("range" if isinstance(item, YList) else "value", item, kw)
    return out


def _placed(states: tuple[State, ...], given: Mapping[str, tuple[str, Any, Where]],
            where: Where, ranges_ok: bool = True) -> tuple[tuple[tuple[str, tuple[float, float]],
                                                              ...], tuple[tuple[str, float], ...]]:
    ranges, held = [], []
    for state in states:
        if state.name in given:
            kind, item, kw = given[state.name]
            if kind == "range":
                if not ranges_ok:
                    raise SpecError(kw, "expected a number (a held value)")
                ranges.append((state.name, _range(item, kw, state.size)))
            else:
                held.append((state.name, expect_number(item, kw) * state.size))
        elif state.default is not None:
            held.append((state.name, state.default))
        else:
            raise SpecError(where, f"state '{state.name}' is not given: give a range "
                                   f"[lo, hi] or a value, or a 'value' in 'states'")
    return tuple(ranges), tuple(held)


def _count(mapping: YMap, where: Where, key: str) -> int:
    return expect_int(mapping[key], child_where(mapping, where, key), minimum=1,
                      maximum=MAX_SAMPLES)


def _scatter(value: Any, where: Where, states: tuple[State, ...]) -> Scatter:
    mapping = expect_map(value, where)
    keys = ("n", "dwell", "dwell_at")
    given = _state_entries(mapping, where, states, keys, "a scatter")
    if "n" not in mapping:
        raise SpecError(where, "missing required key 'n'")
    ranges, held = _placed(states, given, where)
    dwell = 0.0
    if mapping.get("dwell") is not None:
        dw = child_where(mapping, where, "dwell")
        dwell = expect_number(mapping["dwell"], dw)
        if not 0.0 <= dwell <= 1.0:
            raise SpecError(dw, f"dwell is a share of the draws: expected a number from 0 to "
                                f"1, found {dwell:g}")
    ranged = [name for name, _ in ranges]
    dwell_at = tuple(ranged)
    if mapping.get("dwell_at") is not None:
        aw = child_where(mapping, where, "dwell_at")
        items = expect_list(mapping["dwell_at"], aw)
        dwell_at = ()
        for i, item in enumerate(items):
            iw = child_where(items, aw, i)
            if item not in ranged:
                raise SpecError(iw, f"'{excerpt(str(item))}' is not a ranged state of this "
                                    f"scatter{did_you_mean(str(item), ranged)}; ranged: "
                                    f"{', '.join(ranged) or 'none'}")
            dwell_at += (str(item),)
    return Scatter(_count(mapping, where, "n"), ranges, held, dwell,
                   tuple(s for s in ranged if s in dwell_at))


def _dwells(value: Any, where: Where, states: tuple[State, ...]) -> Dwells:
    mapping = expect_map(value, where)
    given = _state_entries(mapping, where, states, ("count", "samples"), "dwells")
    for key in ("count", "samples"):
        if key not in mapping:
            raise SpecError(where, f"missing required key '{key}'")
    ranges, held = _placed(states, given, where)
    count, samples = _count(mapping, where, "count"), _count(mapping, where, "samples")
    if count * samples > MAX_SAMPLES:
        raise SpecError(where, f"count x samples is {count * samples}, more than "
                               f"{MAX_SAMPLES} observations")
    return Dwells(count, samples, ranges, held)


def _points(mapping: YMap, where: Where, key: str, states: dict[str, State]
            ) -> dict[str, float]:
    kw = child_where(mapping, where, key)
    points = expect_map(mapping[key], kw)
    out = {}
    for name, item in points.items():
        iw = child_where(points, kw, name)
        if name not in states:
            raise SpecError(iw, f"no state '{excerpt(str(name))}'"
                                f"{did_you_mean(str(name), states)}; states: "
                                f"{', '.join(states)}")
        out[str(name)] = expect_number(item, iw) * states[name].size
    return out


def _line(value: Any, where: Where, states: tuple[State, ...]) -> Line:
    mapping = expect_map(value, where)
    keys = ("n", "from", "to", "jitter")
    given = _state_entries(mapping, where, states, keys, "a line")
    for key in ("n", "from", "to"):
        if key not in mapping:
            raise SpecError(where, f"missing required key '{key}'")
    by_name = {s.name: s for s in states}
    start = _points(mapping, where, "from", by_name)
    end = _points(mapping, where, "to", by_name)
    jitter = _points(mapping, where, "jitter", by_name) if mapping.get("jitter") else {}
    for name, sigma in jitter.items():
        if sigma < 0:
            raise SpecError(child_where(mapping, where, "jitter").child(name),
                            f"a jitter is a standard deviation: expected a number of at "
                            f"least 0, found {sigma:g}")
    first, last = [], []
    for state in states:
        name = state.name
        held = given.get(name)
        if held is not None:
            if name in start or name in end:
                raise SpecError(held[2], f"state '{name}' is given both as a held value and "
                                         "in 'from'/'to'")
            if held[0] == "range":
                raise SpecError(held[2], "expected a number (a held value); a line moves "
                                         "the states given in 'from' and 'to'")
            a = b = expect_number(held[1], held[2]) * state.size
        elif name in start or name in end:
            a = start[name] if name in start else end[name]
            b = end.get(name, a)
        elif state.default is not None:
            a = b = state.default
        else:
            raise SpecError(where, f"state '{name}' is not given: give it in 'from' (and "
                                   f"'to'), a held value, or a 'value' in 'states'")
        first.append((name, a))
        last.append((name, b))
    order = [s.name for s in states]
    return Line(_count(mapping, where, "n"), tuple(first), tuple(last),
                tuple((k, jitter[k]) for k in order if k in jitter))


def _series(value: Any, where: Where, states: tuple[State, ...]) -> Series:
    mapping = expect_map(value, where)
    given = _state_entries(mapping, where, states, ("n",), "a series")
    if "n" not in mapping:
        raise SpecError(where, "missing required key 'n'")
    exprs = []
    for state in states:
        if state.name in given:
            _, item, kw = given[state.name]
            exprs.append((state.name, parse_expr(item, kw)))
        elif state.default is not None:
            exprs.append((state.name, parse_expr(repr(state.default / state.size), where)))
        else:
            raise SpecError(where, f"state '{state.name}' is not given: give an expression "
                                   f"of t, a value, or a 'value' in 'states'")
    return Series(_count(mapping, where, "n"), tuple(exprs))


_PARSERS: dict[str, Callable[[Any, Where, tuple[State, ...]], Motion]] = {
    "scatter": _scatter, "line": _line, "dwells": _dwells, "series": _series}


def _run(name: str, value: Any, where: Where, states: tuple[State, ...]) -> Run:
    mapping = check_keys(value, where, optional=(*MOTIONS, "dt", "t0", "doc"))
    motions = [key for key in MOTIONS if mapping.get(key) is not None]
    if len(motions) != 1:
        found = " and ".join(f"'{m}'" for m in motions) or "none"
        raise SpecError(where, f"a run needs exactly one motion, one of "
                               f"{', '.join(MOTIONS)}; found {found}")
    kind = motions[0]
    motion = _PARSERS[kind](mapping[kind], child_where(mapping, where, kind), states)
    dt = DEFAULT_DT
    if mapping.get("dt") is not None:
        dw = child_where(mapping, where, "dt")
        dt = expect_number(mapping["dt"], dw)
        if dt <= 0:
            raise SpecError(dw, f"expected a positive number, found {dt:g}")
    t0 = 0.0 if mapping.get("t0") is None else expect_number(mapping["t0"],
                                                             child_where(mapping, where, "t0"))
    return Run(name, motion, dt, t0, _doc(mapping, where), where)


def _runs(value: Any, where: Where, states: tuple[State, ...]) -> tuple[Run, ...]:
    mapping = expect_map(value, where)
    if not mapping:
        raise SpecError(where, "a scenario needs at least one run")
    return tuple(_run(expect_name(key, child_where(mapping, where, key), "a run name"), run,
                      child_where(mapping, where, key), states)
                 for key, run in mapping.items())


# --------------------------------------------------------------------------- design


def design_keys(run: Run) -> tuple[str, ...]:
    """What a design may change in ``run``: its ranged states, ``dwell`` (a scatter) and
    ``n``."""
    motion = run.motion
    if not isinstance(motion, (Scatter, Dwells)):
        return ()
    keys = tuple(name for name, _ in motion.ranges)
    return (*keys, "dwell", "n") if isinstance(motion, Scatter) else (*keys, "n")


def _design(value: Any, where: Where, runs: tuple[Run, ...], states: tuple[State, ...]
            ) -> DesignSpace:
    mapping = check_keys(value, where, required=("run", "limits"), optional=("doc",))
    rw = child_where(mapping, where, "run")
    name = expect_name(mapping["run"], rw, "a run name")
    names = tuple(run.name for run in runs)
    if name not in names:
        raise SpecError(rw, f"no run named '{name}'{did_you_mean(name, names)}; runs: "
                            f"{', '.join(names)}")
    run = runs[names.index(name)]
    if run.motion.kind not in DESIGNABLE:
        raise SpecError(rw, f"run '{name}' is a {run.motion.kind}; only a scatter or dwells "
                            "run can be designed")
    keys = design_keys(run)
    lw = child_where(mapping, where, "limits")
    limits_map = check_keys(mapping["limits"], lw, optional=keys)
    if not limits_map:
        raise SpecError(lw, f"lists nothing that may change; list some of {', '.join(keys)}")
    units = {s.name: s for s in states}
    limits = []
    motion = run.motion
    assert isinstance(motion, (Scatter, Dwells))
    ranges = dict(motion.ranges)
    for key in keys:
        if key not in limits_map:
            continue
        kw = child_where(limits_map, lw, key)
        lo, hi = _range(limits_map[key], kw, 1.0)
        if key == "dwell" and not 0.0 <= lo <= hi <= 1.0:
            raise SpecError(kw, f"dwell is a share of the draws: its limits must lie within "
                                f"[0, 1], found [{lo:g}, {hi:g}]")
        if key == "n" and (lo != int(lo) or hi != int(hi) or lo < 1 or hi > MAX_SAMPLES):
            raise SpecError(kw, f"n's limits must be whole numbers from 1 to {MAX_SAMPLES}, "
                                f"found [{lo:g}, {hi:g}]")
        if key == "n":
            a = b = float(motion.n)
        elif key == "dwell":
            a = b = motion.dwell
        else:
            factor = units[key].size
            a, b = ranges[key][0] / factor, ranges[key][1] / factor
        if a < lo - 1e-12 * max(1.0, abs(lo)) or b > hi + 1e-12 * max(1.0, abs(hi)):
            shown = f"{a:g}" if a == b else f"[{a:g}, {b:g}]"
            raise SpecError(kw, f"run '{name}' has {key} {shown}, outside its limits "
                                f"[{lo:g}, {hi:g}]")
        limits.append((key, (lo, hi)))
    return DesignSpace(name, tuple(limits), _doc(mapping, where), where)


# --------------------------------------------------------------------------- entry points


TOP_KEYS = ("doc", "extends", "constants", "truth", "expressions", "effects", "design")


def _unique(scenario: Scenario) -> None:
    """No name declared twice across constants, truth, effect values, states, the time,
    expressions and columns (effect values may repeat across effects)."""
    seen: dict[str, str] = {TIME: "the built-in time state"}
    groups: list[tuple[str, list[tuple[str, Where]]]] = [
        ("constants", [(c.name, c.where) for c in scenario.constants]),
        ("truth", [(v.name, v.where) for v in scenario.truth]),
        ("states", [(s.name, s.where) for s in scenario.states]),
        ("expressions", [(e.name, e.spec.where) for e in scenario.expressions]),
        ("columns", [(c.name, c.where) for c in scenario.columns if c.solve is not None]),
    ]
    for section, entries in groups:
        for name, where in entries:
            if name in seen:
                raise SpecError(where, f"'{name}' is already defined in {seen[name]}")
            seen[name] = section
    for effect in scenario.effects:
        for v in effect.values:
            if v.name in seen:
                raise SpecError(v.where, f"'{v.name}' is already defined in {seen[v.name]}")
    expressions = {e.name for e in scenario.expressions}
    for c in scenario.columns:     # an 'expr' column is a symbol only as an effect's target
        if c.expr is not None and c.name in expressions:
            raise SpecError(c.where, f"column '{c.name}' has the name of an expression: an "
                                     "effect adding to it would be ambiguous; rename one")


def parse_scenario(doc: YMap, where: Where) -> Scenario:
    """Validate a loaded scenario document.

    Parameters
    ----------
    doc
        The top-level mapping (extends already merged).
    where
        Its provenance.

    Returns
    -------
    Scenario
        The frozen scenario (its symbols resolved lazily, on the first simulation).

    Raises
    ------
    SpecError
        On any unknown or missing key, wrong type or invalid value, naming file:line and
        key path.
    """
    check_keys(doc, where, required=("scenario", "states", "columns", "runs"),
               optional=TOP_KEYS)
    name = expect_name(doc["scenario"], child_where(doc, where, "scenario"), "a scenario name")
    constants = _constants(doc.get("constants"), child_where(doc, where, "constants"))
    numbers = {c.name: c.internal for c in constants}
    states = _states(doc["states"], child_where(doc, where, "states"))
    columns = _columns(doc["columns"], child_where(doc, where, "columns"), numbers)
    runs_where = child_where(doc, where, "runs")
    runs = _runs(doc["runs"], runs_where, states)
    design, inherited = None, ""
    if doc.get("design") is not None:
        design_where = child_where(doc, where, "design")
        try:
            design = _design(doc["design"], design_where, runs, states)
        except SpecError as err:
            if design_where.via is None:
                raise       # the file's own section: wrong as written
            inherited = str(err)
    text = doc.get("doc")
    scenario = Scenario(
        name=name,
        states=states,
        columns=columns,
        runs=runs,
        constants=constants,
        truth=_values(doc.get("truth"), child_where(doc, where, "truth"), "a true value"),
        expressions=_expressions(doc.get("expressions"), child_where(doc, where,
                                                                     "expressions")),
        effects=_effects(doc.get("effects"), child_where(doc, where, "effects"), columns,
                         numbers),
        design=design,
        inherited_design=inherited,
        doc="" if text is None else " ".join(expect_str(text, child_where(doc, where,
                                                                           "doc")).split()),
        source=where.file,
        runs_where=runs_where,
        document=doc,
        where=where,
    )
    _unique(scenario)
    check(scenario)
    return scenario


def load_scenario(path: str | Path) -> Scenario:
    """Load and validate a scenario YAML file.

    Parameters
    ----------
    path
        The scenario file (schema in this module's docstring).

    Returns
    -------
    Scenario
        A frozen scenario; change it with :meth:`Scenario.overlay`.

    Raises
    ------
    SpecError
        If the file is missing, is not valid YAML, or does not follow the schema; the
        message names ``file:line``, the key path and, for unknown keys or symbols, the
        nearest valid one.
    """
    doc, where = load_with_extends(path, "scenario", merge_scenario)
    return parse_scenario(doc, where)
