"""Experiment design (issue 17): predicted uncertainty of a planned motion, optimised
motions within a scenario's limits, checked against Monte-Carlo calibrations (on the
courier; the planar arm and the bundled examples are designed in their own tests)."""

from __future__ import annotations

import dataclasses
import json
import os

import numpy as np
import pytest
import yaml
from conftest import ROOT

import symcal
from symcal.base.errors import SpecError, SymcalError
from symcal.cli import main
from symcal.data.dataset import make_dataset
from symcal.data.loading import needed_columns
from symcal.experiment.optimize import design, parse_target, with_motion
from symcal.experiment.predict import predict
from symcal.problem.build import load_problem
from symcal.simulation import load_scenario, quiet, run_states, simulate_run
from symcal.simulation.graph import graph

PROBLEM = ROOT / "problems" / "dual_sensor_calibration.yaml"
SCENARIO = ROOT / "problems" / "scenarios" / "courier_dual.yaml"
MOUNT = ("l_x", "l_y", "cs.h")


@pytest.fixture(scope="module")
def problem():
    return load_problem(PROBLEM)


@pytest.fixture(scope="module")
def scenario():
    return load_scenario(SCENARIO)


def _variant(tmp_path, text: str):
    path = tmp_path / "variant.yaml"
    path.write_text(f"scenario: variant\nextends: {SCENARIO}\n{text}")
    return path


# ----------------------------------------------------------------------- scenario language


@pytest.mark.parametrize(("text", "message"), [
    ("design: {run: calibraton, limits: {n: [1, 10]}}",
     "design.run: no run named 'calibraton' (did you mean 'calibration'?); runs: "
     "calibration, flyby"),
    ("design: {run: flyby, limits: {n: [1, 400]}}",
     "design.run: run 'flyby' is a line; only a scatter or dwells run can be designed"),
    ("design: {run: calibration, limits: {theta: [-1, 1]}}",
     "design.limits.theta: run 'calibration' has theta [-1.5, 1.5], outside its "
     "limits [-1, 1]"),
    ("design: {run: calibration, limits: {dwell: [0, 2]}}",
     "design.limits.dwell: dwell is a share of the draws: its limits must lie within [0, 1], "
     "found [0, 2]"),
    ("design: {run: calibration, limits: {n: [10.5, 1000]}}",
     "design.limits.n: n's limits must be whole numbers from 1 to"),
    ("design: {run: calibration, limits: {n: [2000, 1000]}}",
     "design.limits.n: expected lo <= hi, found [2000, 1000]"),
    ("design: {run: calibration, limits: {speed: [1, 2]}}",
     "design.limits.speed: unknown key 'speed'"),
    ("design: {run: calibration, limits: {theta: ~, dwell: ~, n: ~}}",
     "design.limits: lists nothing that may change; list some of x, y, theta, dwell, n"),
    ("runs: {calibration: {scatter: {dwell: 1.5}}}",
     "dwell is a share of the draws: expected a number from 0 to 1, found 1.5"),
])
def test_bad_design_sections_are_refused_with_file_and_line(tmp_path, text, message):
    path = _variant(tmp_path, text)
    with pytest.raises(SpecError) as err:
        load_scenario(path)
    assert message in str(err.value)
    assert "variant.yaml:3" in str(err.value)


def test_dwell_puts_a_share_at_the_ends_and_keeps_the_positions(scenario):
    run = "calibration"
    plain = simulate_run(scenario, run, seed=3, n=2000)
    values = {"x": (0.0, 2.032), "y": (0.0, 2.032), "theta": (-1.5, 1.5), "dwell": 0.6,
              "n": 1000}
    dwelling = simulate_run(with_motion(scenario, run, values), run, seed=3, n=2000)
    ends = np.isclose(np.abs(dwelling["theta_ref"]), np.deg2rad(1.5), rtol=0, atol=1e-15)
    assert abs(ends.mean() - 0.6) < 0.04            # binomial sd 0.011
    assert abs(np.mean(dwelling["theta_ref"][ends] > 0) - 0.5) < 0.05
    same = ~ends
    np.testing.assert_array_equal(dwelling["theta_ref"][same], plain["theta_ref"][same])


@pytest.mark.parametrize("name", ["courier_dual.yaml", "courier_dual_model.yaml"])
def test_the_symbolic_readings_are_the_simulators(name):
    """The readings the design differentiates are the simulator's, noiseless: explicit
    ones as written, solved ones by the unrolled Newton steps (to 1e-12 mm)."""
    import casadi as ca

    sc = quiet(load_scenario(ROOT / "problems" / "scenarios" / name))
    run = sc.runs[0]
    cols = simulate_run(sc, run.name, seed=5, n=50)
    t, states = run_states(sc, run, 5, 50)
    g = graph(sc)
    symbolic = g.explicit_columns()
    names = ["p1", "p2", "p3", "p4", "psi_x", "psi_y", "x_ref", "y_ref", "theta_ref"]
    fn = ca.Function("f", [g.states, g.t], [ca.vertcat(*(symbolic[c] for c in names))])
    got = np.array(fn.map(50)(states, t[None, :]))
    for k, column in enumerate(names):
        np.testing.assert_allclose(got[k], cols[column], rtol=0, atol=1e-12)
    assert g.implicit == ("model" in name)


# ----------------------------------------------------------------------- targets


@pytest.mark.parametrize(("text", "message"), [
    ("l_x", "--target l_x: expected NAME=VALUE with an optional unit, e.g. l_x=5um"),
    ("l_z=5um", "--target l_z=5um: the problem has no parameter 'l_z' (did you mean"),
    ("l_x=-5um", "--target l_x=-5um: a standard error must be positive"),
    ("l_x=5s", "--target l_x=5s: 's' is not a unit of l_x, which is in 'mm'"),
])
def test_bad_targets_are_refused(problem, text, message):
    with pytest.raises(SymcalError) as err:
        parse_target(text, problem)
    assert str(err.value).startswith(message)


def test_targets_convert_to_the_parameters_unit(problem):
    assert parse_target("l_x=5um", problem).value == pytest.approx(0.005)
    assert parse_target("l_x = 0.005", problem).value == pytest.approx(0.005)


def test_an_unidentifiable_target_is_refused(problem, scenario):
    with pytest.raises(SymcalError) as err:
        design(problem, scenario, targets=(parse_target("o_x=1um", problem),))
    assert str(err.value).startswith("--target o_x=1um: 'o_x' is determined only in a "
                                     "combination")


# ----------------------------------------------------------------------- the command line


def test_cli_prediction_json_shape(capsys):
    code = main(["design", str(PROBLEM), "--scenario", str(SCENARIO), "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert code == 0
    assert set(doc) == {"parameters", "binding", "scenario"}
    assert doc["binding"] == [] and doc["scenario"] is None
    assert set(doc["parameters"]["l_x"]) == {"predicted_se", "baseline_se"}
    assert doc["parameters"]["l_x"]["predicted_se"] == doc["parameters"]["l_x"]["baseline_se"]
    assert 0.01 < doc["parameters"]["l_x"]["baseline_se"] < 0.05      # mm: 10-50 um
    assert doc["parameters"]["o_x"]["baseline_se"] is None            # only in combination


@pytest.mark.parametrize(("argv", "message"), [
    (["--target", "l_x=5um"], "--target and --criterion choose a motion: they need "
                              "--optimize"),
    (["--out", "x"], "--out x writes the optimised scenario: it needs --optimize"),
])
def test_cli_option_errors(capsys, argv, message):
    code = main(["design", str(PROBLEM), "--scenario", str(SCENARIO), *argv])
    assert code == 2
    assert message in capsys.readouterr().err


def test_a_scenario_without_design_section_is_refused(problem):
    plain = ROOT / "problems" / "scenarios" / "courier_dual_clean.yaml"
    sc = dataclasses.replace(load_scenario(plain), design=None)
    with pytest.raises(SymcalError) as err:
        design(problem, sc)
    assert "has no 'design' section" in str(err.value)


# ----------------------------------------------------------------------- Monte Carlo


def _monte_carlo(problem, scenario, seeds):
    values = []
    for seed in seeds:
        data = make_dataset("calibration", "mc", simulate_run(scenario, "calibration",
                                                              seed=seed),
                            needed_columns(problem))
        result = symcal.solve(problem, {"calibration": data})
        assert result.success
        values.append([result.params[name].value for name in MOUNT])
    return np.std(np.array(values), axis=0, ddof=1)


@pytest.mark.slow
def test_designed_motion_meets_its_target_and_predictions_match_monte_carlo(problem,
                                                                           scenario, tmp_path,
                                                                           capsys):
    # the design: l_x within 20 um with the fewest observations, within the limits
    code = main(["design", str(PROBLEM), "--scenario", str(SCENARIO), "--optimize",
                 "--target", "l_x=20um", "--out", str(tmp_path / "d"), "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert code == 0
    assert doc["scenario"] == str(tmp_path / "d" / "scenario.yaml")
    lx = doc["parameters"]["l_x"]
    assert lx["predicted_se"] <= 0.020 < lx["baseline_se"]
    designed = load_scenario(tmp_path / "d" / "scenario.yaml")    # loadable, simulate-able
    motion = designed.runs[0].motion
    assert motion.n < 1000                                         # fewer observations
    assert (tmp_path / "d" / "motion.png").stat().st_size > 1000
    # Monte Carlo on the designed motion (the default one: the next test)
    spread = _assert_monte_carlo_matches(problem, designed)
    # l_x meets its target within the same 20 % (seeds 0-99: 22.5 um, 95 % interval
    # 19.8-26.2 um, for a prediction of 20.0 um)
    assert spread[0] <= 0.020 * 1.2


def _assert_monte_carlo_matches(problem, sc):
    # 100 seeds: the SD of 100 draws has a relative standard error of 7 %.  On 300-400
    # seeds the ratios MC / predicted are 0.94-1.07 on both motions (each 95 % interval
    # within 1 +- 0.15); over sliding windows of 100 seeds they range 0.84-1.27, so a
    # window can fail the 20 % criterion by chance (about 1 in 10)
    predicted = predict(problem, sc)
    spread = _monte_carlo(problem, sc, range(100))
    for name, mc in zip(MOUNT, spread, strict=True):
        assert mc == pytest.approx(predicted.se[name], rel=0.2), (sc.name, name)
    return spread


@pytest.mark.slow
def test_predictions_match_monte_carlo_on_the_default_motion(problem, scenario):
    _assert_monte_carlo_matches(problem, scenario)


@pytest.mark.slow
def test_the_bundled_target_reports_its_binding_limits(problem, scenario):
    out = design(problem, scenario, targets=(parse_target("l_x=5um", problem),))
    assert out.met == {"l_x": False}
    assert set(out.binding) >= {"theta <= 1.5 deg", "theta >= -1.5 deg", "dwell <= 1",
                                "n <= 1000"}
    assert out.after["n"] == 1000 and out.after["dwell"] == pytest.approx(1.0, abs=1e-6)
    best = out.final.se["l_x"]
    assert best < 0.5 * out.baseline.se["l_x"]                # 29.5 -> 12.9 um
    assert out.needed_n > 5000
    for name in ("l_y", "cs.h"):   # the others barely move (measured: cs.h +7 %)
        assert out.final.se[name] <= 1.10 * out.baseline.se[name]
    dumped = yaml.safe_load(out.scenario_yaml(SCENARIO, SCENARIO.parent))
    assert dumped["runs"]["calibration"]["scatter"]["theta"] == [-1.5, 1.5]


@pytest.mark.slow
def test_diagnose_points_to_design_when_a_direction_is_poorly_determined(problem):
    from symcal.report.text import diagnosis_verdict
    from symcal.revise.diagnose import diagnose

    verdict = diagnosis_verdict(diagnose(symcal.solve(problem)))
    pointer = [line for line in verdict if line.startswith("poorly determined")]
    assert len(pointer) == 1
    assert "l_x" in pointer[0] and "symcal design" in pointer[0]
    shown = os.path.relpath(SCENARIO)   # relative to where the command runs
    assert "--scenario " + (str(SCENARIO) if shown.startswith("..") else shown) in pointer[0]
