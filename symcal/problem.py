"""Spec → symbolic :class:`Problem`: parameters θ, per-observation inputs u, named residuals.

Names are resolved lazily and memoised: a constraint pulls in the problem expressions and
instance outputs it refers to, an instance pulls in its input bindings, and a cycle among
definitions is reported with its path.  Models see only their own symbols; problems see
constants, parameters, expressions, data columns and dotted instance signals (``s1.p_hat``).
"""

from __future__ import annotations

import fnmatch
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import casadi as ca

from symcal import expr
from symcal.errors import SpecError, Where
from symcal.language.common import ExprSpec, ParameterSpec, apply_parameter_overrides
from symcal.language.model import ImplicitSpec
from symcal.language.problem import DatasetSpec, InstanceSpec, ProblemSpec, load_problem_spec
from symcal.suggest import did_you_mean


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


@dataclass(frozen=True, eq=False)
class Problem:
    """A calibration problem in symbolic form.

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
    datasets
        Where each named dataset comes from.
    stages
        The ordered steps of the calibration (one stage over everything by default).
    weighting
        ``"equal"``: the cost is Σ (g/σ)² as written; ``"estimated"``: each stage with
        several constraints is solved again, weighted by the inverse of their covariance
        estimated from the residuals (feasible generalised least squares).
    implicit
        Definitions solved by fixed-point steps, with their convergence checks.
    explicit
        When there are implicit definitions: the same problem with zero steps each (each
        one equal to its start: the explicit model), used to start the solver from a
        closed-form estimate.
    spec
        The validated spec the problem was built from.
    hooks
        Only in a diagnostic build (``build_problem(spec, hooks=True)``): for each instance
        output, a symbol added to it (zero in use), so that the derivative of any residual
        with respect to any sensor output is exact.  Evaluate with the hooks as extra rows
        of u set to zero.
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
    datasets: dict[str, DatasetSpec]
    stages: tuple[Stage, ...]
    weighting: str
    index: dict[str, int] = field(repr=False)
    implicit: tuple[ImplicitOutput, ...] = ()
    explicit: Problem | None = field(default=None, repr=False)
    spec: ProblemSpec | None = field(default=None, repr=False)
    hooks: dict[str, ca.SX] = field(default_factory=dict, repr=False)

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Names of all parameters, in the order of ``theta``."""
        return tuple(p.name for p in self.parameters)

    @property
    def free(self) -> tuple[bool, ...]:
        """Which parameters are free (not fixed)."""
        return tuple(not p.fixed for p in self.parameters)

    def constraint(self, name: str) -> Quantity:
        """The constraint called ``name``."""
        return next(c for c in self.constraints if c.name == name)

    def columns_of(self, sx: ca.SX) -> list[str]:
        """Data columns an expression depends on, in ``u`` order."""
        used = {v.name() for v in ca.symvar(sx)}
        return [c for c in self.columns if c in used]


def _enter(stack: list[str], key: str, where: Where) -> None:
    """Push ``key`` on the resolution stack, or report the cycle it would close."""
    if key in stack:
        cycle = stack[stack.index(key):] + [key]
        raise SpecError(where, f"cyclic definition: {' -> '.join(cycle)}")
    stack.append(key)


class _Scope:
    """Lazy, memoised resolution of names to SX with cycle detection.

    ``values`` are ready symbols; ``defs`` are expressions resolved on first use;
    ``fallback`` resolves other names (columns, dotted signals) or returns None.
    """

    def __init__(
        self,
        label: str,
        values: dict[str, ca.SX],
        defs: dict[str, ExprSpec],
        fallback: Callable[[str, Where, list[str]], ca.SX | None],
        known: Callable[[], list[str]],
        stack: list[str],
        implicit: dict[str, ImplicitSpec] | None = None,
        explicit: bool = False,
    ) -> None:
        self.label = label
        self.values = dict(values)
        self.defs = defs
        self.fallback = fallback
        self.known = known
        self.stack = stack
        self.implicit = implicit or {}
        self.explicit = explicit
        self.unknowns: dict[str, ca.SX] = {}
        self.solved: list[ImplicitOutput] = []

    def build(self, spec: ExprSpec) -> ca.SX:
        """Build one expression, reporting errors at its provenance."""
        return expr.to_casadi(spec.node, lambda node: self.lookup(node.name, spec.where))

    def lookup(self, name: str, where: Where) -> ca.SX:
        if name in self.values:
            return self.values[name]
        if name in self.unknowns:
            return self.unknowns[name]
        if name in self.implicit and name in self.defs:
            return self._solve_implicit(name, where)
        if name in self.defs:
            _enter(self.stack, f"{self.label}{name}", where)
            try:
                value = self.build(self.defs[name])
            finally:
                self.stack.pop()
            self.values[name] = value
            return value
        found = self.fallback(name, where, self.stack)
        if found is not None:
            return found
        pool = [k for k in self.known() if k != "pi"]  # pi is never what a typo meant
        raise SpecError(where, f"unknown symbol '{name}'{did_you_mean(name, pool)}")


    def _solve_implicit(self, name: str, where: Where) -> ca.SX:
        """Unroll ``x = F(x)`` from its start; memoised intermediates get the final x."""
        spec = self.implicit[name]
        key = f"{self.label}{name}"
        _enter(self.stack, key, where)  # a start that needs the name itself is a cycle
        try:
            start = self.build(spec.start)
        finally:
            self.stack.pop()
        unknown = ca.SX.sym(key)
        if ca.depends_on(start, unknown):  # pragma: no cover - a fresh symbol
            raise SpecError(spec.where, f"the start of '{name}' refers to '{name}' itself")
        known_before = set(self.values)
        self.unknowns[name] = unknown
        outer, self.stack = self.stack, [key]  # definitions in progress outside are rebuilt
        try:                                   # here in terms of the unknown
            fmap = self.build(self.defs[name])
        finally:
            self.stack = outer
            del self.unknowns[name]
        if not ca.depends_on(fmap, unknown):
            raise SpecError(spec.where, f"'{name}' is declared implicit but its definition "
                                        "does not refer to itself")
        steps = 0 if self.explicit else spec.steps
        iterates = [start]
        for _ in range(steps):
            iterates.append(ca.substitute(fmap, unknown, iterates[-1]))
        final = iterates[-1]
        last_step = final - iterates[-2] if steps else ca.SX(0)
        for other in set(self.values) - known_before:
            self.values[other] = ca.substitute(self.values[other], unknown, final)
        self.values[name] = final
        self.solved.append(ImplicitOutput(
            key, steps, ca.substitute(ca.jacobian(fmap, unknown), unknown, final), last_step))
        return final


def _model_scope(
    inst: InstanceSpec, inputs: dict[str, ca.SX], params: dict[str, ca.SX], stack: list[str],
    explicit: bool = False,
) -> _Scope:
    model = inst.model
    values: dict[str, ca.SX] = {k: ca.SX(c.value) for k, c in model.constants.items()}
    values.update(inputs)
    values.update(params)
    values["pi"] = ca.SX(ca.pi)
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

    return _Scope(f"{inst.name}.", values, defs, fallback,
                  lambda: [*values, *defs], stack, model.implicit, explicit)


class _Builder:
    """Builds a :class:`Problem` from a :class:`ProblemSpec`."""

    def __init__(self, spec: ProblemSpec, explicit: bool = False,
                 shared: _Builder | None = None, presets: dict[str, ca.SX] | None = None,
                 hooks: bool = False) -> None:
        self.spec = spec
        self.explicit = explicit
        self.with_hooks = hooks
        self.hooks: dict[str, ca.SX] = {}
        self.implicit: list[ImplicitOutput] = []
        self.stack: list[str] = []
        self.signals: dict[str, Quantity] = {}
        self.built: set[str] = set()
        self.nested = shared is not None
        if shared is not None:  # a sub-build sharing θ and the data columns
            self.parameters, self.symbols = shared.parameters, shared.symbols
            self.column_symbols = shared.column_symbols
        else:
            self.parameters, self.symbols, self.column_symbols = [], {}, {}
            for inst in spec.instances.values():
                for pname, pspec in inst.model.parameters.items():
                    if pname in inst.overrides:
                        entry, at = inst.overrides[pname]
                        pspec = apply_parameter_overrides(pspec, entry, at)
                    self._add_parameter(f"{inst.name}.{pname}", pspec)
            for pspec in spec.parameters.values():
                self._add_parameter(pspec.name, pspec)
        values = {k: ca.SX(c.value) for k, c in spec.constants.items()}
        values.update({p.name: self.symbols[p.name] for p in spec.parameters.values()})
        values["pi"] = ca.SX(ca.pi)
        values.update(presets or {})
        defs = {k: q.expr for k, q in spec.expressions.items()}
        self.scope = _Scope("", values, defs, self._fallback, self._known, self.stack)

    def _add_parameter(self, name: str, p: ParameterSpec) -> None:
        scale = p.scale if p.scale is not None else (abs(p.value) or 1.0)
        self.parameters.append(Parameter(name, p.value, p.unit, p.lower, p.upper, p.fixed,
                                         scale, p.doc, p.where))
        self.symbols[name] = ca.SX.sym(name)

    def _known(self) -> list[str]:
        return [*self.scope.values, *self.scope.defs, *self.spec.columns, *self._signal_names(),
                *self.symbols]

    def _signal_names(self) -> list[str]:
        return [f"{i}.{n}" for i, inst in self.spec.instances.items()
                for n in (*inst.model.outputs, *inst.model.inputs)]

    def _fallback(self, name: str, where: Where, stack: list[str]) -> ca.SX | None:
        if "." in name:
            if name in self.symbols:
                return self.symbols[name]
            inst_name = name.split(".", 1)[0]
            if inst_name in self.spec.instances:
                self._instance(self.spec.instances[inst_name], where)
                if name in self.signals:
                    return self.signals[name].sx
                inst = self.spec.instances[inst_name]
                known = [f"{inst_name}.{n}" for n in (*inst.model.outputs, *inst.model.inputs,
                                                      *inst.model.parameters)]
                raise SpecError(where, f"unknown symbol '{name}': instance '{inst_name}' has no "
                                       f"output, input or parameter '{name.split('.', 1)[1]}'"
                                       f"{did_you_mean(name, known)}")
            return None
        if name in self.spec.columns:
            if name not in self.column_symbols:
                self.column_symbols[name] = ca.SX.sym(name)
            return self.column_symbols[name]
        return None

    def _instance(self, inst: InstanceSpec, where: Where) -> None:
        if inst.name in self.built:
            return
        _enter(self.stack, f"{inst.name} (inputs)", where)
        try:
            inputs = {k: self.scope.build(b) for k, b in inst.bindings.items()}
        finally:
            self.stack.pop()
        params = {k: self.symbols[f"{inst.name}.{k}"] for k in inst.model.parameters}
        scope = _model_scope(inst, inputs, params, self.stack, self.explicit)
        model = inst.model
        for name, out in model.outputs.items():
            sx = scope.lookup(name, out.where)
            full = f"{inst.name}.{name}"
            if self.with_hooks:
                self.hooks[full] = ca.SX.sym(f"hook:{full}")
                sx = sx + self.hooks[full]
            self.signals[full] = Quantity(full, sx, out.unit, doc=out.doc)
        for name in model.implicit:
            scope.lookup(name, model.implicit[name].where)
        self.implicit += scope.solved
        for name, inp in model.inputs.items():
            period = None
            if inp.period is not None:
                value = scope.build(inp.period)
                if not value.is_constant():
                    raise SpecError(inp.period.where, "a period must be a constant expression")
                period = float(ca.evalf(value))
            self.signals[f"{inst.name}.{name}"] = Quantity(
                f"{inst.name}.{name}", inputs[name], inp.unit, doc=inp.doc, period=period)
        self.built.add(inst.name)

    def _solve_problem_implicit(self) -> None:
        """Solve the problem's implicit expressions jointly by unrolled fixed-point steps.

        The map is built by a sub-build in which the implicit names are placeholders, so
        that every instance that depends on them is evaluated afresh; the final iterates
        are then preset for the real build.
        """
        items = self.spec.implicit
        names = list(items)
        start = ca.vertcat(*(self.scope.build(items[n].start) for n in names))
        unknowns = {n: ca.SX.sym(n) for n in names}
        x = ca.vertcat(*unknowns.values())
        if ca.depends_on(start, x):  # pragma: no cover - fresh symbols
            raise SpecError(self.spec.where, "an implicit start refers to an implicit name")
        sub = _Builder(self.spec, self.explicit, shared=self, presets=unknowns)
        fmap = ca.vertcat(*(sub.scope.build(self.spec.expressions[n].expr) for n in names))
        for n in names if not self.explicit else ():
            if not ca.depends_on(fmap, unknowns[n]):
                raise SpecError(items[n].where, f"'{n}' is declared implicit but no implicit "
                                                "definition depends on it")
        steps = 0 if self.explicit else max(item.steps for item in items.values())
        iterates = [start]
        for _ in range(steps):
            iterates.append(ca.substitute(fmap, x, iterates[-1]))
        final = iterates[-1]
        for k, n in enumerate(names):
            self.scope.values[n] = final[k]
        norm = ca.mmax(ca.sum2(ca.fabs(ca.jacobian(fmap, x))))  # ‖∂F/∂x‖∞
        last = ca.mmax(ca.fabs(final - iterates[-2])) if steps else ca.SX(0)
        self.implicit.append(ImplicitOutput(", ".join(names), steps,
                                            ca.substitute(norm, x, final), last))

    def build(self) -> Problem:
        spec = self.spec
        if spec.implicit and not self.nested:
            self._solve_problem_implicit()
        for inst in spec.instances.values():
            self._instance(inst, inst.where)
        expressions = tuple(
            Quantity(k, self.scope.lookup(k, q.where), q.unit, doc=q.doc)
            for k, q in spec.expressions.items()
        )
        constraints = tuple(
            Quantity(k, self.scope.build(q.expr), q.unit, q.sigma, q.doc)
            for k, q in spec.constraints.items()
        )
        comparisons = tuple(
            Comparison(k, self.scope.build(c.estimate), self.scope.build(c.reference),
                       c.unit, c.datasets, c.remove_mean, c.doc)
            for k, c in spec.comparisons.items()
        )
        for q in constraints if not self.explicit else ():
            if not any(ca.depends_on(q.sx, self.symbols[p.name]) for p in self.parameters):
                raise SpecError(spec.constraints[q.name].where,
                                f"constraint '{q.name}' does not depend on any parameter")
        columns = tuple(c for c in spec.columns if c in self.column_symbols)
        u = ca.vertcat(*(self.column_symbols[c] for c in columns)) if columns else ca.SX(0, 1)
        theta = ca.vertcat(*(self.symbols[p.name] for p in self.parameters))
        signal_order = self._signal_names()
        signals = tuple(self.signals[n] for n in signal_order if n in self.signals)
        return Problem(
            spec.name, spec.doc, spec.path, tuple(self.parameters), theta, columns, u,
            constraints, expressions, signals, comparisons, dict(spec.datasets),
            self._stages(), spec.weighting, {p.name: i for i, p in enumerate(self.parameters)},
            tuple(self.implicit), None, spec, dict(self.hooks),
        )

    def _stages(self) -> tuple[Stage, ...]:
        names = [p.name for p in self.parameters]
        fixed = {p.name for p in self.parameters if p.fixed}
        if not self.spec.stages:
            free = tuple(n for n in names if n not in fixed)
            return (Stage("calibration", tuple(self.spec.constraints), free),)
        stages = []
        for st in self.spec.stages:
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


def build_problem(spec: ProblemSpec, hooks: bool = False) -> Problem:
    """Turn a validated spec into a symbolic :class:`Problem`.

    With implicit definitions, the problem carries an explicit twin (zero fixed-point
    steps each) in ``explicit``.  ``hooks=True`` makes a diagnostic build (see
    :attr:`Problem.hooks`), without a twin.
    """
    problem = _Builder(spec, hooks=hooks).build()
    if not problem.implicit or hooks:
        return problem
    return replace(problem, explicit=_Builder(spec, explicit=True).build())


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
