"""Dual-sensor calibration (§3.2): IPOPT path, stages, uncertainty, failure handling."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from conftest import ROOT

import symcal
from symcal.cli import main
from symcal.data.dataset import make_dataset
from symcal.language.problem_file import load_problem_spec
from symcal.problem.build import build_problem
from symcal.simulation import load_scenario, simulate_run, truth

DUAL = ROOT / "problems" / "dual_sensor_calibration.yaml"
PLATEN = ROOT / "problems" / "platen_self_calibration.yaml"
SCENARIOS = ROOT / "problems" / "scenarios"
SCENARIO = SCENARIOS / "courier_dual.yaml"
MOUNT = ("cs.h", "l_x", "l_y")
UM = 1e-3


def _paper_scenario(n: int = 1000):
    """The paper's synthetic test: model-consistent data (courier_dual_model.yaml), 1 µm
    noise on every reading (the coordination angles' 2e-5 rad is 1 µm at h = 50 mm)."""
    return load_scenario(SCENARIOS / "courier_dual_model.yaml").overlay(
        {"constants": {"sigma_p": 1e-3, "step_p": 0.0, "sigma_psi": 1e-3 / 50.0}})


def _data(scenario, seed: int, n: int | None = None) -> dict[str, symcal.Dataset]:
    return {name: make_dataset(name, "simulated", simulate_run(scenario, name, seed, n), [])
            for name in ("calibration", "flyby")}


def _true_values(scenario) -> dict[str, float]:
    values = dict(truth(scenario)["parameters"])
    values["cs.h"] = values.pop("h")
    return values


def _single_stage():
    spec = load_problem_spec(DUAL)
    return build_problem(dataclasses.replace(spec, study=dataclasses.replace(spec.study,
                                                                           stages=())))


def _paper_start(true: dict[str, float], seed: int) -> dict[str, float]:
    """5 % error on the coordination parameters, 3 µm random error on the platen's."""
    rng = np.random.default_rng(seed)
    start = {}
    for name, value in true.items():
        if name.startswith("s"):
            start[name] = value + rng.normal(0, 3 * UM)
        else:
            start[name] = value * (1 + 0.05 * rng.choice([-1, 1]))
    return start


REPEATS = 16


@pytest.fixture(scope="module")
def repeated() -> tuple[list[symcal.Result], dict[str, float]]:
    """The paper's synthetic experiment, repeated with 16 noise seeds and starts."""
    scenario = _paper_scenario()
    true = _true_values(scenario)
    problem = _single_stage().with_weighting("estimated")
    results = [symcal.solve(problem, _data(scenario, seed=200 + k),
                            initial=_paper_start(true, seed=300 + k))
               for k in range(REPEATS)]
    return results, true


@pytest.fixture(scope="module")
def paper_result(repeated) -> tuple[symcal.Result, dict[str, float]]:
    results, true = repeated
    return results[0], true


def _rms_error(results: list[symcal.Result], true: dict[str, float], name: str) -> float:
    return float(np.sqrt(np.mean([(r.params[name].value - true[name]) ** 2 for r in results])))


@pytest.mark.slow
def test_paper_claim_mounting_within_20_um(repeated) -> None:
    """The paper: h, l_x, l_y within 20 µm.  Over 16 repetitions the RMS error of h and
    l_y is well below 20 µm (measured 3.4 and 7.3 µm; with the paper's equal weights
    16.6 and 24.1 µm).  l_x cannot be promised within 20 µm on this design: the platen's
    angle noise (0.1 mrad) acts through the 90 mm lever, so its standard error is about
    20 µm whatever the weighting (measured RMS 21.9 µm); the test bounds it at 25 µm."""
    results, true = repeated
    assert all(r.success and r.method == "lm" for r in results)
    assert _rms_error(results, true, "cs.h") < 10 * UM
    assert _rms_error(results, true, "l_y") < 15 * UM
    assert _rms_error(results, true, "l_x") < 25 * UM


@pytest.mark.slow
def test_paper_claim_rest_within_1_um(repeated) -> None:
    """k1..k10 of every segment within 1 µm in every repetition."""
    results, true = repeated
    for result in results:
        rest = [p for p in result.params.values() if p.se is not None and p.name.startswith("s")]
        assert len(rest) == 40
        worst = max(abs(p.value - true[p.name]) for p in rest)
        assert worst < 1 * UM, worst


@pytest.mark.slow
def test_paper_experiment_within_four_standard_errors(paper_result) -> None:
    result, true = paper_result
    for p in result.params.values():
        if p.se is not None:
            assert abs(p.value - true[p.name]) < 4 * p.se, (p.name, p.value, true[p.name])
    for combo in result.identifiability.identifiable_combinations:
        value = sum(c * true[name] for name, c in combo.coefficients.items())
        assert abs(combo.value - value) < 4 * combo.se, combo.text


@pytest.mark.slow
def test_standard_errors_match_monte_carlo_spread(repeated) -> None:
    """Predicted standard errors against the spread of the 16 repeated calibrations.

    With 16 repetitions the sample standard deviation itself scatters by about 18 %;
    the ratio must lie within [0.5, 1.7] (beyond 3 of those standard deviations).
    """
    results, true = repeated
    for name in ("cs.h", "l_x", "l_y", "s1.k1", "s2.k9", "s3.k10"):
        spread = _rms_error(results, true, name)
        predicted = float(np.sqrt(np.mean([r.uncertainty.se[name] ** 2 for r in results])))
        assert 0.5 < spread / predicted < 1.7, (name, spread, predicted)


@pytest.mark.slow
def test_null_space_of_the_dual_problem(paper_result) -> None:
    result, _ = paper_result
    assert [c.text for c in result.identifiability.null_space] == [
        "s1.k0 + s3.k0 + o_x", "s2.k0 + s4.k0 + o_y"]
    assert [c.text for c in result.identifiability.identifiable_combinations] == [
        "s1.k0 - o_x", "s3.k0 - o_x", "s2.k0 - o_y", "s4.k0 - o_y"]


@pytest.mark.slow
def test_staged_solve_reports_every_stage() -> None:
    scenario = _paper_scenario()
    result = symcal.solve(symcal.load_problem(DUAL), _data(scenario, seed=7))
    assert [(st.name, st.method) for st in result.stages] == [
        ("platen", "linear"), ("coordination", "linear"), ("full", "lm")]
    assert all(st.success for st in result.stages)
    platen, coordination, full = result.stages
    assert [c.name for c in platen.costs] == ["g_p"]
    assert [c.name for c in coordination.costs] == ["g_x", "g_y"]
    assert coordination.cost_after < coordination.cost_before
    assert full.cost_after <= full.cost_before
    assert len(full.free) == 49
    # the stage fixing the platen must leave it untouched; the first stage the mounting
    assert set(coordination.unmoved) == set()
    assert result.stages[0].free == tuple(f"s{i}.k{j}" for i in range(1, 5) for j in range(9))
    assert full.conditioning_before.condition_number > 1e6
    true = _true_values(scenario)
    for name in MOUNT:
        assert abs(result.params[name].value - true[name]) < 4 * result.uncertainty.se[name]


def test_linear_problem_same_estimate_through_both_paths() -> None:
    problem = symcal.load_problem(PLATEN)
    linear = symcal.solve(problem, options=symcal.SolveOptions(method="linear"))
    ipopt = symcal.solve(problem, options=symcal.SolveOptions(method="ipopt"))
    assert (linear.method, ipopt.method) == ("linear", "ipopt")
    a = np.array([p.value for p in linear.params.values()])
    b = np.array([p.value for p in ipopt.params.values()])
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-9)
    assert ipopt.stages[0].cost_after == pytest.approx(linear.stages[0].cost_after, rel=1e-9)


@pytest.mark.slow
def test_failed_solve_is_marked_with_last_iterate(capsys) -> None:
    scenario = _paper_scenario()
    data = _data(scenario, seed=8)
    result = symcal.solve(symcal.load_problem(DUAL), data, symcal.SolveOptions(max_iter=1))
    full = result.stages[-1]
    assert not result.success and not full.success
    assert full.status == "iteration_limit"
    assert full.message.startswith("trust-region Levenberg-Marquardt: stopped: iteration "
                                   "limit (1) reached before convergence (a Gauss-Newton "
                                   "step would still lower the cost by ")
    assert full.iterations == 1
    assert full.cost_after < full.cost_before  # the best iterate, not the start
    assert "*** FAILED ***" in symcal.text_report(result)


def test_cli_failed_solve_exits_1_and_prints_report(capsys) -> None:
    code = main(["solve", str(DUAL), "--max-iter", "1", "--quiet"])
    out = capsys.readouterr()
    assert code == 1
    assert "3. full: lm  *** FAILED ***" in out.out
    assert out.err == ""


@pytest.mark.slow
def test_cli_progress_on_stderr_and_json_on_stdout(capsys) -> None:
    assert main(["solve", str(DUAL), "--json"]) == 0
    out = capsys.readouterr()
    assert "  full: iteration   1  cost " in out.err
    doc = json.loads(out.out)
    assert [s["name"] for s in doc["stages"]] == ["platen", "coordination", "full"]
    full = doc["stages"][2]
    assert full["method"] == "lm" and full["status"].startswith("converged")
    assert {c["name"] for c in full["costs"]} == {"g_x", "g_y", "g_p"}
    assert full["hessian_conditioning"]["before"]["condition_number"] > 1e6
    assert set(doc["uncertainty"]["correlation"]["names"]) >= {"cs.h", "l_x"}


@pytest.mark.slow
def test_parameter_at_bound_is_reported(tmp_path) -> None:
    text = DUAL.read_text().replace("parameters: {h: {value: 52.5}}",
                                    "parameters: {h: {value: 48, upper: 49.5}}")
    text = text.replace("../models/", f"{ROOT.as_posix()}/models/").replace(
        "scenarios/", f"{ROOT.as_posix()}/problems/scenarios/")
    path = tmp_path / "bounded.yaml"
    path.write_text(text)
    result = symcal.solve(symcal.load_problem(path), _data(_paper_scenario(), seed=9))
    coordination = result.stages[1]
    assert coordination.method == "ipopt"
    assert coordination.notes[0] == ("the closed-form estimate put cs.h outside its bounds; "
                                     "solved again with IPOPT, which respects them")
    assert "cs.h" in coordination.at_bound
    assert result.params["cs.h"].value == pytest.approx(49.5, abs=1e-6)
