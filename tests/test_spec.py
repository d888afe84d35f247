"""Spec errors name file, line, key path and symbol, with did-you-mean (exact text)."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

import symcal
from symcal.base.errors import SpecError

MODEL = """\
model: seg
constants:
  rho: {value: 1.016, unit: mm}
inputs:
  p: {unit: mm, period: rho}
parameters:
  k0: {value: 0, unit: mm}
  k1: {value: 0, unit: mm, lower: -1, upper: 1}
expressions:
  f: 2*pi/rho
  e: k0 + k1*sin(f*p)
outputs:
  p_hat: {expr: p + e, unit: mm}
"""

PROBLEM = """\
problem: demo
constants:
  l_s: 9.7
instances:
  s1: {model: seg.yaml, inputs: {p: p1}}
  s2: {model: seg.yaml, inputs: {p: p2}}
expressions:
  theta: (s1.p_hat - s2.p_hat) / l_s
constraints:
  g: s1.p_hat - s2.p_hat
datasets:
  calibration: {path: data.csv}
columns: courier
"""


def _error(tmp_path: Path, monkeypatch, model: str = MODEL, problem: str = PROBLEM) -> str:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "seg.yaml").write_text(textwrap.dedent(model))
    (tmp_path / "prob.yaml").write_text(textwrap.dedent(problem))
    with pytest.raises(SpecError) as err:
        symcal.load_problem("prob.yaml")
    return str(err.value)


def test_valid_files_load(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "seg.yaml").write_text(MODEL)
    (tmp_path / "prob.yaml").write_text(PROBLEM)
    problem = symcal.load_problem("prob.yaml")
    assert problem.parameter_names == ("s1.k0", "s1.k1", "s2.k0", "s2.k1")
    assert problem.columns == ("p1", "p2")
    assert [s.name for s in problem.signals] == ["s1.p_hat", "s1.p", "s2.p_hat", "s2.p"]
    assert problem.signals[1].period == pytest.approx(1.016)
    assert problem.parameters[1].lower == -1


@pytest.mark.parametrize(("model", "problem", "message"), [
    (MODEL.replace("parameters:", "paramters:"), PROBLEM,
     "seg.yaml:6: paramters: unknown key 'paramters' (did you mean 'parameters'?); allowed "
     "keys: model, doc, extends, constants, inputs, parameters, expressions, outputs, "
     "implicit, candidates"),
    (MODEL.replace("k0: {value: 0", "k0: {valu: 0"), PROBLEM,
     "seg.yaml:7: parameters.k0.valu: unknown key 'valu' (did you mean 'value'?); allowed keys: "
     "value, unit, lower, upper, fixed, scale, doc"),
    (MODEL.replace("sin(f*p)", "sin(f*pp)"), PROBLEM,
     "seg.yaml:11: expressions.e: unknown symbol 'pp' (did you mean 'p'?)"),
    (MODEL.replace("sin(f*p)", "sine(f*p)"), PROBLEM,
     "seg.yaml:11: expressions.e: unknown function 'sine' (did you mean 'sin'?)"),
    (MODEL.replace("f: 2*pi/rho", "f: 2*pi/rho + e"), PROBLEM,
     "seg.yaml:10: expressions.f: cyclic definition: s1.e -> s1.f -> s1.e"),
    (MODEL.replace("lower: -1", "lower: 2"), PROBLEM,
     "seg.yaml:8: parameters.k1: lower bound 2 is above upper bound 1"),
    (MODEL.replace("k1: {value: 0", "k1: {value: 5"), PROBLEM,
     "seg.yaml:8: parameters.k1: initial value 5 is outside its bounds [-1, 1]"),
    (MODEL.replace("k0: {value: 0", "k0: {value: abc"), PROBLEM,
     "seg.yaml:7: parameters.k0.value: expected a number, found text ('abc')"),
    (MODEL.replace("  f: 2*pi/rho", "  rho: 2"), PROBLEM,
     "seg.yaml:10: expressions.rho: 'rho' is already defined in constants"),
    (MODEL.replace("model: seg", "model: seg\nmodel: again"), PROBLEM,
     "seg.yaml:2: invalid YAML: duplicate key 'model' (first at line 1)"),
    (MODEL.replace("p: {unit: mm, period: rho}", "p: {unit: mm, period: rho"), PROBLEM,
     "seg.yaml:6: invalid YAML: expected ',' or '}', but got ':'"),
    (MODEL.replace("model: seg", "doc: no name"), PROBLEM,
     "seg.yaml:1: missing required key 'model'"),
    (MODEL, PROBLEM.replace("s1.p_hat - s2.p_hat\n", "s1.p_ht - s2.p_hat\n"),
     "prob.yaml:10: constraints.g: unknown symbol 's1.p_ht': instance 's1' has no output, "
     "input or parameter 'p_ht' (did you mean 's1.p_hat'?)"),
    (MODEL, PROBLEM.replace("inputs: {p: p2}", "inputs: {p: p5}"),
     "prob.yaml:6: instances.s2.inputs.p: unknown symbol 'p5' (did you mean 'p1'?)"),
    (MODEL, PROBLEM.replace("inputs: {p: p2}", "inputs: {}"),
     "prob.yaml:6: instances.s2.inputs: input 'p' of model 'seg' is not bound "
     "(add 'p: <column or expression>')"),
    (MODEL, PROBLEM.replace("inputs: {p: p2}", "inputs: {p: p2, q: p3}"),
     "prob.yaml:6: instances.s2.inputs.q: 'q' is not an input of model 'seg'; it has: p"),
    (MODEL, PROBLEM.replace("s2: {model: seg.yaml", "s2: {model: segg.yaml"),
     "prob.yaml:6: instances.s2.model: model file not found: segg.yaml (did you mean 'seg.yaml'?)"),
    (MODEL, PROBLEM.replace("calibration:", "validation:"),
     "prob.yaml:11: datasets: a problem needs a dataset to fit (the data it is solved on): "
     "one named 'calibration', or one with 'role: fit'"),
    (MODEL, PROBLEM.replace("calibration:", "validation:").replace(
        "{path: data.csv}", "{path: data.csv, role: fitt}"),
     "prob.yaml:12: datasets.validation.role: unknown role 'fitt' (did you mean 'fit'?); "
     "choose from: fit, check"),
    (MODEL, PROBLEM.replace("{path: data.csv}", "{}"),
     "prob.yaml:12: datasets.calibration: a dataset needs exactly one of 'path' (a CSV or "
     "NPZ file) or 'simulate' (a scenario file)"),
    (MODEL, PROBLEM.replace("inputs: {p: p1}", "inputs: {p: s2.p_hat}").replace(
        "inputs: {p: p2}", "inputs: {p: s1.p_hat}"),
     "prob.yaml:6: instances.s2.inputs.p: cyclic definition: s1 (inputs) -> s2 (inputs) -> "
     "s1 (inputs)"),
    (MODEL, PROBLEM.replace("g: s1.p_hat - s2.p_hat", "g: l_s * 2"),
     "prob.yaml:10: constraints.g: constraint 'g' does not depend on any parameter"),
    (MODEL, PROBLEM.replace("constants:\n  l_s: 9.7", "constants:\n  p1: 9.7"),
     "prob.yaml:3: constants.p1: 'p1' is already defined in columns"),
    (MODEL.replace("e: k0 + k1*sin(f*p)", "e: k0 + k1*sin(f*s1.p)"), PROBLEM,
     "seg.yaml:11: expressions.e: 's1.p': a model refers only to its own symbols; dotted "
     "names (instance.output) belong in problem files"),
])
def test_spec_error_messages(tmp_path, monkeypatch, model, problem, message) -> None:
    assert _error(tmp_path, monkeypatch, model, problem) == message


def test_missing_problem_file(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SpecError, match="^nothere.yaml: problem file not found$"):
        symcal.load_problem("nothere.yaml")


def test_top_level_must_be_mapping(tmp_path, monkeypatch) -> None:
    assert _error(tmp_path, monkeypatch, problem="- a\n- b\n") == (
        "prob.yaml:1: a problem file must be a mapping of keys, found a YList")
