"""Implicit models: the error evaluated at the corrected reading (issue: eq. 3's
approximation).  Data are simulated with the distortion applied at the true position."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest
from conftest import ROOT

import symcal
from symcal.analysis.implicit import implicit_checks
from symcal.base.errors import SpecError
from symcal.cli import main
from symcal.data.dataset import make_dataset
from symcal.experiment.predict import noise_floors
from symcal.simulation import load_scenario, quiet, simulate_run, truth
from symcal.solvers.objective import Objective

PROBLEMS = ROOT / "problems"
SCENARIOS = PROBLEMS / "scenarios"
UM = 1e-3


def _data(scenario, seed: int) -> dict[str, symcal.Dataset]:
    return {name: make_dataset(name, "simulated", simulate_run(scenario, name, seed), [])
            for name in ("calibration", "flyby")}


@pytest.fixture(scope="module")
def platen_pair():
    scenario = load_scenario(SCENARIOS / "courier_platen_clean.yaml")
    data = _data(scenario, seed=21)
    explicit = symcal.solve(PROBLEMS / "platen_self_calibration.yaml", data)
    implicit = symcal.solve(PROBLEMS / "platen_self_calibration_implicit.yaml", data)
    # the floor the exact (implicit) model reaches: the noise propagated through it
    floor = noise_floors(implicit.problem, scenario)["g_p_std"] * np.sqrt((1000 - 33) / 1000)
    return scenario, explicit, implicit, floor


def test_implicit_platen_reaches_the_noise_floor(platen_pair) -> None:
    _, explicit, implicit, floor = platen_pair
    ratio = implicit.stat("g_p", unit="mm").after.std / floor
    assert abs(ratio - 1) < 0.05, ratio
    # the explicit model cannot: it leaves a structured residual of order e'·e
    assert explicit.stat("g_p", unit="mm").after.std / floor > 1.2


def test_implicit_platen_recovers_truth_where_explicit_is_biased(platen_pair) -> None:
    scenario, explicit, implicit, _ = platen_pair
    true = truth(scenario)["parameters"]

    def worst(result: symcal.Result) -> float:
        return max(abs(p.value - true[p.name]) / p.se for p in result.params.values() if p.se)

    assert worst(implicit) < 4
    assert worst(explicit) > 8  # biased by many standard errors


def test_implicit_platen_keeps_the_explicit_null_space(platen_pair) -> None:
    _, explicit, implicit, _ = platen_pair
    assert implicit.method == "lm" and explicit.method == "linear"
    assert [c.text for c in implicit.identifiability.null_space] == [
        c.text for c in explicit.identifiability.null_space]
    assert implicit.stages[0].notes[0] == \
        "started from the explicit model's closed-form estimate"
    assert implicit.stages[0].notes[-1].startswith("weighting: each observation's "
                                                   "constraints whitened by their covariance "
                                                   "propagated from the readings' declared "
                                                   "noise")


def test_fixed_point_checks_reported(platen_pair) -> None:
    _, _, implicit, _ = platen_pair
    checks = {(c.name, c.dataset): c for c in implicit.implicit}
    assert set(checks) == {(f"s{i}.u", d) for i in range(1, 5) for d in ("calibration", "flyby")}
    for c in checks.values():
        assert c.steps == 4 and c.contracts
        assert 0.05 < c.contraction < 0.5
        assert c.remaining < 0.05 * UM  # four steps leave well under 0.1 µm
    assert "Implicit definitions (fixed-point steps, checked at the estimate)" in \
        symcal.text_report(implicit)


def test_implicit_model_is_nonlinear_and_its_twin_linear() -> None:
    problem = symcal.load_problem(PROBLEMS / "platen_self_calibration_implicit.yaml")
    free = np.ones(len(problem.parameters), dtype=bool)
    assert Objective(problem, ("g_p",), free).nonlinear() == ["g_p"]
    assert problem.explicit is not None
    assert Objective(problem.explicit, ("g_p",), free).nonlinear() == []
    assert [i.steps for i in problem.explicit.implicit] == [0, 0, 0, 0]


def test_explicit_and_implicit_agree_when_errors_are_tiny() -> None:
    scenario = load_scenario(SCENARIOS / "courier_platen_clean.yaml")
    tiny = {k: v * 1e-3 for k, v in truth(scenario)["parameters"].items()}
    scenario = scenario.overlay({"truth": tiny})
    data = _data(scenario, seed=22)
    explicit = symcal.solve(PROBLEMS / "platen_self_calibration.yaml", data)
    implicit = symcal.solve(PROBLEMS / "platen_self_calibration_implicit.yaml", data)
    for p in explicit.params.values():
        if p.se is not None:
            assert abs(implicit.params[p.name].value - p.value) < 0.01 * p.se, p.name


@pytest.fixture(scope="module")
def dual_noiseless():
    scenario = quiet(load_scenario(SCENARIOS / "courier_dual_clean.yaml"))
    data = _data(scenario, seed=23)
    true = dict(truth(scenario)["parameters"])
    true["cs.h"] = true.pop("h")
    explicit = symcal.solve(
        symcal.load_problem(PROBLEMS / "dual_sensor_calibration.yaml").with_weighting("equal"),
        data)
    implicit = symcal.solve(
        symcal.load_problem(PROBLEMS / "dual_sensor_calibration_implicit.yaml")
        .with_weighting("equal"), data)
    return true, explicit, implicit


@pytest.mark.slow
def test_implicit_dual_removes_the_mounting_bias(dual_noiseless) -> None:
    """Noiseless data: the implicit form recovers h, l_x, l_y to well under 2 µm, where the
    explicit form is biased (measured: h +6.2, l_x -11.5, l_y -54 µm)."""
    true, explicit, implicit = dual_noiseless
    assert implicit.success
    for name in ("cs.h", "l_x", "l_y"):
        assert abs(implicit.params[name].value - true[name]) < 2 * UM, name
    bias = {n: explicit.params[n].value - true[n] for n in ("cs.h", "l_x", "l_y")}
    assert abs(bias["l_y"]) > 20 * UM and abs(bias["l_x"]) > 5 * UM, bias
    for cost in implicit.stages[-1].costs:  # noiseless: residuals vanish
        assert cost.rms_after < 0.01, cost


@pytest.mark.slow
def test_not_a_contraction_is_a_failed_result(tmp_path, capsys) -> None:
    base = (PROBLEMS / "platen_self_calibration_implicit.yaml").as_posix()
    path = tmp_path / "steep.yaml"
    path.write_text(f"problem: steep\nextends: {base}\n"
                    "instances:\n  s1: {parameters: {k1: {value: 0.3, fixed: true}}}\n")
    problem = symcal.load_problem(path)
    theta = np.array([p.value for p in problem.parameters])
    data = _data(load_scenario(SCENARIOS / "courier_platen_clean.yaml"), seed=24)
    checks = implicit_checks(problem, data, theta)
    steep = {c.dataset: c for c in checks if c.name == "s1.u"}
    assert not steep["calibration"].contracts and steep["calibration"].contraction > 1.5
    assert steep["flyby"].contracts  # segment 1 stands still on the fly-by
    assert main(["solve", str(path), "--quiet"]) == 1
    out = capsys.readouterr().out
    assert "'s1.u' is not a contraction on dataset 'calibration': max |dF/dx| = " in out
    assert "NO: not a contraction" in out


MODEL = """\
model: seg
inputs: {p: {}}
parameters: {k: 0.01}
expressions:
  u: p + e
  e: k*sin(u) + w
  w: k*p
outputs:
  p_hat: p + e
"""


@pytest.mark.parametrize(("implicit", "message"), [
    ("implicit:\n  u: {start: p}\n  q: {start: p}\n",
     "seg.yaml:12: implicit.q: 'q' is not an output or expression of model 'seg'"),
    ("implicit:\n  u: {start: p, steps: 0}\n",
     "seg.yaml:11: implicit.u.steps: expected a whole number of at least 1, found 0"),
    ("implicit:\n  u: {start: p}\n  w: {start: 0}\n",
     "seg.yaml:12: implicit.w: 'w' is declared implicit but its definition does not refer to "
     "itself"),
    ("", "seg.yaml:5: expressions.u: cyclic definition: s1.e -> s1.u -> s1.e"),
])
def test_implicit_spec_errors(tmp_path, monkeypatch, implicit, message) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "seg.yaml").write_text(MODEL + implicit)
    (tmp_path / "prob.yaml").write_text(textwrap.dedent("""\
        problem: demo
        instances:
          s1: {model: seg.yaml, inputs: {p: p1}}
          s2: {model: seg.yaml, inputs: {p: p2}}
        constraints: {g: s1.p_hat - s2.p_hat}
        datasets: {calibration: {path: data.csv}}
        columns: courier
        """))
    with pytest.raises(SpecError) as err:
        symcal.load_problem("prob.yaml")
    assert str(err.value) == message


@pytest.mark.slow
def test_implicit_dual_reaches_the_noise_floor_on_clean_data() -> None:
    """The bundled implicit dual problem on clean simulated data: every constraint at its
    noise floor (within 5 %); the explicit problem stays above it on the same data."""
    scenario = load_scenario(SCENARIOS / "courier_dual_clean.yaml")
    data = _data(scenario, seed=25)
    dof = np.sqrt((3 * 1000 - 47) / (3 * 1000))
    implicit = symcal.solve(PROBLEMS / "dual_sensor_calibration_implicit.yaml", data)
    floors = noise_floors(implicit.problem, scenario)   # what the exact model reaches
    explicit = symcal.solve(PROBLEMS / "dual_sensor_calibration.yaml", data)
    for name in ("g_x", "g_y", "g_p"):
        floor = floors[f"{name}_std"] * dof
        assert abs(implicit.stat(name, unit="mm").after.std / floor - 1) < 0.05, name
    assert explicit.stat("g_p", unit="mm").after.std / (floors["g_p_std"] * dof) > 1.1
