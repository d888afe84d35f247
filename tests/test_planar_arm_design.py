"""The planar arm in the scenario language (examples/planar_arm/scenario.yaml): its
swing run reads what simulate_arm.py's does, and its calibration motion can be designed
(issue 24 item 2)."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from conftest import ROOT

import symcal
from symcal.data.dataset import make_dataset
from symcal.experiment.optimize import design, parse_target
from symcal.experiment.predict import predict
from symcal.simulation import load_scenario, quiet, simulate_run, truth

EXAMPLE = ROOT / "examples" / "planar_arm"
FIXED = EXAMPLE / "problem_fixed.yaml"


def test_the_swing_run_reads_what_the_numpy_simulator_reads() -> None:
    spec = importlib.util.spec_from_file_location("simulate_arm", EXAMPLE / "simulate_arm.py")
    assert spec is not None and spec.loader is not None
    arm = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(arm)
    scenario = quiet(load_scenario(EXAMPLE / "scenario.yaml"))
    assert truth(scenario)["parameters"] == arm.TRUTH
    ours = simulate_run(scenario, "swing")
    theirs = arm.simulate(1, {}, noise=0.0)["calibration"]
    np.testing.assert_allclose(ours["t"], theirs[:, 0], rtol=0, atol=1e-12)
    for i in (1, 2, 3):
        np.testing.assert_allclose(ours[f"q{i}"], theirs[:, i], rtol=0, atol=1e-12)


def test_the_arms_swing_can_be_designed() -> None:
    """A wider swing within the arm's reach determines every parameter better; a target
    on a2 is met with fewer readings than the narrow swing has."""
    problem = symcal.load_problem(FIXED)
    scenario = load_scenario(EXAMPLE / "scenario.yaml")
    base = predict(problem, scenario)
    assert (base.identifiability.rank, base.identifiability.n_free) == (6, 6)
    out = design(problem, scenario, criterion="D")
    assert "phi1 >= -24 deg" in out.binding
    for name, se in base.se.items():
        assert out.final.se[name] < se, name
    target = design(problem, scenario, targets=(parse_target("a2=2um", problem),))
    assert target.met == {"a2": True} and target.after["n"] < 200
    assert target.final.se["a2"] <= 2e-6 < base.se["a2"]


@pytest.mark.slow
def test_predicted_standard_errors_match_monte_carlo() -> None:
    """40 seeds of the narrow swing: the spread of a2 and py within 25 % of the
    predicted standard errors."""
    problem = symcal.load_problem(FIXED)
    scenario = load_scenario(EXAMPLE / "scenario.yaml")
    predicted = predict(problem, scenario)
    values = []
    for seed in range(40):
        data = {"calibration": make_dataset("calibration", "mc", simulate_run(
            scenario, "calibration", seed), []),
                "validation": make_dataset("validation", "mc", simulate_run(
                    scenario, "calibration", seed + 100), [])}
        result = symcal.solve(problem, data)
        assert result.success
        values.append([result.params[n].value for n in ("a2", "py")])
    spread = np.std(np.array(values), axis=0, ddof=1)
    for k, name in enumerate(("a2", "py")):
        assert spread[k] == pytest.approx(predicted.se[name], rel=0.25), name
