"""The problem compiler: a validated spec into a symbolic :class:`Problem`, once.

One build per problem.  Names are resolved lazily and memoised
(:mod:`symcal.problem.names`): a constraint pulls in the problem expressions and instance
outputs it refers to, an instance pulls in its input bindings, and a cycle among
definitions is reported with its path.  Models see only their own symbols; problems see
constants, parameters, expressions, data columns and dotted instance signals (``s1.p_hat``).

The build leaves two kinds of symbols open, and the problem's views are derived from it by
substitution, never by building again; the compiler returns them all as values:

- every implicit definition (``x = F(x)``) is a placeholder symbol with its start and its
  map; the problem in use unrolls the maps (fixed-point steps), the explicit twin
  (:attr:`Problem.explicit`) takes every start (zero steps: the explicit model)
  (:mod:`symcal.problem.implicit`);
- every instance output carries a *hook*, a symbol added to its error expression when
  the output is ``reading + error`` (inside an implicit definition when there is one) and
  to the output otherwise; the problem in use sets the hooks to zero, the diagnostic view
  (:attr:`Problem.diagnostic`) keeps them, so that the derivative of any residual with
  respect to a term added where it belongs is exact;
- every reading with a declared noise (a column, or an input bound to an expression:
  :mod:`symcal.problem.readings`) carries a *noise symbol* added to it; the problem in
  use sets them to zero, the noisy view (:attr:`Problem.noisy`) keeps them, so that the
  derivative of any residual with respect to a reading's error is exact (the propagation
  of the declared noise, :mod:`symcal.analysis.floors`).
"""

from __future__ import annotations

import fnmatch
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path

import casadi as ca

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import SpecError, Where
from symcal.base.files import input_refusal
from symcal.base.units import Unit, size, size_of, text_of
from symcal.language.common import (
    ConstantSpec,
    ParameterSpec,
    apply_parameter_overrides,
    parse_expr,
)
from symcal.language.dimensions import describe, same_dimension
from symcal.language.model_file import ModelSpec
from symcal.language.problem_file import (
    ComparisonSpec,
    InstanceSpec,
    ProblemSpec,
    load_problem_spec,
)
from symcal.language.yamlio import display_path
from symcal.problem.implicit import close_at_starts, close_unrolled
from symcal.problem.names import (
    Implicits,
    OpenDefinition,
    Scope,
    Symbols,
    check_declared,
    declared,
    enter,
    instance_scope,
    scaled,
    unit_text,
)
from symcal.problem.readings import plan_noise
from symcal.problem.space import (
    check_spaces,
    expressions_needed,
    instance_space,
    problem_candidates,
)
from symcal.problem.symbolic import (
    Comparison,
    ConstantInfo,
    ImplicitOutput,
    Instance,
    Parameter,
    Problem,
    Quantity,
    Reading,
    Stage,
    Study,
    Views,
)

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


class _Compiler:
    """The one build of a problem: every expression with its implicit placeholders and
    hooks open (:meth:`views` closes them).  It is also the problem scope's
    :class:`~symcal.problem.names.Outside`: columns, dotted signals and parameters."""

    def __init__(self, spec: ProblemSpec) -> None:
        self.spec = spec
        system = spec.system
        self.model_level: list[OpenDefinition] = []
        self.stack: list[str] = []
        self.signals: dict[str, Quantity] = {}
        self.hooks: dict[str, ca.SX] = {}
        self.built: set[str] = set()
        self.parameters: list[Parameter] = []
        self.symbols: dict[str, ca.SX] = {}
        self.scaled: dict[str, ca.SX] = {}         # parameter symbols in internal units
        self.param_units: dict[str, Unit | None] = {}
        self.column_symbols: dict[str, ca.SX] = {}
        self.noise_plan = plan_noise(system)
        self.noise_symbols: dict[str, ca.SX] = {}    # reading -> its noise symbol
        self.constant_info: list[ConstantInfo] = []  # each with its symbol δ
        self.extra_signals = expressions_needed(system)
        for inst in system.instances.values():
            for pname, pspec in inst.model.parameters.items():
                if pname in inst.overrides:
                    entry, at = inst.overrides[pname]
                    pspec = apply_parameter_overrides(pspec, entry, at)
                self._add_parameter(f"{inst.name}.{pname}", pspec)
        for pspec in system.parameters.values():
            self._add_parameter(pspec.name, pspec)
        values = {k: self._constant(k, c, None) for k, c in system.constants.items()}
        # every model constant an instance does not bind, per instance: its value + δ
        self.instance_constants = {
            i.name: {k: self._constant(f"{i.name}.{k}", c, i) for k, c in
                     i.model.constants.items() if k not in i.constants}
            for i in system.instances.values()}
        values.update({p.name: self.scaled[p.name] for p in system.parameters.values()})
        values["pi"] = ca.SX(ca.pi)
        units = {k: declared(c.unit) for k, c in system.constants.items()}
        units.update({p.name: self.param_units[p.name] for p in system.parameters.values()})
        units["pi"] = declared("1")
        written = {k: declared(q.unit) for k, q in system.expressions.items()}
        # problem-level implicit names are placeholders from the start, so that instances
        # bound to them can be built before their maps (in their declared unit, if any)
        self.problem_symbols = {n: ca.SX.sym(n) for n in system.implicit}
        values.update(self.problem_symbols)
        units.update({n: written[n] for n in system.implicit})
        defs = {k: q.expr for k, q in system.expressions.items()}
        self.signal_units: dict[str, Unit | None] = {}
        self.scope = Scope("", Symbols(values, units, defs, written), self, self.stack,
                           Implicits({}, []))
        self._build_all()
        self.candidates = problem_candidates(
            system, [c.key for c in self.constant_info],
            [p.name for p in self.parameters if p.fixed])

    # ------------------------------------------------------------------ building

    def _add_parameter(self, name: str, p: ParameterSpec) -> None:
        scale = p.scale if p.scale is not None else (abs(p.value) or 1.0)
        self.parameters.append(Parameter(name, p.value, p.unit, p.lower, p.upper, p.fixed,
                                         scale, p.doc, p.where))
        self.symbols[name] = ca.SX.sym(name)
        self.scaled[name] = scaled(self.symbols[name], p.unit)
        self.param_units[name] = declared(p.unit)

    def _constant(self, key: str, c: ConstantSpec, inst: InstanceSpec | None) -> ca.SX:
        """A constant's value in internal units plus its symbol δ (open in the diagnostic
        view, zero in every other: "this value is off"), recorded in ``constant_info``."""
        delta = ca.SX.sym(f"const:{key}")
        self.constant_info.append(ConstantInfo(
            key, c.name, inst.name if inst is not None else None,
            inst.model.path if inst is not None else None, c.value, c.unit, c.doc, c.where,
            delta))
        return ca.SX(c.value * size(c.unit)) + delta

    def _at_start(self, value: ca.SX) -> ca.SX:
        """``value`` with every constant's δ at zero and every parameter at its start."""
        symbols = [c.symbol for c in self.constant_info]
        values = [ca.SX(0)] * len(symbols)
        symbols += [self.symbols[p.name] for p in self.parameters]
        values += [ca.SX(p.value) for p in self.parameters]
        return ca.substitute([value], symbols, values)[0]

    def _bound_constants(self, inst: InstanceSpec) -> dict[str, ca.SX]:
        """The instance's model constants: each bound one (``constants: {rho: rho}``) as
        the problem expression it is bound to, checked (a constant expression of
        parameters and constants, in the constant's dimension); the others as declared."""
        out = dict(self.instance_constants[inst.name])
        model = inst.model
        allowed = {p.name for p in self.parameters} | {c.symbol.name()
                                                       for c in self.constant_info}
        for key, b in inst.constants.items():
            if key not in model.constants:
                raise SpecError(b.where, f"'{key}' is not a constant of model '{model.name}'"
                                         f"{did_you_mean(key, model.constants)}")
            enter(self.stack, f"{inst.name} (constants)", b.where)
            try:
                value = self.scope.build(b)
            finally:
                self.stack.pop()
            want, found = declared(model.constants[key].unit), self.scope.unit(b)
            if not same_dimension(want, found):
                raise SpecError(b.where, f"constant '{key}' of model '{model.name}' is in "
                                         f"{describe(want)}, but '{b.text}' bound to it is in "
                                         f"{describe(found)}")
            varying = [v.name() for v in ca.symvar(value) if v.name() not in allowed
                       and not v.name().startswith(("noise:", "hook:"))]
            if varying:
                raise SpecError(b.where, f"constant '{key}' of model '{model.name}' is bound "
                                         f"to '{b.text}', which varies with "
                                         f"{', '.join(sorted(set(varying)))}: a constant is "
                                         "bound to an expression of parameters and constants")
            out[key] = value
        return out

    # ------------------------------------------------------------------ Outside

    def hint(self, name: str) -> str:
        """Where an unknown symbol is a column of a data file the problem names: say so."""
        for ds in self.spec.study.datasets.values():
            if ds.path is not None and name in data_columns(ds.path):
                return (f"; {display_path(ds.path)} (dataset '{ds.name}') has a column "
                        f"'{name}': declare it under 'columns:', e.g. "
                        f"columns: {{{name}: {{unit: mm}}}}")
        return ""

    def known(self) -> list[str]:
        """Columns, dotted signals and parameters (the problem scope adds its own)."""
        return [*self.spec.system.columns, *self._signal_names(), *self.symbols]

    def _signal_names(self) -> list[str]:
        names = []
        for i, inst in self.spec.system.instances.items():
            model = inst.model
            points = [model.evaluation_point(n) for n in model.inputs]
            names += [f"{i}.{n}" for n in (*model.outputs, *model.inputs,
                                           *(p for p in points if p and p not in model.outputs),
                                           *self.extra_signals.get(i, ()))]
        return names

    def resolve(self, name: str, where: Where) -> ca.SX | None:
        """A dotted signal or parameter (the instance is built on first use), a column."""
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
            value = scaled(self.column_symbols[name], system.columns[name].unit)
            noise = self.noise_plan.columns.get(name)
            if noise is not None and noise.sigma > 0:           # 0: declared exact
                value = value + self._noise_symbol(name)
            return value
        return None

    def _noise_symbol(self, reading: str) -> ca.SX:
        """The noise symbol of a declared reading (internal units), made on first use."""
        if reading not in self.noise_symbols:
            self.noise_symbols[reading] = ca.SX.sym(f"noise:{reading}")
        return self.noise_symbols[reading]

    def unit(self, name: str) -> Unit | None:
        """The unit of a name :meth:`_fallback` resolved: a parameter, a signal, a column."""
        if name in self.param_units:
            return self.param_units[name]
        if name in self.signal_units:
            return self.signal_units[name]
        column = self.spec.system.columns.get(name)
        return declared(column.unit) if column is not None else None

    def _instance(self, inst: InstanceSpec, where: Where) -> None:
        if inst.name in self.built:
            return
        enter(self.stack, f"{inst.name} (inputs)", where)
        try:
            inputs = {k: self.scope.build(b) for k, b in inst.bindings.items()}
        finally:
            self.stack.pop()
        model = inst.model
        input_units: dict[str, Unit | None] = {}
        for k, b in inst.bindings.items():
            found = self.scope.unit(b)
            want = declared(model.inputs[k].unit)
            if not same_dimension(want, found):
                raise SpecError(b.where, f"input '{k}' of model '{model.name}' is in "
                                         f"{describe(want)}, but '{b.text}' bound to it is "
                                         f"in {describe(found)}")
            input_units[k] = want if want is not None else found
            noise = self.noise_plan.inputs.get(f"{inst.name}.{k}")   # bound to an
            if noise is not None and noise.sigma > 0:                  # expression
                inputs[k] = inputs[k] + self._noise_symbol(f"{inst.name}.{k}")
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
        scope = instance_scope(inst, inputs, params, input_units, self.stack,
                               self.model_level, on_error, self._bound_constants(inst))
        for name, out in model.outputs.items():
            full = f"{inst.name}.{name}"
            sx = scope.lookup(name, out.where)
            if full in on_output:
                sx = sx + self.hooks[full]
            self.signal_units[full] = scope.units.get(name)
            self.signals[full] = Quantity(full, sx, unit_text(out.unit, scope.units.get(name)),
                                          doc=out.doc)
        for name in model.implicit:
            scope.lookup(name, model.implicit[name].where)
        for name, inp in model.inputs.items():
            period = None
            unit = input_units[name]
            if inp.period is not None:
                value = self._at_start(scope.build(inp.period))
                if not value.is_constant():
                    raise SpecError(inp.period.where, "a period must be a constant expression")
                found = scope.unit(inp.period)
                if found is None or not text_of(found):
                    # a plain number is in the input's own unit, as a noise is (360 for an
                    # input in deg is a turn, not 360 rad)
                    value = value * (1.0 if unit is None else size_of(unit))
                elif not same_dimension(unit, found):
                    raise SpecError(inp.period.where, f"the period of input '{name}' is in "
                                                      f"{describe(found)}, but the input is in "
                                                      f"{describe(unit)}")
                period = float(ca.evalf(value))
            self.signal_units[f"{inst.name}.{name}"] = unit
            self.signals[f"{inst.name}.{name}"] = Quantity(
                f"{inst.name}.{name}", inputs[name], unit_text(inp.unit, unit), doc=inp.doc,
                period=period)
            point = model.evaluation_point(name)
            if point is not None and point not in model.outputs:
                sx = scope.lookup(point, inp.where)
                self.signal_units[f"{inst.name}.{point}"] = scope.units.get(point)
                self.signals[f"{inst.name}.{point}"] = Quantity(
                    f"{inst.name}.{point}", sx, unit_text(inp.unit, scope.units.get(point)),
                    doc=f"where the model evaluates its error in {name}", period=period)
        for name in self.extra_signals.get(inst.name, ()):   # named by a search space
            sx = scope.lookup(name, model.expressions[name].where)
            self.signal_units[f"{inst.name}.{name}"] = scope.units.get(name)
            self.signals[f"{inst.name}.{name}"] = Quantity(
                f"{inst.name}.{name}", sx, unit_text("", scope.units.get(name)),
                doc=f"expression '{name}' of model '{model.name}'")
        self.built.add(inst.name)

    def _build_all(self) -> None:
        system = self.spec.system
        for inst in system.instances.values():
            self._instance(inst, inst.where)
        self.expressions = []
        for k, q in system.expressions.items():
            sx = self.scope.lookup(k, q.where)
            self.expressions.append(Quantity(k, sx, unit_text(q.unit, self.scope.units.get(k)),
                                             doc=q.doc))
        self.constraints = []
        for k, q in system.constraints.items():
            sx = self.scope.build(q.expr)
            found = self.scope.unit(q.expr)
            check_declared(q.where, f"constraint '{k}'", declared(q.unit), found)
            unit = unit_text(q.unit, found)
            # a written sigma is in the constraint's unit; g/sigma is formed in internal units
            sigma = q.sigma * size(unit) if q.sigma_given else q.sigma
            self.constraints.append(Quantity(k, sx, unit, sigma, q.doc, loss=q.loss))
        self.comparisons = [self._comparison(k, c) for k, c in system.comparisons.items()]
        self.problem_level = self._problem_implicit()
        references = {v.name() for c in self.comparisons for v in ca.symvar(c.reference)
                      if v.name() in system.columns}
        check_spaces(system, references, self._sx_of, self.hooks)

    def _sx_of(self, name: str) -> ca.SX | None:
        """The SX of a signal or a problem expression (hooks open), None for a column."""
        if name in self.signals:
            return self.signals[name].sx
        if name in self.spec.system.expressions:
            return self.scope.lookup(name, self.spec.system.expressions[name].where)
        return None

    def _comparison(self, name: str, c: ComparisonSpec) -> Comparison:
        estimate, reference = self.scope.build(c.estimate), self.scope.build(c.reference)
        a, b = self.scope.unit(c.estimate), self.scope.unit(c.reference)
        if not same_dimension(a, b):
            raise SpecError(c.where, f"comparison '{name}': the estimate '{c.estimate.text}' "
                                     f"is in {describe(a)}, but the reference "
                                     f"'{c.reference.text}' is in {describe(b)}")
        check_declared(c.where, f"comparison '{name}'", declared(c.unit),
                        a if a is not None else b)
        unit = unit_text(c.unit, a if a is not None else b)
        return Comparison(name, estimate, reference, unit, c.datasets, c.remove_mean, c.doc)

    def _problem_implicit(self) -> list[OpenDefinition]:
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
            out.append(OpenDefinition(n, self.problem_symbols[n], start, fmap, item.steps,
                                 item.where))
        return out

    # ------------------------------------------------------------------ closing

    def views(self) -> Problem:
        """The problem in use, holding its views as values (:class:`Views`): the
        diagnostic view (hooks open) and, with implicit definitions, the explicit twin
        (every one at its start); all three by substitution from this one build."""
        diagnostic = self._view(*close_unrolled(self.model_level, self.problem_level),
                                hooks_open=True, constants_open=True)
        # the other views close definitions free of the constants' symbols, so that their
        # implicit checks (derivatives taken before δ is zero) are those of a build
        # without them, bit for bit
        model, top = self._without_deltas(self.model_level), \
            self._without_deltas(self.problem_level)
        closed = close_unrolled(model, top)
        explicit = None
        if closed[0]:
            explicit = self._view(*close_at_starts(model, top), hooks_open=False)
        noisy = self._view(*closed, noise_open=True) if self.noise_symbols else None
        use = self._view(*closed, hooks_open=False)
        self._check_dependence(use.constraints)
        return replace(use, views=Views(diagnostic, explicit, noisy))

    def _without_deltas(self, defs: list[OpenDefinition]) -> list[OpenDefinition]:
        """Open definitions with every constant's symbol δ at zero."""
        deltas = [c.symbol for c in self.constant_info]
        if not deltas or not defs:
            return defs
        zeros = [ca.SX(0)] * len(deltas)
        out = []
        for d in defs:
            start, fmap = ca.substitute([d.start, d.fmap], deltas, zeros)
            out.append(replace(d, start=start, fmap=fmap))
        return out

    def _view(self, symbols: list[ca.SX], values: list[ca.SX], checks: list[ImplicitOutput],
              *, hooks_open: bool = False, noise_open: bool = False,
              constants_open: bool = False) -> Problem:
        """The problem with the placeholders at ``values``, and the hooks, the noise
        symbols and the constants' symbols open or zero."""
        hooks = list(self.hooks.values())
        closing = ([] if hooks_open else hooks) + \
            ([] if noise_open else list(self.noise_symbols.values())) + \
            ([] if constants_open else [c.symbol for c in self.constant_info])
        if closing:
            zeros = [ca.SX(0)] * len(closing)
            if values:   # the implicit values and checks hold them too: close them first
                values = ca.substitute(values, closing, zeros)
                checks = [replace(c,
                                  derivative=ca.substitute([c.derivative], closing, zeros)[0],
                                  last_step=ca.substitute([c.last_step], closing, zeros)[0])
                          for c in checks]
            symbols, values = symbols + closing, values + zeros
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
        system = self.spec.system
        columns = tuple(c for c in system.columns if c in self.column_symbols)
        u = ca.vertcat(*(self.column_symbols[c] for c in columns)) if columns else ca.SX(0, 1)
        theta = ca.vertcat(*(self.symbols[p.name] for p in self.parameters))
        instances = {k: Instance(k, i.model, {b: e.text for b, e in i.bindings.items()}, i.doc,
                                 {c: e.text for c, e in i.constants.items()},
                                 instance_space(i))
                     for k, i in system.instances.items()}
        return Problem(
            self.spec.name, self.spec.doc, self.spec.path, tuple(self.parameters), theta,
            columns, u, tuple(cons), tuple(exprs), tuple(sig_closed[n] for n in order),
            tuple(comps), self._study(cons), self.spec.options, instances, dict(system.columns),
            tuple(checks), dict(self.hooks) if hooks_open else {}, self.spec,
            readings=self._readings(), constants=self._constants(),
            candidates=self.candidates)

    def _constants(self) -> tuple[ConstantInfo, ...]:
        """Every constant, marked with whether the search may test it."""
        tested = set(self.candidates.constants)
        return tuple(replace(c, tested=c.key in tested) for c in self.constant_info)

    def _readings(self) -> tuple[Reading, ...]:
        """Every declared reading the problem reads, columns in ``u`` order, then inputs."""
        plan, out = self.noise_plan, []
        for name in self.spec.system.columns:
            if name in plan.columns and name in self.column_symbols:
                d = plan.columns[name]        # an exact reading's symbol is in no expression
                out.append(Reading(name, "column", d.sigma, d.unit, d.spec.text, d.origin,
                                   self.noise_symbols.get(name, ca.SX.sym(f"noise:{name}"))))
        for name, d in plan.inputs.items():
            if name.split(".", 1)[0] in self.built:
                out.append(Reading(name, "input", d.sigma, d.unit, d.spec.text, d.origin,
                                   self.noise_symbols.get(name, ca.SX.sym(f"noise:{name}"))))
        return tuple(out)

    def _study(self, constraints: list[Quantity]) -> Study:
        """The study; an unwritten weighting is ``propagated`` where every column the
        constraints read declares its noise, one at least is noisy and no constraint has
        a robust loss, else ``equal``."""
        study = self.spec.study
        weighting, declared = study.weighting, study.weighting != "auto"
        if not declared:
            system = self.spec.system
            read = {v.name() for q in constraints for v in ca.symvar(q.sx)}
            used = [c for c in system.columns if c in self.column_symbols and c in read]
            noisy = any(self.noise_plan.columns[c].sigma > 0 for c in used
                        if c in self.noise_plan.columns)
            complete = all(c in self.noise_plan.columns for c in used)
            robust = any(q.loss is not None for q in system.constraints.values())
            weighting = "propagated" if complete and noisy and not robust else "equal"
        return Study(dict(study.datasets), self._stages(), weighting, declared)

    def _check_dependence(self, constraints: tuple[Quantity, ...]) -> None:
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


def build_problem(spec: ProblemSpec) -> Problem:
    """Turn a validated spec into a symbolic :class:`Problem` (one build; the explicit twin
    and the diagnostic view are derived from it on demand)."""
    return _Compiler(spec).views()


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


def with_instance(problem: Problem, name: str, model: ModelSpec,
                  bindings: Mapping[str, str] | None = None) -> Problem:
    """The problem with instance ``name`` using ``model``, its bindings kept and
    ``bindings`` (input → expression text) added; ``problem`` is not modified.

    Parameters
    ----------
    problem
        A built problem.
    name
        One of its instances.
    model
        The model the instance uses instead.
    bindings
        Inputs to bind in addition, as expression text.

    Returns
    -------
    Problem
        Built anew from the problem's spec.
    """
    spec = problem.spec
    old = spec.system.instances[name]
    new_bindings = dict(old.bindings)
    for key, text in (bindings or {}).items():
        new_bindings[key] = parse_expr(str(text), old.where.child("inputs").child(key))
    new = replace(old, model=model, bindings=new_bindings)
    instances = {k: (new if k == name else v) for k, v in spec.system.instances.items()}
    return build_problem(replace(spec, system=replace(spec.system, instances=instances)))
