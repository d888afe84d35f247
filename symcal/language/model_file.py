"""Sensor model files (``models/*.yaml``) → validated, frozen :class:`ModelSpec`."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import SpecError, Where
from symcal.language import expr
from symcal.language.candidates import (
    CandidatesSpec,
    check_model_variables,
    model_candidate_names,
    parse_candidates,
)
from symcal.language.common import (
    ConstantSpec,
    ExprSpec,
    ParameterSpec,
    check_unique,
    display_unit,
    parse_constant,
    parse_expr,
    parse_parameter,
    section,
)
from symcal.language.fields import (
    check_keys,
    child_where,
    expect_int,
    expect_name,
    expect_str,
    expect_symbol,
)
from symcal.language.noise import NoiseSpec, in_unit_of, parse_noise
from symcal.language.overlay import resolve_base
from symcal.language.yamlio import load_yaml

MODEL_KEYS = ["doc", "extends", "constants", "inputs", "parameters", "expressions", "outputs",
              "implicit", "candidates"]
MAX_STEPS = 50
BASE = "base."  # prefix under which an extending model sees the definitions it overrides


@dataclass(frozen=True)
class InputSpec:
    """A per-observation input of a model; ``period`` (an expression) marks it periodic;
    ``noise`` is the declared standard deviation of its reading (None: not declared)."""

    name: str
    unit: str
    doc: str
    period: ExprSpec | None
    where: Where
    noise: NoiseSpec | None = None


@dataclass(frozen=True)
class OutputSpec:
    """A named output: an expression of the model's symbols."""

    name: str
    expr: ExprSpec
    unit: str
    doc: str
    where: Where


@dataclass(frozen=True)
class ImplicitSpec:
    """An output or expression defined in terms of itself, solved by fixed-point steps.

    ``x = F(x)`` is unrolled ``steps`` times from ``x₀ = start``: with ``start`` the raw
    value, zero steps is the explicit model and each step applies the correction at the
    corrected value again.
    """

    name: str
    start: ExprSpec
    steps: int
    where: Where


@dataclass(frozen=True)
class ModelSpec:
    """A sensor model as declared in YAML: symbols, expressions and outputs."""

    name: str
    doc: str
    path: Path
    constants: dict[str, ConstantSpec]
    inputs: dict[str, InputSpec]
    parameters: dict[str, ParameterSpec]
    expressions: dict[str, ExprSpec]
    outputs: dict[str, OutputSpec]
    where: Where
    extends: ModelSpec | None = None
    implicit: dict[str, ImplicitSpec] = field(default_factory=dict)
    #: The search space of candidate effects the model declares (``candidates:``, its own
    #: or inherited); None: not declared.
    candidates: CandidatesSpec | None = None
    #: The units expressions declare (``NAME: {expr: ..., unit: ...}``), by name.
    expression_units: dict[str, str] = field(default_factory=dict)

    def error_expression(self, output: str) -> str | None:
        """The expression E when ``output`` is ``input + E`` (or ``E + input``): the
        sensor's error, where a missing term belongs."""
        spec = self.outputs.get(output)
        if spec is None:
            return None
        node = spec.expr.node
        if isinstance(node, expr.Binary) and node.op == "+":
            for a, b in ((node.left, node.right), (node.right, node.left)):
                if isinstance(a, expr.Name) and a.name in self.inputs and \
                        isinstance(b, expr.Name) and b.name in self.expressions:
                    return b.name
        return None

    def evaluation_point(self, name: str) -> str | None:
        """Where the model evaluates its error for input ``name``: an expression solved
        from it (``implicit: {u: {start: p}}``) or defined as the input itself (``u: p``,
        the explicit model); None when there is no such expression."""
        for key, spec in self.implicit.items():
            if isinstance(spec.start.node, expr.Name) and spec.start.node.name == name:
                return key
        for key, value in self.expressions.items():
            if isinstance(value.node, expr.Name) and value.node.name == name:
                return key
        return None


def _parse_input(name: str, value: Any, where: Where) -> InputSpec:
    expect_symbol(name, where, "an input's name")
    entry = check_keys(value, where, optional=["unit", "doc", "period", "noise"])
    unit = display_unit(entry.get("unit"), child_where(entry, where, "unit"))
    doc = expect_str(entry["doc"], child_where(entry, where, "doc")) if "doc" in entry else ""
    at = child_where(entry, where, "period")
    period = (parse_expr(in_unit_of(entry["period"], unit, at, "the period"), at)
              if "period" in entry else None)
    noise = (parse_noise(entry["noise"], child_where(entry, where, "noise"), unit)
             if "noise" in entry else None)
    return InputSpec(name, unit, doc, period, where, noise)


def _parse_output(name: str, value: Any, where: Where) -> OutputSpec:
    expect_symbol(name, where, "an output's name")
    if not isinstance(value, dict):
        return OutputSpec(name, parse_expr(value, where), "", "", where)
    entry = check_keys(value, where, required=["expr"], optional=["unit", "doc"])
    doc = expect_str(entry["doc"], child_where(entry, where, "doc")) if "doc" in entry else ""
    return OutputSpec(
        name, parse_expr(entry["expr"], child_where(entry, where, "expr")),
        display_unit(entry.get("unit"), child_where(entry, where, "unit")), doc, where,
    )


DEFAULT_STEPS = 4


def parse_implicit(name: str, value: Any, where: Where) -> ImplicitSpec:
    expect_name(name, where, "an implicit definition's name")
    entry = check_keys(value, where, required=["start"], optional=["steps", "doc"])
    steps = DEFAULT_STEPS
    if "steps" in entry:
        at = child_where(entry, where, "steps")
        steps = expect_int(entry["steps"], at, 1)
        if steps > MAX_STEPS:
            raise SpecError(at, f"at most {MAX_STEPS} fixed-point steps, found {steps}")
    return ImplicitSpec(name, parse_expr(entry["start"], child_where(entry, where, "start")),
                        steps, where)


def expression_nodes(model: ModelSpec) -> list[expr.Node]:
    """The AST of every expression a model declares or inherits (outputs, expressions,
    periods of inputs, starts of implicit definitions)."""
    specs = [*model.expressions.values(), *(o.expr for o in model.outputs.values()),
             *(i.period for i in model.inputs.values() if i.period is not None),
             *(d.start for d in model.implicit.values())]
    return [spec.node for spec in specs]


def _check_implicit(model: ModelSpec) -> None:
    for name, spec in model.implicit.items():
        if name not in model.outputs and name not in model.expressions:
            defined = [*model.outputs, *model.expressions]
            raise SpecError(spec.where, f"'{name}' is not an output or expression of model "
                                        f"'{model.name}'{did_you_mean(name, defined)}")


def _parse_expression(name: str, value: Any, where: Where) -> tuple[ExprSpec, str]:
    """An expression, written as text (or a number), or as ``{expr, unit, doc}`` as a
    problem's expressions and a model's outputs are: its unit is then checked against
    the expression's."""
    if not isinstance(value, dict):
        return parse_expr(value, where), ""
    entry = check_keys(value, where, required=["expr"], optional=["unit", "doc"])
    if "doc" in entry:
        expect_str(entry["doc"], child_where(entry, where, "doc"))
    return (parse_expr(entry["expr"], child_where(entry, where, "expr")),
            display_unit(entry.get("unit"), child_where(entry, where, "unit")))


def _merge_units(parent: dict[str, str], child: dict[str, str],
                 redefined: set[str]) -> dict[str, str]:
    """The declared units of the merged expressions, keyed as :func:`_merge_definitions`
    keys them: a parent's moves to ``base.NAME`` where the child redefines ``NAME``, whose
    own unit is the child's, or else the parent's."""
    merged = {(BASE + k if k.startswith(BASE) else k): u for k, u in parent.items()}
    for name in redefined:
        if name in merged:
            merged[BASE + name] = merged.pop(name)
            merged[name] = merged[BASE + name]
    merged.update(child)
    return merged


def _shift_base(spec: ExprSpec) -> ExprSpec:
    """Push a parent's own ``base.X`` references one level down (``base.base.X``)."""
    node = expr.rename(spec.node, lambda n: BASE + n if n.startswith(BASE) else n)
    return replace(spec, node=node)


def _merge_definitions(
    parent: dict[str, ExprSpec], child: dict[str, ExprSpec]
) -> dict[str, ExprSpec]:
    """Parent definitions overridden by the child move to ``base.NAME``."""
    merged: dict[str, ExprSpec] = {}
    for name, spec in parent.items():
        key = BASE + name if name.startswith(BASE) else name
        merged[key] = _shift_base(spec)
    for name in child:
        if name in merged:
            merged[BASE + name] = merged.pop(name)
    merged.update(child)
    return merged


def _extend(parent: ModelSpec, child: ModelSpec) -> ModelSpec:
    """The model ``child`` declares on top of ``parent`` (see :func:`load_model`)."""
    for name, inp in child.inputs.items():
        if name in parent.inputs:
            raise SpecError(inp.where, f"input '{name}' is already declared by the extended "
                                       f"model '{parent.name}'")
    parent_exprs = dict(parent.expressions)
    parent_exprs.update({k: o.expr for k, o in parent.outputs.items()})
    child_exprs = dict(child.expressions)
    child_exprs.update({k: o.expr for k, o in child.outputs.items()})
    merged = _merge_definitions(parent_exprs, child_exprs)
    outputs = {**parent.outputs, **{k: _inherit(parent.outputs.get(k), o)
                                    for k, o in child.outputs.items()}}
    outputs = {k: replace(o, expr=merged[k]) for k, o in outputs.items()}
    expressions = {k: v for k, v in merged.items() if k not in outputs}
    model = ModelSpec(
        child.name, child.doc or parent.doc, child.path,
        {**parent.constants, **child.constants}, {**parent.inputs, **child.inputs},
        {**parent.parameters, **child.parameters}, expressions, outputs, child.where, parent,
        {**parent.implicit, **child.implicit},
        child.candidates if child.candidates is not None else parent.candidates,
        _merge_units(parent.expression_units, child.expression_units,
                     set(child.expressions)),
    )
    _check_sections(model)
    _check_implicit(model)
    _check_candidates(model)
    return model


def _inherit(parent: OutputSpec | None, child: OutputSpec) -> OutputSpec:
    """An output the child redefines: a unit or doc it does not write is the parent's
    (``p_hat: base.p_hat + c*u`` keeps the output's declared unit)."""
    if parent is None:
        return child
    return replace(child, unit=child.unit or parent.unit, doc=child.doc or parent.doc)


def _check_candidates(model: ModelSpec) -> None:
    """The variables of the model's ``candidates:`` are its own names."""
    if model.candidates is not None:
        known = model_candidate_names(model.inputs, model.outputs, model.expressions)
        check_model_variables(model.candidates, known, model.name)


def _check_sections(model: ModelSpec) -> None:
    """A name may be defined in one section only."""
    check_unique({
        sect: [(k, v.where) for k, v in group.items() if not k.startswith(BASE)]
        for sect, group in (("constants", model.constants), ("inputs", model.inputs),
                            ("parameters", model.parameters),
                            ("expressions", model.expressions), ("outputs", model.outputs))
    })


def load_model(path: str | Path, _chain: tuple[Path, ...] = ()) -> ModelSpec:
    """Load and validate one sensor model file.

    A model may ``extends: other.yaml`` (relative to it): it inherits the other model's
    constants, inputs, parameters, expressions and outputs, adds its own, and may
    redefine constants, parameters, expressions and outputs.  A redefined expression can
    refer to the definition it replaces as ``base.NAME``, e.g. ``e: base.e + k9*sin(f*q)``;
    the inherited definitions that use ``NAME`` (such as ``p_hat: p + e``) see the new one.

    A definition may refer to itself, directly or through others, when it is listed under
    ``implicit: {NAME: {start: EXPR, steps: N}}``: it is then solved by N fixed-point
    steps from ``start`` (default N = 4).

    Parameters
    ----------
    path
        The model's YAML file.

    Returns
    -------
    ModelSpec
        The validated model; expressions are parsed, symbols not yet resolved.

    Raises
    ------
    SpecError
        Naming file, line and key path for any problem in the file.
    """
    path = Path(path)
    doc, where = load_yaml(path, "model")
    check_keys(doc, where, required=["model"], optional=MODEL_KEYS)
    name = expect_name(doc["model"], child_where(doc, where, "model"), "the model's name")
    text = expect_str(doc["doc"], child_where(doc, where, "doc")) if "doc" in doc else ""

    def entries(key: str, parse: Any) -> dict[str, Any]:
        mapping, at = section(doc, where, key)
        return {k: parse(k, v, child_where(mapping, at, k)) for k, v in mapping.items()}

    constants = entries("constants", parse_constant)
    inputs = entries("inputs", _parse_input)
    parameters = entries("parameters", parse_parameter)
    declared = entries("expressions", _parse_expression)
    expressions = {k: spec for k, (spec, _) in declared.items()}
    units = {k: unit for k, (_, unit) in declared.items() if unit}
    for key in expressions:
        expect_symbol(key, expressions[key].where, "an expression's name")
    outputs = entries("outputs", _parse_output)
    for key in expressions:
        if key.startswith(BASE):
            raise SpecError(expressions[key].where, f"'{key}' cannot be defined: 'base.' "
                                                    "names refer to an extended model")
    candidates = (parse_candidates(doc["candidates"], child_where(doc, where, "candidates"))
                  if "candidates" in doc else None)
    model = ModelSpec(name, text, path.resolve(), constants, inputs, parameters, expressions,
                      outputs, where, None, entries("implicit", parse_implicit), candidates,
                      units)
    _check_sections(model)
    if "extends" not in doc:
        _check_implicit(model)
        _check_candidates(model)
        return model
    at = child_where(doc, where, "extends")
    chain = (*_chain, path.resolve())
    parent_path = resolve_base(doc["extends"], at, path, "model", chain)
    return _extend(load_model(parent_path, chain), model)
