"""Spec → symbolic :class:`Problem`: parameters θ, per-observation inputs u, named residuals.

One build per problem.  Names are resolved lazily and memoised: a constraint pulls in the
problem expressions and instance outputs it refers to, an instance pulls in its input
bindings, and a cycle among definitions is reported with its path.  Models see only their
own symbols; problems see constants, parameters, expressions, data columns and dotted
instance signals (``s1.p_hat``).

The build leaves two kinds of symbols open, and the problem's views are derived from it by
substitution, never by building again:

- every implicit definition (``x = F(x)``) is a placeholder symbol with its start and its
  map; the problem in use unrolls the maps (fixed-point steps), the explicit twin
  (:attr:`Problem.explicit`) takes every start (zero steps: the explicit model);
- every instance output carries a *hook*, a symbol added to its error expression when
  the output is ``reading + error`` (inside an implicit definition when there is one) and
  to the output otherwise; the problem in use sets the hooks to zero, the diagnostic view
  (:attr:`Problem.diagnostic`) keeps them, so that the derivative of any residual with
  respect to a term added where it belongs is exact.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import casadi as ca

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import SpecError, Where
from symcal.base.files import input_refusal
from symcal.base.units import Unit, parse_unit, size, text_of
from symcal.language import expr
from symcal.language.common import ExprSpec, ParameterSpec, apply_parameter_overrides, parse_expr
from symcal.language.dimensions import DimensionError, describe, same_dimension, unit_of
from symcal.language.loss import LossSpec
from symcal.language.model_file import ImplicitSpec, ModelSpec
from symcal.language.options import SolveOptions
from symcal.language.problem_file import (
    ColumnSpec,
    ComparisonSpec,
    DatasetSpec,
    InstanceSpec,
    ProblemSpec,
    load_problem_spec,
)
from symcal.language.yamlio import display_path

#: At most this many bytes of a data file are read to find its column names for a hint.
HEADER_BYTES = 1 << 16


def data_columns(path: Path) -> tuple[str, ...]:
    """The column names of a CSV (its header line) or NPZ file, or () when unreadable."""
    if input_refusal(path, HEADER_BYTES << 14) is not None:   # a FIFO must never block
        return ()
    try:
        if path.suffix.lower() == ".npz":
            import numpy as np

            with np.load(path, allow_pickle=False) as npz:
                return tuple(npz.files)
        with open(path, "rb") as fh:
            head = fh.read(HEADER_BYTES).decode("utf-8-sig", errors="replace")
    except (OSError, ValueError):
        return ()
    return tuple(c.strip() for c in head.splitlines()[0].split(",")) if head else ()


@dataclass(frozen=True)
class Parameter:
    """One scalar parameter of the problem, named ``instance.name`` or ``name``."""

    name: str
    value: float
    unit: str
    lower: float
    upper: float
    fixed: bool
    scale: float
    doc: str
    where: Where


@dataclass(frozen=True, eq=False)
class Quantity:
    """A named symbolic quantity of one observation (constraint, expression or signal)."""

    name: str
    sx: ca.SX
    unit: str = ""
    sigma: float = 1.0
    doc: str = ""
    period: float | None = None
    loss: LossSpec | None = None


@dataclass(frozen=True, eq=False)
class Comparison:
    """An estimate of a quantity and its independent reference."""

    name: str
    estimate: ca.SX
    reference: ca.SX
    unit: str
    datasets: tuple[str, ...] | None
    remove_mean: bool
    doc: str


@dataclass(frozen=True, eq=False)
class ImplicitOutput:
    """A definition solved by fixed-point steps ``x = F(x)``, with what checks it.

    ``derivative`` is ∂F/∂x at the final iterate (the map contracts where |·| < 1);
    ``last_step`` is the change made by the last step (how far from converged).
    """

    name: str
    steps: int
    derivative: ca.SX
    last_step: ca.SX


@dataclass(frozen=True)
class Stage:
    """One step of a calibration: constraints used and parameters freed (by name)."""

    name: str
    constraints: tuple[str, ...]
    free: tuple[str, ...]
    method: str = "auto"
    doc: str = ""


@dataclass(frozen=True)
class Instance:
    """A sensor instance of the problem: its model, its input bindings (as written)."""

    name: str
    model: ModelSpec
    bindings: Mapping[str, str]
    doc: str


@dataclass(frozen=True)
class Study:
    """On what data and in which steps a problem is solved.

    ``weighting``: ``"equal"`` (the cost is Σ (g/σ)² as written) or ``"estimated"`` (each
    stage with several constraints is solved again, weighted by the inverse of their
    covariance estimated from the residuals: feasible generalised least squares).
    """

    datasets: Mapping[str, DatasetSpec]
    stages: tuple[Stage, ...]
    weighting: str


@dataclass(frozen=True, eq=False)
class Problem:
    """A calibration problem in symbolic form: the system, the study, the solve options.

    Attributes
    ----------
    parameters
        Every scalar parameter, in the order of ``theta``.
    theta
        SX column of parameter symbols.
    columns
        Names of the data columns the problem reads, in the order of ``u``.
    u
        SX column of per-observation input symbols.
    constraints
        Named residuals g(θ, u) that must vanish for consistent measurements.
    expressions
        The problem's named expressions.
    signals
        Every instance input and output (``s1.p``, ``s1.p_hat``).
    comparisons
        Estimates to compare with a reference sensor.
    study
        Datasets, stages and weighting (:class:`Study`).
    options
        The solve options the problem file declares (``solver:``).
    instances
        The sensor instances by name.
    column_specs
        Every column the problem declares (used or not), with unit, role and doc.
    implicit
        Definitions solved by fixed-point steps, with their convergence checks.
    hooks
        Instance output → its hook symbol (see :attr:`diagnostic`).
    spec
        The validated spec the problem was built from (for derived problems).
    """

    name: str
    doc: str
    path: Path
    parameters: tuple[Parameter, ...]
    theta: ca.SX
    columns: tuple[str, ...]
    u: ca.SX
    constraints: tuple[Quantity, ...]
    expressions: tuple[Quantity, ...]
    signals: tuple[Quantity, ...]
    comparisons: tuple[Comparison, ...]
    study: Study
    options: SolveOptions
    instances: Mapping[str, Instance]
    column_specs: Mapping[str, ColumnSpec]
    implicit: tuple[ImplicitOutput, ...]
    hooks: Mapping[str, ca.SX]
    spec: ProblemSpec = field(repr=False)
    _build: _Build | None = field(default=None, repr=False)
    _mode: str = field(default="use", repr=False)

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Names of all parameters, in the order of ``theta``."""
        return tuple(p.name for p in self.parameters)

    @cached_property
    def index(self) -> dict[str, int]:
        """Position of each parameter in θ, by name."""
        return {p.name: i for i, p in enumerate(self.parameters)}

    @property
    def free(self) -> tuple[bool, ...]:
        """Which parameters are free (not fixed)."""
        return tuple(not p.fixed for p in self.parameters)

    @property
    def datasets(self) -> Mapping[str, DatasetSpec]:
        """Where each named dataset comes from (``study.datasets``)."""
        return self.study.datasets

    @property
    def stages(self) -> tuple[Stage, ...]:
        """The ordered steps of the calibration (``study.stages``)."""
        return self.study.stages

    @property
    def weighting(self) -> str:
        """``"equal"`` or ``"estimated"`` (``study.weighting``)."""
        return self.study.weighting

    def constraint(self, name: str) -> Quantity:
        """The constraint called ``name``."""
        return next(c for c in self.constraints if c.name == name)

    def columns_of(self, sx: ca.SX) -> list[str]:
        """Data columns an expression depends on, in ``u`` order."""
        used = {v.name() for v in ca.symvar(sx)}
        return [c for c in self.columns if c in used]

    def quantity(self, name: str) -> ca.SX:
        """The SX of a named constraint, expression, signal or comparison (estimate minus
        reference), looked up in that order: a comparison named like an expression is
        reached through the expression it compares.

        Raises
        ------
        KeyError
            With the names there are, for an unknown name.
        """
        for group in (self.constraints, self.expressions, self.signals):
            for q in group:
                if q.name == name:
                    return q.sx
        for comp in self.comparisons:
            if comp.name == name:
                return comp.estimate - comp.reference
        known = [q.name for g in (self.constraints, self.expressions, self.signals) for q in g]
        known += [c.name for c in self.comparisons]
        raise KeyError(f"problem '{self.name}' has no quantity '{name}'"
                       f"{did_you_mean(name, known)}")

    def source_files(self) -> tuple[Path, ...]:
        """Every file the problem was built from: the problem file, the files it extends,
        and its model files (through their ``extends`` too)."""
        own = self.spec.sources or (Path(self.path),)
        return (*own, *(f for f in self.model_files() if f not in own))

    def model_files(self) -> tuple[Path, ...]:
        """Every model file the problem's instances read, through ``extends`` too."""
        files: list[Path] = []
        for inst in self.instances.values():
            model: ModelSpec | None = inst.model
            while model is not None:
                if model.path not in files:
                    files.append(model.path)
                model = model.extends
        return tuple(files)

    @property
    def explicit(self) -> Problem | None:
        """With implicit definitions: the same problem with every one at its start (zero
        fixed-point steps: the explicit model), to start the solver from a closed form."""
        if not self.implicit or self._build is None or self._mode != "use":
            return None
        return self._view("explicit")

    @property
    def diagnostic(self) -> Problem:
        """The problem with the hooks left open: evaluate with the hooks as extra rows of
        u set to zero; the derivative of a residual by a hook is its derivative by that
        sensor output."""
        if self._build is None or self._mode == "diagnostic":
            return self
        return self._view("diagnostic")

    def _view(self, mode: str) -> Problem:
        cache = self.__dict__.setdefault("_views", {})
        if mode not in cache:
            assert self._build is not None
            cache[mode] = self._build.problem(mode)
        return cache[mode]

    def with_instance(self, name: str, model: ModelSpec,
                      bindings: Mapping[str, str] | None = None) -> Problem:
        """The problem with instance ``name`` using ``model``, its bindings kept and
        ``bindings`` (input → expression text) added; this problem is not modified."""
        old = self.spec.system.instances[name]
        new_bindings = dict(old.bindings)
        for key, text in (bindings or {}).items():
            new_bindings[key] = parse_expr(str(text), old.where.child("inputs").child(key))
        new = replace(old, model=model, bindings=new_bindings)
        instances = {k: (new if k == name else v) for k, v in self.spec.system.instances.items()}
        return build_problem(replace(self.spec, system=replace(self.spec.system,
                                                               instances=instances)))

    def with_weighting(self, weighting: str) -> Problem:
        """The problem with another weighting of its constraints (no rebuild)."""
        if weighting == self.weighting:
            return self
        return replace(self, study=replace(self.study, weighting=weighting))


def _declared(text: str) -> Unit | None:
    """The unit a declaration names, or None when it names none (not checked)."""
    return parse_unit(text) if text else None


def _unit_text(declared: str, found: Unit | None) -> str:
    """The unit a quantity is shown in: as declared, else the unit its expression has."""
    return declared or (text_of(found) if found is not None else "")


def _scaled(sx: ca.SX, unit: str) -> ca.SX:
    """A symbol's value in internal units (mm, rad, s): ``sx`` times the size of its
    declared unit (unchanged when that is 1)."""
    factor = size(unit)
    return sx if factor == 1.0 else sx * factor


def _check_declared(where: Where, what: str, declared: Unit | None,
                    found: Unit | None) -> None:
    """Refuse a declared unit of another dimension than the expression's."""
    if not same_dimension(declared, found):
        raise SpecError(where, f"{what} is declared in {describe(declared)}, but its "
                               f"expression is in {describe(found)}")


def _enter(stack: list[str], key: str, where: Where) -> None:
    """Push ``key`` on the resolution stack, or report the cycle it would close."""
    if key in stack:
        cycle = stack[stack.index(key):] + [key]
        raise SpecError(where, f"cyclic definition: {' -> '.join(cycle)}")
    stack.append(key)


@dataclass
class _Implicit:
    """An implicit definition left open by the build: x = F(x), from ``start``."""

    key: str
    symbol: ca.SX
    start: ca.SX
    fmap: ca.SX
    steps: int
    where: Where


class _Scope:
    """Lazy, memoised resolution of names to SX with cycle detection.

    ``values`` are ready symbols; ``defs`` are expressions resolved on first use;
    ``fallback`` resolves other names (columns, dotted signals) or returns None.  A name in
    ``implicit`` resolves to a placeholder symbol whose start and map are recorded in
    ``opened``; a name in ``hooked`` gets its hook symbol added to its definition.
    """

    def __init__(
        self,
        label: str,
        values: dict[str, ca.SX],
        defs: dict[str, ExprSpec],
        fallback: Callable[[str, Where, list[str]], ca.SX | None],
        known: Callable[[], list[str]],
        stack: list[str],
        implicit: Mapping[str, ImplicitSpec],
        opened: list[_Implicit],
        hooked: Mapping[str, ca.SX] | None = None,
        hint: Callable[[str], str] | None = None,
        units: Mapping[str, Unit | None] | None = None,
        declared: Mapping[str, Unit | None] | None = None,
        unit_fallback: Callable[[str], Unit | None] | None = None,
    ) -> None:
        self.label = label
        self.values = dict(values)
        self.defs = defs
        self.fallback = fallback
        self.known = known
        self.stack = stack
        self.implicit = implicit
        self.opened = opened
        self.hooked = dict(hooked or {})
        self.hint = hint or (lambda _name: "")
        self.units: dict[str, Unit | None] = dict(units or {})
        self.declared = dict(declared or {})
        self.unit_fallback = unit_fallback or (lambda _name: None)

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
        return self.unit_fallback(name)

    def _def_unit(self, name: str) -> Unit | None:
        """The unit of definition ``name``: as declared (checked against its expression's),
        else its expression's."""
        spec = self.defs[name]
        found = self.unit(spec)
        want = self.declared.get(name)
        _check_declared(spec.where, f"'{name}'", want, found)
        return want if want is not None else found

    def lookup(self, name: str, where: Where) -> ca.SX:
        if name in self.values:
            return self.values[name]
        if name in self.implicit and name in self.defs:
            return self._open_implicit(name, where)
        if name in self.defs:
            _enter(self.stack, f"{self.label}{name}", where)
            try:
                value = self.build(self.defs[name])
            finally:
                self.stack.pop()
            if name in self.hooked:
                value = value + self.hooked[name]
            self.values[name] = value
            self.units[name] = self._def_unit(name)
            return value
        found = self.fallback(name, where, self.stack)
        if found is not None:
            return found
        pool = [k for k in self.known() if k != "pi"]  # pi is never what a typo meant
        raise SpecError(where, f"unknown symbol '{name}'{did_you_mean(name, pool)}"
                               f"{self.hint(name)}")

    def _open_implicit(self, name: str, where: Where) -> ca.SX:
        """A placeholder for ``name``; its start and its map are built and recorded."""
        spec = self.implicit[name]
        key = f"{self.label}{name}"
        _enter(self.stack, key, where)  # a start that needs the name itself is a cycle
        try:
            start = self.build(spec.start)
        finally:
            self.stack.pop()
        symbol = ca.SX.sym(key)
        self.values[name] = symbol
        start_unit = self.unit(spec.start)
        want = self.declared.get(name)
        _check_declared(spec.start.where, f"the start of '{name}'", want, start_unit)
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
        self.opened.append(_Implicit(key, symbol, start, fmap, spec.steps, spec.where))
        return symbol


def _instance_scope(
    inst: InstanceSpec, inputs: dict[str, ca.SX], params: dict[str, ca.SX], stack: list[str],
    opened: list[_Implicit], hooked: Mapping[str, ca.SX],
    input_units: Mapping[str, Unit | None],
) -> _Scope:
    model = inst.model
    values: dict[str, ca.SX] = {k: ca.SX(c.value * size(c.unit))
                                for k, c in model.constants.items()}
    values.update(inputs)
    values.update(params)
    values["pi"] = ca.SX(ca.pi)
    units: dict[str, Unit | None] = {k: _declared(c.unit)
                                          for k, c in model.constants.items()}
    units.update(input_units)
    units.update({k: _declared(p.unit) for k, p in model.parameters.items()})
    units["pi"] = _declared("1")
    defs = dict(model.expressions)
    defs.update({k: o.expr for k, o in model.outputs.items()})

    def fallback(name: str, where: Where, _stack: list[str]) -> None:
        if name.startswith("base."):
            raise SpecError(where, f"'{name}': model '{model.name}' does not redefine "
                                   f"'{name[5:]}' of a model it extends")
        if "." in name:
            raise SpecError(where, f"'{name}': a model refers only to its own symbols; dotted "
                                   "names (instance.output) belong in problem files")
        return None

    declared = {k: _declared(o.unit) for k, o in model.outputs.items()}
    return _Scope(f"{inst.name}.", values, defs, fallback,
                  lambda: [*values, *defs], stack, model.implicit, opened, hooked,
                  units=units, declared=declared)


def _unroll(fmap: ca.SX, x: ca.SX, start: ca.SX, steps: int) -> tuple[ca.SX, ca.SX]:
    """The final iterate of ``x ← fmap(x)`` from ``start`` and the change of its last step."""
    iterates = [start]
    for _ in range(steps):
        iterates.append(ca.substitute(fmap, x, iterates[-1]))
    last = iterates[-1] - iterates[-2] if steps else ca.SX.zeros(start.shape)
    return iterates[-1], last


class _Build:
    """The one build of a problem: every expression with its implicit placeholders and
    hooks open, and how to close them for each view (``use``, ``explicit``,
    ``diagnostic``)."""

    def __init__(self, spec: ProblemSpec) -> None:
        self.spec = spec
        system = spec.system
        self.model_level: list[_Implicit] = []
        self.stack: list[str] = []
        self.signals: dict[str, Quantity] = {}
        self.hooks: dict[str, ca.SX] = {}
        self.built: set[str] = set()
        self.parameters: list[Parameter] = []
        self.symbols: dict[str, ca.SX] = {}
        self.scaled: dict[str, ca.SX] = {}         # parameter symbols in internal units
        self.param_units: dict[str, Unit | None] = {}
        self.column_symbols: dict[str, ca.SX] = {}
        for inst in system.instances.values():
            for pname, pspec in inst.model.parameters.items():
                if pname in inst.overrides:
                    entry, at = inst.overrides[pname]
                    pspec = apply_parameter_overrides(pspec, entry, at)
                self._add_parameter(f"{inst.name}.{pname}", pspec)
        for pspec in system.parameters.values():
            self._add_parameter(pspec.name, pspec)
        values = {k: ca.SX(c.value * size(c.unit)) for k, c in system.constants.items()}
        values.update({p.name: self.scaled[p.name] for p in system.parameters.values()})
        values["pi"] = ca.SX(ca.pi)
        units = {k: _declared(c.unit) for k, c in system.constants.items()}
        units.update({p.name: self.param_units[p.name] for p in system.parameters.values()})
        units["pi"] = _declared("1")
        declared = {k: _declared(q.unit) for k, q in system.expressions.items()}
        # problem-level implicit names are placeholders from the start, so that instances
        # bound to them can be built before their maps (in their declared unit, if any)
        self.problem_symbols = {n: ca.SX.sym(n) for n in system.implicit}
        values.update(self.problem_symbols)
        units.update({n: declared[n] for n in system.implicit})
        defs = {k: q.expr for k, q in system.expressions.items()}
        self.signal_units: dict[str, Unit | None] = {}
        self.scope = _Scope("", values, defs, self._fallback, self._known, self.stack, {}, [],
                            hint=self._column_hint, units=units, declared=declared,
                            unit_fallback=self._unit_fallback)
        self._build_all()

    # ------------------------------------------------------------------ building

    def _add_parameter(self, name: str, p: ParameterSpec) -> None:
        scale = p.scale if p.scale is not None else (abs(p.value) or 1.0)
        self.parameters.append(Parameter(name, p.value, p.unit, p.lower, p.upper, p.fixed,
                                         scale, p.doc, p.where))
        self.symbols[name] = ca.SX.sym(name)
        self.scaled[name] = _scaled(self.symbols[name], p.unit)
        self.param_units[name] = _declared(p.unit)

    def _column_hint(self, name: str) -> str:
        """Where an unknown symbol is a column of a data file the problem names: say so."""
        for ds in self.spec.study.datasets.values():
            if ds.path is not None and name in data_columns(ds.path):
                return (f"; {display_path(ds.path)} (dataset '{ds.name}') has a column "
                        f"'{name}': declare it under 'columns:', e.g. "
                        f"columns: {{{name}: {{unit: mm}}}}")
        return ""

    def _known(self) -> list[str]:
        return [*self.scope.values, *self.scope.defs, *self.spec.system.columns,
                *self._signal_names(), *self.symbols]

    def _signal_names(self) -> list[str]:
        names = []
        for i, inst in self.spec.system.instances.items():
            model = inst.model
            points = [model.evaluation_point(n) for n in model.inputs]
            names += [f"{i}.{n}" for n in (*model.outputs, *model.inputs,
                                           *(p for p in points if p and p not in model.outputs))]
        return names

    def _fallback(self, name: str, where: Where, stack: list[str]) -> ca.SX | None:
        system = self.spec.system
        if "." in name:
            if name in self.symbols:
                return self.scaled[name]
            inst_name = name.split(".", 1)[0]
            if inst_name in system.instances:
                self._instance(system.instances[inst_name], where)
                if name in self.signals:
                    return self.signals[name].sx
                inst = system.instances[inst_name]
                known = [f"{inst_name}.{n}" for n in (*inst.model.outputs, *inst.model.inputs,
                                                      *inst.model.parameters)]
                raise SpecError(where, f"unknown symbol '{name}': instance '{inst_name}' has no "
                                       f"output, input or parameter '{name.split('.', 1)[1]}'"
                                       f"{did_you_mean(name, known)}")
            return None
        if name in system.columns:
            if name not in self.column_symbols:
                self.column_symbols[name] = ca.SX.sym(name)
            return _scaled(self.column_symbols[name], system.columns[name].unit)
        return None

    def _unit_fallback(self, name: str) -> Unit | None:
        """The unit of a name :meth:`_fallback` resolved: a parameter, a signal, a column."""
        if name in self.param_units:
            return self.param_units[name]
        if name in self.signal_units:
            return self.signal_units[name]
        column = self.spec.system.columns.get(name)
        return _declared(column.unit) if column is not None else None

    def _instance(self, inst: InstanceSpec, where: Where) -> None:
        if inst.name in self.built:
            return
        _enter(self.stack, f"{inst.name} (inputs)", where)
        try:
            inputs = {k: self.scope.build(b) for k, b in inst.bindings.items()}
        finally:
            self.stack.pop()
        model = inst.model
        input_units: dict[str, Unit | None] = {}
        for k, b in inst.bindings.items():
            found = self.scope.unit(b)
            want = _declared(model.inputs[k].unit)
            if not same_dimension(want, found):
                raise SpecError(b.where, f"input '{k}' of model '{model.name}' is in "
                                         f"{describe(want)}, but '{b.text}' bound to it is "
                                         f"in {describe(found)}")
            input_units[k] = want if want is not None else found
        params = {k: self.scaled[f"{inst.name}.{k}"] for k in inst.model.parameters}
        # an output `reading + error` is hooked on its error, where a missing term goes
        # (inside an implicit definition when there is one); any other on itself
        on_error: dict[str, ca.SX] = {}      # error expression -> its hook
        on_output: set[str] = set()           # outputs hooked on themselves
        for name in model.outputs:
            full = f"{inst.name}.{name}"
            self.hooks[full] = ca.SX.sym(f"hook:{full}")
            error = model.error_expression(name)
            if error is not None and error not in on_error:
                on_error[error] = self.hooks[full]
            else:
                on_output.add(full)
        scope = _instance_scope(inst, inputs, params, self.stack, self.model_level, on_error,
                                input_units)
        for name, out in model.outputs.items():
            full = f"{inst.name}.{name}"
            sx = scope.lookup(name, out.where)
            if full in on_output:
                sx = sx + self.hooks[full]
            self.signal_units[full] = scope.units.get(name)
            self.signals[full] = Quantity(full, sx, _unit_text(out.unit, scope.units.get(name)),
                                          doc=out.doc)
        for name in model.implicit:
            scope.lookup(name, model.implicit[name].where)
        for name, inp in model.inputs.items():
            period = None
            unit = input_units[name]
            if inp.period is not None:
                value = scope.build(inp.period)
                if not value.is_constant():
                    raise SpecError(inp.period.where, "a period must be a constant expression")
                found = scope.unit(inp.period)
                if not same_dimension(unit, found):
                    raise SpecError(inp.period.where, f"the period of input '{name}' is in "
                                                      f"{describe(found)}, but the input is in "
                                                      f"{describe(unit)}")
                period = float(ca.evalf(value))
            self.signal_units[f"{inst.name}.{name}"] = unit
            self.signals[f"{inst.name}.{name}"] = Quantity(
                f"{inst.name}.{name}", inputs[name], _unit_text(inp.unit, unit), doc=inp.doc,
                period=period)
            point = model.evaluation_point(name)
            if point is not None and point not in model.outputs:
                sx = scope.lookup(point, inp.where)
                self.signal_units[f"{inst.name}.{point}"] = scope.units.get(point)
                self.signals[f"{inst.name}.{point}"] = Quantity(
                    f"{inst.name}.{point}", sx, _unit_text(inp.unit, scope.units.get(point)),
                    doc=f"where the model evaluates its error in {name}", period=period)
        self.built.add(inst.name)

    def _build_all(self) -> None:
        system = self.spec.system
        for inst in system.instances.values():
            self._instance(inst, inst.where)
        self.expressions = []
        for k, q in system.expressions.items():
            sx = self.scope.lookup(k, q.where)
            self.expressions.append(Quantity(k, sx, _unit_text(q.unit, self.scope.units.get(k)),
                                             doc=q.doc))
        self.constraints = []
        for k, q in system.constraints.items():
            sx = self.scope.build(q.expr)
            found = self.scope.unit(q.expr)
            _check_declared(q.where, f"constraint '{k}'", _declared(q.unit), found)
            unit = _unit_text(q.unit, found)
            # a written sigma is in the constraint's unit; g/sigma is formed in internal units
            sigma = q.sigma * size(unit) if q.sigma_given else q.sigma
            self.constraints.append(Quantity(k, sx, unit, sigma, q.doc, loss=q.loss))
        self.comparisons = [self._comparison(k, c) for k, c in system.comparisons.items()]
        self.problem_level = self._problem_implicit()

    def _comparison(self, name: str, c: ComparisonSpec) -> Comparison:
        estimate, reference = self.scope.build(c.estimate), self.scope.build(c.reference)
        a, b = self.scope.unit(c.estimate), self.scope.unit(c.reference)
        if not same_dimension(a, b):
            raise SpecError(c.where, f"comparison '{name}': the estimate '{c.estimate.text}' "
                                     f"is in {describe(a)}, but the reference "
                                     f"'{c.reference.text}' is in {describe(b)}")
        _check_declared(c.where, f"comparison '{name}'", _declared(c.unit),
                        a if a is not None else b)
        unit = _unit_text(c.unit, a if a is not None else b)
        return Comparison(name, estimate, reference, unit, c.datasets, c.remove_mean, c.doc)

    def _problem_implicit(self) -> list[_Implicit]:
        system = self.spec.system
        hooks = list(self.hooks.values())
        out = []
        for n, item in system.implicit.items():
            start = self.scope.build(item.start)
            if any(ca.depends_on(start, s) for s in self.problem_symbols.values()):
                raise SpecError(item.where, "an implicit start refers to an implicit name")
            fmap = self.scope.build(system.expressions[n].expr)
            start_unit, map_unit = self.scope.unit(item.start), self.scope.units.get(n)
            if not same_dimension(start_unit, map_unit):
                raise SpecError(item.where, f"the start of '{n}' is in {describe(start_unit)}, "
                                            f"but '{n}' is in {describe(map_unit)}")
            if hooks:  # the true positions are solved from the outputs as modelled
                fmap = ca.substitute(fmap, ca.vertcat(*hooks), ca.SX.zeros(len(hooks)))
            out.append(_Implicit(n, self.problem_symbols[n], start, fmap, item.steps,
                                 item.where))
        return out

    # ------------------------------------------------------------------ closing

    def _close(self, unrolled: bool) -> tuple[list[ca.SX], list[ca.SX], list[ImplicitOutput]]:
        """Placeholders and their values in this view, and the implicit checks."""
        model, top = self.model_level, self.problem_level
        if not unrolled:
            return self._close_at_starts()
        # model level: innermost (latest opened) first, each in terms of the ones opened
        # before it; then forward, so that every value is free of model placeholders
        finals: dict[int, tuple[ca.SX, ca.SX, ca.SX]] = {}
        for k in range(len(model) - 1, -1, -1):
            d = model[k]
            later = [model[j].symbol for j in finals]
            later_values = [finals[j][0] for j in finals]
            fmap = ca.substitute(d.fmap, ca.vertcat(*later), ca.vertcat(*later_values)) \
                if later else d.fmap
            start = ca.substitute(d.start, ca.vertcat(*later), ca.vertcat(*later_values)) \
                if later else d.start
            final, last = _unroll(fmap, d.symbol, start, d.steps)
            deriv = ca.substitute(ca.jacobian(fmap, d.symbol), d.symbol, final)
            finals[k] = (final, deriv, last)
        values: list[ca.SX] = []
        outs: list[tuple[ca.SX, ca.SX]] = []
        for k in range(len(model)):
            final, deriv, last = finals[k]
            if k:
                earlier = ca.vertcat(*(m.symbol for m in model[:k]))
                final, deriv, last = ca.substitute([final, deriv, last], [earlier],
                                                   [ca.vertcat(*values)])
            values.append(final)
            outs.append((deriv, last))
        symbols = [d.symbol for d in model]
        checks_pending = [(d.key, d.steps, deriv, last) for d, (deriv, last) in zip(model, outs,
                                                                                   strict=True)]
        if top:
            x = ca.vertcat(*(d.symbol for d in top))
            fmap = ca.vertcat(*(d.fmap for d in top))
            if model:
                fmap = ca.substitute([fmap], symbols, values)[0]
            for d in top:
                if not ca.depends_on(fmap, d.symbol):
                    raise SpecError(d.where, f"'{d.key}' is declared implicit but no implicit "
                                             "definition depends on it")
            steps = max(d.steps for d in top)
            final, last = _unroll(fmap, x, ca.vertcat(*(d.start for d in top)), steps)
            norm = ca.mmax(ca.sum2(ca.fabs(ca.jacobian(fmap, x))))  # ‖∂F/∂x‖∞
            top_values = [final[k] for k in range(len(top))]
            top_symbols = [d.symbol for d in top]
            values = ca.substitute(values, top_symbols, top_values) if values else []
            closed = []
            for key, count, dv, ls in checks_pending:
                dv, ls = ca.substitute([dv, ls], top_symbols, top_values)
                closed.append((key, count, dv, ls))
            checks_pending = closed
            checks_pending.insert(0, (", ".join(d.key for d in top), steps,
                                      ca.substitute(norm, x, final), ca.mmax(ca.fabs(last))))
            symbols += top_symbols
            values += top_values
        checks = [ImplicitOutput(k, s, dv, ls) for k, s, dv, ls in checks_pending]
        return symbols, values, checks

    def _close_at_starts(self) -> tuple[list[ca.SX], list[ca.SX], list[ImplicitOutput]]:
        """Every placeholder at its start: the explicit model (zero fixed-point steps)."""
        model, top = self.model_level, self.problem_level
        symbols = [d.symbol for d in (*model, *top)]
        values = _resolve_starts(symbols, [d.start for d in (*model, *top)])
        zero = ca.SX(0)
        checks = [ImplicitOutput(d.key, 0, zero, zero) for d in model]
        if top:
            checks.insert(0, ImplicitOutput(", ".join(d.key for d in top), 0, zero, zero))
        return symbols, values, checks

    def problem(self, mode: str) -> Problem:
        """The problem in view ``mode``: ``use``, ``explicit`` or ``diagnostic``."""
        symbols, values, checks = self._close(unrolled=mode != "explicit")
        hooks = list(self.hooks.values())
        if mode != "diagnostic" and hooks:
            zeros = [ca.SX(0)] * len(hooks)
            if values:   # the implicit values and checks hold hooks too: close them first
                values = ca.substitute(values, hooks, zeros)
                checks = [replace(c, derivative=ca.substitute([c.derivative], hooks, zeros)[0],
                                  last_step=ca.substitute([c.last_step], hooks, zeros)[0])
                          for c in checks]
            symbols, values = symbols + hooks, values + zeros
        groups: list[list[ca.SX]] = [
            [q.sx for q in self.constraints], [q.sx for q in self.expressions],
            [q.sx for q in self.signals.values()],
            [c.estimate for c in self.comparisons], [c.reference for c in self.comparisons]]
        flat = [sx for g in groups for sx in g]
        closed = ca.substitute(flat, symbols, values) if symbols and flat else flat
        it = iter(closed)
        cons = [replace(q, sx=next(it)) for q in self.constraints]
        exprs = [replace(q, sx=next(it)) for q in self.expressions]
        order = [n for n in self._signal_names() if n in self.signals]
        sig_closed = {q.name: replace(q, sx=next(it)) for q in self.signals.values()}
        comps_est = [next(it) for _ in self.comparisons]
        comps = [replace(c, estimate=e, reference=next(it))
                 for c, e in zip(self.comparisons, comps_est, strict=True)]
        if mode == "use":
            self._check_dependence(cons)
        system, study = self.spec.system, self.spec.study
        columns = tuple(c for c in system.columns if c in self.column_symbols)
        u = ca.vertcat(*(self.column_symbols[c] for c in columns)) if columns else ca.SX(0, 1)
        theta = ca.vertcat(*(self.symbols[p.name] for p in self.parameters))
        instances = {k: Instance(k, i.model, {b: e.text for b, e in i.bindings.items()}, i.doc)
                     for k, i in system.instances.items()}
        return Problem(
            self.spec.name, self.spec.doc, self.spec.path, tuple(self.parameters), theta,
            columns, u, tuple(cons), tuple(exprs), tuple(sig_closed[n] for n in order),
            tuple(comps), Study(dict(study.datasets), self._stages(), study.weighting),
            self.spec.options, instances, dict(system.columns), tuple(checks),
            dict(self.hooks) if mode == "diagnostic" else {}, self.spec, self, mode)

    def _check_dependence(self, constraints: list[Quantity]) -> None:
        for q in constraints:
            if not any(ca.depends_on(q.sx, self.symbols[p.name]) for p in self.parameters):
                raise SpecError(self.spec.system.constraints[q.name].where,
                                f"constraint '{q.name}' does not depend on any parameter")

    def _stages(self) -> tuple[Stage, ...]:
        names = [p.name for p in self.parameters]
        fixed = {p.name for p in self.parameters if p.fixed}
        study = self.spec.study
        if not study.stages:
            free = tuple(n for n in names if n not in fixed)
            return (Stage("calibration", tuple(self.spec.system.constraints), free),)
        stages = []
        for st in study.stages:
            chosen: list[str] = []
            for pattern, where in st.free:
                matched = [n for n in names if fnmatch.fnmatchcase(n, pattern)]
                if not matched:
                    raise SpecError(where, f"'{pattern}' matches no parameter"
                                           f"{did_you_mean(pattern, names)}")
                chosen += [n for n in matched if n not in chosen]
            free = tuple(n for n in names if n in chosen and n not in fixed)
            if not free:
                raise SpecError(st.where, f"stage '{st.name}' frees only fixed parameters")
            stages.append(Stage(st.name, st.constraints, free, st.method, st.doc))
        return tuple(stages)


def _resolve_starts(symbols: list[ca.SX], starts: list[ca.SX]) -> list[ca.SX]:
    """Every placeholder at its start, starts that name other placeholders included."""
    values = list(starts)
    for _ in range(len(symbols) + 1):
        if not any(ca.depends_on(v, s) for v in values for s in symbols):
            return values
        values = ca.substitute(values, symbols, values)
    raise SpecError(Where("implicit"), "the starts of implicit definitions refer to each "
                                       "other in a cycle")


def build_problem(spec: ProblemSpec) -> Problem:
    """Turn a validated spec into a symbolic :class:`Problem` (one build; the explicit twin
    and the diagnostic view are derived from it on demand)."""
    return _Build(spec).problem("use")


def load_problem(path: str | Path) -> Problem:
    """Load a problem file, its models, and build the symbolic problem.

    Parameters
    ----------
    path
        The problem's YAML file.

    Returns
    -------
    Problem

    Raises
    ------
    SpecError
        For any problem in the files, naming file, line, key path and symbol.
    """
    return build_problem(load_problem_spec(path))
