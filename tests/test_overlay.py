"""Problem and scenario files that ``extends`` another: merge rules, provenance, errors.

The bundled variants (``*_implicit`` problems, ``*_clean`` scenarios) are overlays; they
are checked against the full files they replaced, kept in ``tests/overlay_cases/``.
"""

from __future__ import annotations

import dataclasses
import textwrap
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np
import pytest

import symcal
import symcal.simulation
from symcal.base.errors import SpecError
from symcal.language.overlay import (
    MAX_DEPTH,
    extends_chain,
    load_with_extends,
    merge_problem,
    merge_scenario,
)
from symcal.language.yamlio import YList, YMap, load_yaml
from symcal.simulation import load_scenario, simulate_run

ROOT = Path(__file__).resolve().parent.parent
CASES = Path(__file__).resolve().parent / "overlay_cases"
PATH_KEYS = {"instances": "model", "datasets": ("path", "simulate")}

SEG = """\
model: seg
constants:
  rho: {value: 1, unit: mm}
inputs:
  p: {unit: mm}
parameters:
  k0: {value: 0, unit: mm}
  k1: {value: 0, unit: mm}
outputs:
  p_hat: {expr: p + k0 + k1*sin(p/rho), unit: mm}
"""

SEG_Q = """\
model: seg_q
extends: seg.yaml
inputs:
  q: {unit: mm}
parameters:
  k2: {value: 0, unit: mm/mm}
outputs:
  p_hat: base.p_hat + k2*q
"""

SEG_R = """\
model: seg_r
inputs:
  r: {unit: mm}
outputs:
  p_hat: r
"""

BASE = """\
problem: base
doc: the base problem
columns:
  p1: {unit: mm}
  p2: {unit: mm}
  q1: {unit: mm}
  x_ref: {unit: mm}
constants:
  l_s: 9.7
parameters:
  a: {value: 1, unit: mm, scale: 2}
  b: 0.5
instances:
  s1: {model: ../models/seg.yaml, inputs: {p: p1}, parameters: {k0: {value: 0.1}}, doc: first}
  s2: {model: ../models/seg.yaml, inputs: {p: p2}}
expressions:
  d: s1.p_hat - s2.p_hat
  m: (s1.p_hat + s2.p_hat) / 2
constraints:
  g: d / l_s
  h: {expr: d * a + b, sigma: 2}
comparisons:
  pos: {estimate: m, reference: x_ref}
stages:
  - {name: one, constraints: [g], free: ["s?.k0"]}
  - {name: two, constraints: [g, h], free: ["*"]}
datasets:
  calibration: {path: data.csv}
  flyby: {simulate: scen.yaml, run: flyby}
"""

SCENARIO = """\
scenario: base
doc: a toy courier
constants:
  sigma: 0.001
  rho: {value: 1, unit: mm}
truth:
  s1.k0: 0.004
  s1.k1: 0.017
  s2.k0: -0.003
states:
  x: {unit: mm}
  y: {unit: mm}
  theta: {unit: deg}
expressions:
  e1: s1.k0 + s1.k1*sin(x/rho)
columns:
  p1: {expr: x - e1, unit: mm, noise: sigma}
  p2: {expr: y - s2.k0, unit: mm, noise: sigma}
effects:
  lateral:
    values: {s1.k9: -0.003, s1.k10: 0.0015}
    add: {e1: s1.k9*sin(y/rho) + s1.k10*cos(y/rho)}
  drift:
    values: {s1.rate: 1.0e-5}
    add: {e1: s1.rate*t}
runs:
  calibration:
    scatter: {n: 50, x: [0.0, 10.0], y: [0.0, 10.0], theta: [-0.5, 0.5]}
  flyby:
    line: {n: 20, from: {x: 5.0, y: -5.0}, to: {x: 5.0, y: 5.0}, theta: 0}
"""


# --------------------------------------------------------------------------- helpers


def _write(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))


@pytest.fixture
def toy(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """models/, base/base.yaml and base/scen.yaml in a fresh working directory."""
    monkeypatch.chdir(tmp_path)
    _write(tmp_path, {"models/seg.yaml": SEG, "models/seg_q.yaml": SEG_Q,
                      "models/seg_r.yaml": SEG_R, "base/base.yaml": BASE,
                      "base/scen.yaml": SCENARIO})
    return tmp_path


def _over(root: Path, body: str, name: str = "over.yaml",
          extends: str = "base/base.yaml") -> Path:
    """An overlay problem ``name`` extending ``extends``, with ``body`` after two lines."""
    _write(root, {name: f"problem: over\nextends: {extends}\n" + textwrap.dedent(body)})
    return root / name


def plain(value: Any) -> Any:
    """Loaded YAML as plain dicts and lists."""
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, list):
        return [plain(v) for v in value]
    return value


def merged(path: Path) -> dict:
    return plain(load_with_extends(path, "problem", merge_problem)[0])


def _message(call: Any, *args: Any) -> str:
    with pytest.raises(SpecError) as err:
        call(*args)
    return str(err.value)


def _absolute_paths(doc: dict, home: Path) -> dict:
    """``doc`` with its instances' and datasets' paths resolved against ``home``."""
    for section in ("instances", "datasets"):
        for entry in doc.get(section, {}).values():
            for key in ("model", "path", "simulate"):
                if key in entry:
                    entry[key] = str((home / entry[key]).resolve())
    return doc


def _functions(problem: Any) -> ca.Function:
    outs = [q.sx for q in problem.constraints]
    outs += [c.estimate for c in problem.comparisons] + [c.reference for c in problem.comparisons]
    return ca.Function("f", [problem.theta, problem.u], [ca.vertcat(*outs)])


# --------------------------------------------------------------------------- bundled files


@pytest.mark.parametrize("name", ["platen_self_calibration_implicit",
                                  "dual_sensor_calibration_implicit"])
def test_bundled_problem_overlays_equal_the_full_files(name: str) -> None:
    over, full = ROOT / "problems" / f"{name}.yaml", CASES / f"{name}_full.yaml"
    a = _absolute_paths(merged(over), over.parent)
    b = _absolute_paths(plain(load_yaml(full)[0]), full.parent)
    assert a.pop("problem") == b.pop("problem") == name
    a.pop("doc"), b.pop("doc")
    assert a == b
    new, old = symcal.load_problem(over), symcal.load_problem(full)
    assert [dataclasses.astuple(p)[:-1] for p in new.parameters] == [
        dataclasses.astuple(p)[:-1] for p in old.parameters]
    assert new.columns == old.columns
    assert [(q.name, q.unit, q.sigma) for q in new.constraints] == [
        (q.name, q.unit, q.sigma) for q in old.constraints]
    f_new, f_old = _functions(new), _functions(old)
    rng = np.random.default_rng(5)
    values = np.array([p.value for p in old.parameters])
    scales = np.array([p.scale for p in old.parameters])
    psi = np.array([c.startswith("psi") for c in old.columns])
    for _ in range(4):
        theta = values + 0.05 * scales * rng.standard_normal(values.size)
        u = rng.uniform(0.0, 3.0, len(old.columns)) * np.where(psi, 0.01, 1.0)
        expected = np.array(f_old(theta, u))
        assert np.isfinite(expected).all()
        np.testing.assert_array_equal(np.array(f_new(theta, u)), expected)


def test_dual_overlay_keeps_the_base_instance_overrides() -> None:
    problem = symcal.load_problem(ROOT / "problems" / "dual_sensor_calibration_implicit.yaml")
    h = next(p for p in problem.parameters if p.name == "cs.h")
    assert h.value == 52.5
    doc = merged(ROOT / "problems" / "dual_sensor_calibration_implicit.yaml")
    assert doc["instances"]["s1"]["inputs"] == {"p": "p1", "q": "ty - l_o*tt"}
    assert list(doc["expressions"])[-3:] == ["tx", "ty", "tt"]


@pytest.mark.parametrize("name", ["courier_platen_clean", "courier_dual_clean"])
def test_bundled_scenario_overlays_simulate_the_same_data(name: str) -> None:
    new = load_scenario(ROOT / "problems" / "scenarios" / f"{name}.yaml")
    old = load_scenario(CASES / f"{name}_full.yaml")
    assert new.name == old.name == name
    assert symcal.simulation.truth(new) == symcal.simulation.truth(old)
    assert new.column_names == old.column_names and new.run_names == old.run_names
    for run in old.run_names:
        for seed in (0, 3):
            a, b = simulate_run(new, run, seed=seed), simulate_run(old, run, seed=seed)
            assert list(a) == list(b)
            for column in a:
                assert np.asarray(a[column]).tobytes() == np.asarray(b[column]).tobytes()


def test_hidden_effect_revision_swaps_one_model() -> None:
    home = ROOT / "examples" / "hidden_effect"
    revised, basic = merged(home / "problem_revised.yaml"), merged(home / "problem.yaml")
    assert revised["instances"].pop("s2") == {
        "model": "models/platen_segment_p_hat_h3_p.yaml", "inputs": {"p": "p2"}, "doc": "y segment"}
    basic["instances"].pop("s2")
    assert _absolute_paths(revised, home) == _absolute_paths(basic, home) | {
        "problem": "basic_s2_p_hat_h3_p",
        "doc": "basic plus s2.p_hat += harmonic 3 of s2.p (period 1.016 mm)"}


# --------------------------------------------------------------------------- merge rules


def test_keyed_sections_replace_add_and_remove(toy: Path) -> None:
    over = _over(toy, """\
        doc: the overlay
        weighting: estimated
        constants: {l_s: 10.0, l_o: 4.85}
        parameters: {b: ~, c: {value: 3, unit: mm}}
        columns: {q1: ~, y_ref: {unit: mm}}
        expressions: {m: ~, m2: (s1.p_hat + s2.p_hat) / 2 + l_o}
        constraints: {h: ~, g2: d + c}
        comparisons: {pos: {estimate: m2, reference: x_ref, unit: um}, pos_y: {estimate: m2,
                      reference: y_ref}}
        datasets: {flyby: ~, check: {path: check.csv}}
        """)
    doc = merged(over)
    assert doc["problem"] == "over" and doc["doc"] == "the overlay"
    assert doc["weighting"] == "estimated"
    assert doc["constants"] == {"l_s": 10.0, "l_o": 4.85}
    assert doc["parameters"] == {"a": {"value": 1, "unit": "mm", "scale": 2},
                                 "c": {"value": 3, "unit": "mm"}}
    assert list(doc["columns"]) == ["p1", "p2", "x_ref", "y_ref"]
    assert doc["expressions"] == {"d": "s1.p_hat - s2.p_hat",
                                  "m2": "(s1.p_hat + s2.p_hat) / 2 + l_o"}
    assert doc["constraints"] == {"g": "d / l_s", "g2": "d + c"}
    assert doc["comparisons"]["pos"] == {"estimate": "m2", "reference": "x_ref", "unit": "um"}
    assert list(doc["comparisons"]) == ["pos", "pos_y"]
    assert doc["datasets"] == {"calibration": {"path": str(toy / "base" / "data.csv")},
                               "check": {"path": "check.csv"}}
    assert "extends" not in doc
    problem = symcal.load_problem(_over(toy, "stages: [{name: two, remove: true}]\n"
                                             "constraints: {h: ~}\n", "again.yaml"))
    assert [q.name for q in problem.constraints] == ["g"]
    assert [p.name for p in problem.parameters] == ["s1.k0", "s1.k1", "s2.k0", "s2.k1", "a",
                                                    "b"]


def test_implicit_section_merges_by_key(toy: Path) -> None:
    base = toy / "base" / "base.yaml"
    base.write_text(base.read_text() + "implicit:\n  d: {start: p1 - p2}\n  m: {start: p1}\n")
    doc = merged(_over(toy, "implicit: {m: ~, d: {start: p2, steps: 2}}\n"))
    assert doc["implicit"] == {"d": {"start": "p2", "steps": 2}}


def test_instance_model_swap_keeps_inputs_parameters_and_doc(toy: Path) -> None:
    over = _over(toy, """\
        instances:
          s1: {model: models/seg_q.yaml, inputs: {q: q1}}
          s2: {parameters: {k1: {value: 0.2, fixed: true}}}
          s3: {model: models/seg.yaml, inputs: {p: q1}}
        """)
    doc = merged(over)
    assert doc["instances"]["s1"] == {
        "model": "models/seg_q.yaml", "inputs": {"p": "p1", "q": "q1"},
        "parameters": {"k0": {"value": 0.1}}, "doc": "first"}
    assert doc["instances"]["s2"] == {
        "model": str(toy / "models" / "seg.yaml"), "inputs": {"p": "p2"},
        "parameters": {"k1": {"value": 0.2, "fixed": True}}}
    assert list(doc["instances"]) == ["s1", "s2", "s3"]
    problem = symcal.load_problem(over)
    values = {p.name: (p.value, p.fixed) for p in problem.parameters}
    assert values["s1.k0"] == (0.1, False) and values["s2.k1"] == (0.2, True)
    assert "s1.k2" in values and "s2.k2" not in values


def test_instance_inputs_and_overrides_removed_by_null(toy: Path) -> None:
    doc = merged(_over(toy, "instances: {s1: {parameters: {k0: ~}, doc: ~}, s2: ~}\n"))
    assert doc["instances"] == {"s1": {"model": str(toy / "models" / "seg.yaml"),
                                       "inputs": {"p": "p1"}, "parameters": {}}}
    over = _over(toy, "instances:\n  s2: {inputs: {p: ~}}\n")
    assert _message(symcal.load_problem, over) == (
        "over.yaml:4: instances.s2.inputs: input 'p' of model 'seg' is not bound "
        "(add 'p: <column or expression>')")


def test_stages_merge_by_name(toy: Path) -> None:
    over = _over(toy, """\
        stages:
          - {name: two, constraints: [h], free: [a]}
          - {name: three, constraints: [g, h], free: ["*"], method: ipopt}
          - {name: one, remove: true}
        """)
    stages = merged(over)["stages"]
    assert stages == [{"name": "two", "constraints": ["h"], "free": ["a"]},
                      {"name": "three", "constraints": ["g", "h"], "free": ["*"],
                       "method": "ipopt"}]
    symcal.load_problem(over)  # validates: the stages name known constraints


def test_removing_an_unknown_stage_is_an_error(toy: Path) -> None:
    over = _over(toy, "stages:\n  - {name: tow, remove: true}\n")
    assert _message(merged, over) == (
        "over.yaml:4: stages.0.name: no stage 'tow' to remove (did you mean 'two'?); "
        "stages: one, two")
    over = _over(toy, "stages:\n  - {name: two, remove: yes please}\n")
    assert _message(merged, over) == (
        "over.yaml:4: stages.0.remove: expected true (to remove stage 'two'), found "
        "'yes please'")


def test_a_value_that_is_not_a_mapping_replaces_the_base(toy: Path) -> None:
    _write(toy, {"a.yaml": "problem: a\ncolumns: courier\nconstants: {x: 1}\n",
                 "b.yaml": "problem: b\nextends: a.yaml\ncolumns: {p1: {unit: mm}}\n",
                 "c.yaml": "problem: c\nextends: b.yaml\ncolumns: courier\nconstants: [1]\n"})
    # columns over a preset add to (or replace) the preset's columns, one by one
    columns = merged(toy / "b.yaml")["columns"]
    assert columns["p1"] == {"unit": "mm"} and columns["t"]["role"] == "time"
    assert list(columns) == ["t", "p1", "p2", "p3", "p4", "psi_x", "psi_y", "x_ref", "y_ref",
                             "theta_ref"]
    assert merged(toy / "c.yaml")["columns"] == "courier"
    assert merged(toy / "c.yaml")["constants"] == [1]


def test_provenance_survives_merging(toy: Path) -> None:
    doc, where = load_with_extends(_over(toy, "constraints: {g2: d}\n"), "problem",
                                   merge_problem)
    constraints = doc["constraints"]
    assert isinstance(constraints, YMap)
    assert (constraints.key_files["g"], constraints.key_lines["g"]) == ("base/base.yaml", 20)
    assert (constraints.key_files["g2"], constraints.key_lines["g2"]) == ("over.yaml", 3)
    assert isinstance(doc["stages"], YList) and doc["stages"].item_files == ["base/base.yaml"] * 2
    assert str(where) == "over.yaml:1"


def test_relative_paths_stay_relative_to_the_file_that_wrote_them(toy: Path) -> None:
    _write(toy, {"variants/mid.yaml": """\
        problem: mid
        extends: ../base/base.yaml
        instances:
          s2: {model: ../models/seg_q.yaml, inputs: {q: q1}}
        datasets:
          flyby: {path: flyby.csv}
        """})
    over = _over(toy, "instances: {s3: {model: models/seg.yaml, inputs: {p: q1}}}\n",
                 extends="variants/mid.yaml")
    doc = merged(over)
    models = {k: v["model"] for k, v in doc["instances"].items()}
    assert models == {"s1": str(toy / "models" / "seg.yaml"),
                      "s2": str(toy / "models" / "seg_q.yaml"), "s3": "models/seg.yaml"}
    assert doc["datasets"] == {"calibration": {"path": str(toy / "base" / "data.csv")},
                               "flyby": {"path": str(toy / "variants" / "flyby.csv")}}
    problem = symcal.load_problem(over)
    assert "s2.k2" in [p.name for p in problem.parameters]
    assert extends_chain("over.yaml", "problem") == (
        over, toy / "variants" / "mid.yaml", toy / "base" / "base.yaml")
    assert extends_chain(toy / "base" / "base.yaml", "problem") == (toy / "base" / "base.yaml",)


# --------------------------------------------------------------------------- errors


def test_an_error_in_the_base_names_the_base_and_the_overlay(toy: Path) -> None:
    base = toy / "base" / "base.yaml"
    base.write_text(base.read_text().replace("g: d / l_s", "g: d / zzz"))
    over = _over(toy, "constraints: {g2: d}\n")
    assert _message(symcal.load_problem, over) == (
        "base/base.yaml:20: constraints.g: unknown symbol 'zzz' (in the base of over.yaml)")
    _write(toy, {"mid.yaml": "problem: mid\nextends: over.yaml\n"})
    assert _message(symcal.load_problem, toy / "mid.yaml") == (
        "base/base.yaml:20: constraints.g: unknown symbol 'zzz' (in the base of mid.yaml)")


def test_an_error_in_the_overlay_names_the_overlay(toy: Path) -> None:
    over = _over(toy, "constraints:\n  g2: d * zzz\n")
    assert _message(symcal.load_problem, over) == (
        "over.yaml:4: constraints.g2: unknown symbol 'zzz'")


def test_a_key_kept_from_the_base_under_an_overlay_entry(toy: Path) -> None:
    over = _over(toy, "instances:\n  s1: {model: models/seg_r.yaml}\n")
    assert _message(symcal.load_problem, over) == (
        "base/base.yaml:14: instances.s1.inputs.p: 'p' is not an input of model 'seg_r'; "
        "it has: r (in the base of over.yaml)")


def test_a_cycle_names_the_chain_of_files(toy: Path) -> None:
    _write(toy, {"a.yaml": "problem: a\nextends: b/b.yaml\n",
                 "b/b.yaml": "problem: b\nextends: ../a.yaml\n",
                 "self.yaml": "problem: s\nextends: self.yaml\n"})
    assert _message(symcal.load_problem, toy / "a.yaml") == (
        "b/b.yaml:2: extends: problems extend each other in a cycle: a.yaml -> b/b.yaml -> "
        "a.yaml (in the base of a.yaml)")
    assert _message(symcal.load_problem, toy / "self.yaml") == (
        "self.yaml:2: extends: problems extend each other in a cycle: self.yaml -> self.yaml")


def test_a_missing_base_is_an_error_at_the_extends_line(toy: Path) -> None:
    over = _over(toy, "doc: x\n", extends="base/nothere.yaml")
    assert _message(symcal.load_problem, over) == (
        "over.yaml:2: extends: problem file not found: base/nothere.yaml")
    _write(toy, {"mid.yaml": "problem: mid\nextends: over.yaml\n"})
    assert _message(symcal.load_problem, toy / "mid.yaml") == (
        "over.yaml:2: extends: problem file not found: base/nothere.yaml (in the base of "
        "mid.yaml)")
    over = _over(toy, "", extends="[base.yaml]")
    assert _message(symcal.load_problem, over) == (
        "over.yaml:2: extends: expected text, found a list")


def test_extends_goes_at_most_max_depth_levels(toy: Path) -> None:
    assert MAX_DEPTH == 32
    for level in range(MAX_DEPTH):
        _write(toy, {f"f{level}.yaml": f"problem: f{level}\nextends: f{level + 1}.yaml\n"})
    _write(toy, {f"f{MAX_DEPTH}.yaml": "problem: last\nextends: base/base.yaml\n"})
    assert _message(symcal.load_problem, toy / "f0.yaml") == (
        "f32.yaml:2: extends: more than 32 levels of 'extends' below f0.yaml (in the base of "
        "f0.yaml)")
    assert merged(toy / "f1.yaml")["problem"] == "f1"  # 32 levels: f1 -> ... -> base
    assert len(extends_chain(toy / "f1.yaml", "problem")) == MAX_DEPTH + 1
    assert _message(extends_chain, toy / "f0.yaml", "problem").startswith("f32.yaml:2: ")


def test_a_base_must_be_a_file_of_the_same_kind(toy: Path) -> None:
    over = _over(toy, "", extends="models/seg.yaml")
    assert _message(symcal.load_problem, over) == (
        "over.yaml:2: extends: models/seg.yaml is not a problem file (it has no 'problem' "
        "key); a problem can only extend a problem")
    _write(toy, {"scen.yaml": "scenario: s\nextends: base/base.yaml\n"})
    assert _message(load_scenario, toy / "scen.yaml") == (
        "scen.yaml:2: extends: base/base.yaml is not a scenario file (it has no 'scenario' "
        "key); a scenario can only extend a scenario")


def test_an_overlay_declares_its_own_name(toy: Path) -> None:
    _write(toy, {"over.yaml": "extends: base/base.yaml\ndoc: nameless\n"})
    assert _message(symcal.load_problem, toy / "over.yaml") == (
        "over.yaml:1: missing required key 'problem'")


def test_invalid_yaml_in_a_base_names_the_overlay(toy: Path) -> None:
    (toy / "base" / "base.yaml").write_text("problem: base\nconstants: {a: 1\n")
    message = _message(symcal.load_problem, _over(toy, ""))
    assert message.startswith("base/base.yaml:3: invalid YAML: ")
    assert message.endswith(" (in the base of over.yaml)")


# --------------------------------------------------------------------------- scenarios


def test_scenarios_merge_deeply_and_null_removes(toy: Path) -> None:
    _write(toy, {"clean.yaml": """\
        scenario: clean
        extends: base/scen.yaml
        constants: {sigma: 0.0005}
        truth: {s1.k1: 0.02, s2.k0: ~}
        effects: {drift: ~}
        expressions: {e1: s1.k0 + s1.k1*sin(x/rho)}
        columns: {p2: {expr: y}}
        runs:
          calibration: {scatter: {x: [1.0, 2.0]}}
          flyby: ~
        """})
    scenario = load_scenario(toy / "clean.yaml")
    base = load_scenario(toy / "base" / "scen.yaml")
    assert scenario.name == "clean" and scenario.doc == "a toy courier"
    assert scenario.column("p1").noise == 0.0005 and scenario.column("p2").noise == 0.0005
    assert [(v.name, v.value) for v in scenario.truth] == [("s1.k0", 0.004), ("s1.k1", 0.02)]
    assert [e.name for e in scenario.active_effects] == ["lateral"]
    assert [e.name for e in base.active_effects] == ["lateral", "drift"]
    assert scenario.run_names == ("calibration",)
    scatter = scenario.runs[0].motion
    assert (scatter.n, dict(scatter.ranges)["x"], dict(scatter.ranges)["y"]) == (
        50, (1.0, 2.0), (0.0, 10.0))
    doc = plain(load_with_extends(toy / "clean.yaml", "scenario", merge_scenario)[0])
    assert doc["effects"] == {"lateral": {"values": {"s1.k9": -0.003, "s1.k10": 0.0015},
                                          "add": {"e1": "s1.k9*sin(y/rho) + s1.k10*cos(y/rho)"}}}
    assert doc["columns"]["p2"] == {"expr": "y", "unit": "mm", "noise": "sigma"}


def test_scenario_without_effects(toy: Path) -> None:
    _write(toy, {"clean.yaml": "scenario: clean\nextends: base/scen.yaml\neffects: ~\n"})
    scenario = load_scenario(toy / "clean.yaml")
    assert scenario.active_effects == ()
    base = load_scenario(toy / "base" / "scen.yaml")
    plain_base = base.overlay({"effects": None})
    for seed in (0, 1):
        a = simulate_run(scenario, "calibration", seed=seed)
        b = simulate_run(plain_base, "calibration", seed=seed)
        assert all(np.array_equal(a[c], b[c]) for c in a)


def test_scenario_errors_name_the_file_that_wrote_the_key(toy: Path) -> None:
    scen = toy / "base" / "scen.yaml"
    scen.write_text(scen.read_text().replace("noise: sigma}", "nosie: sigma}", 1))
    _write(toy, {"clean.yaml": "scenario: clean\nextends: base/scen.yaml\n"
                               "runs: {calibration: {dt: -1}}\n"})
    message = _message(load_scenario, toy / "clean.yaml")
    assert message.startswith("base/scen.yaml:17: columns.p1.nosie: unknown key 'nosie' "
                              "(did you mean 'noise'?); allowed keys: ")
    assert message.endswith(" (in the base of clean.yaml)")
    scen.write_text(SCENARIO)
    assert _message(load_scenario, toy / "clean.yaml") == (
        "clean.yaml:3: runs.calibration.dt: expected a positive number, found -1")
