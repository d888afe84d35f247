"""Sensor model files (``models/*.yaml``) → validated, frozen :class:`ModelSpec`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from symcal.errors import Where
from symcal.spec.common import (
    ConstantSpec,
    ExprSpec,
    ParameterSpec,
    check_unique,
    parse_constant,
    parse_expr,
    parse_parameter,
    section,
)
from symcal.spec.fields import check_keys, child_where, expect_name, expect_str
from symcal.spec.yamlio import load_yaml

MODEL_KEYS = ["doc", "constants", "inputs", "parameters", "expressions", "outputs"]


@dataclass(frozen=True)
class InputSpec:
    """A per-observation input of a model; ``period`` (an expression) marks it periodic."""

    name: str
    unit: str
    doc: str
    period: ExprSpec | None
    where: Where


@dataclass(frozen=True)
class OutputSpec:
    """A named output: an expression of the model's symbols."""

    name: str
    expr: ExprSpec
    unit: str
    doc: str
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


def _parse_input(name: str, value: Any, where: Where) -> InputSpec:
    expect_name(name, where, "an input's name")
    entry = check_keys(value, where, optional=["unit", "doc", "period"])
    unit = str(entry.get("unit", ""))
    doc = expect_str(entry["doc"], child_where(entry, where, "doc")) if "doc" in entry else ""
    period = (
        parse_expr(entry["period"], child_where(entry, where, "period"))
        if "period" in entry else None
    )
    return InputSpec(name, unit, doc, period, where)


def _parse_output(name: str, value: Any, where: Where) -> OutputSpec:
    expect_name(name, where, "an output's name")
    if not isinstance(value, dict):
        return OutputSpec(name, parse_expr(value, where), "", "", where)
    entry = check_keys(value, where, required=["expr"], optional=["unit", "doc"])
    doc = expect_str(entry["doc"], child_where(entry, where, "doc")) if "doc" in entry else ""
    return OutputSpec(
        name, parse_expr(entry["expr"], child_where(entry, where, "expr")),
        str(entry.get("unit", "")), doc, where,
    )


def load_model(path: str | Path) -> ModelSpec:
    """Load and validate one sensor model file.

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
    expressions = entries("expressions", lambda k, v, at: parse_expr(v, at))
    for key in expressions:
        expect_name(key, expressions[key].where, "an expression's name")
    outputs = entries("outputs", _parse_output)
    check_unique({
        sect: [(k, v.where) for k, v in group.items()]
        for sect, group in (("constants", constants), ("inputs", inputs),
                            ("parameters", parameters), ("expressions", expressions),
                            ("outputs", outputs))
    })
    return ModelSpec(name, text, path.resolve(), constants, inputs, parameters, expressions,
                     outputs, where)
