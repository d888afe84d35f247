"""Recovery on simulated courier data (§3.1): truth within standard errors, noise floor,
and a hidden lateral effect that keeps the residual above the floor."""

from __future__ import annotations

import courier_scenarios
import numpy as np
import pytest
from conftest import ROOT

import symcal
from symcal.data.dataset import make_dataset
from symcal.simulation import simulate_run, truth

PROBLEM = ROOT / "problems" / "platen_self_calibration.yaml"
N = 1000
RANK = 33


def _clean(*effects: dict):
    """The default scenario with the model's own assumptions (error at the reading,
    small-angle geometry: courier_platen_model.yaml) and only the given effects."""
    return courier_scenarios.platen(*effects)


def _floor(scenario) -> float:
    return courier_scenarios.floors(PROBLEM, scenario)["g_p_std"]


def _solve(scenario, seed: int) -> symcal.Result:
    data = {name: make_dataset(name, "simulated", simulate_run(scenario, name, seed=seed), [])
            for name in ("calibration", "flyby")}
    return symcal.solve(symcal.load_problem(PROBLEM), data)


@pytest.fixture(scope="module")
def clean_result():
    scenario = _clean()
    return scenario, _solve(scenario, seed=11)


def test_every_identifiable_parameter_within_four_standard_errors(clean_result) -> None:
    scenario, result = clean_result
    true = truth(scenario)["parameters"]
    checked = 0
    for p in result.params.values():
        if p.se is not None:
            assert abs(p.value - true[p.name]) < 4 * p.se, (p.name, p.value, true[p.name], p.se)
            checked += 1
    assert checked == 32
    for combo in result.identifiability.identifiable_combinations:
        value = sum(c * true[name] for name, c in combo.coefficients.items())
        assert abs(combo.value - value) < 4 * combo.se, combo.text


def test_calibrated_residual_at_noise_floor(clean_result) -> None:
    scenario, result = clean_result
    floor = _floor(scenario) * np.sqrt((N - RANK) / N)
    after = result.stat("g_p", unit="mm").after.std
    assert abs(after / floor - 1) < 0.2, (after, floor)
    assert result.stat("g_p", unit="mm").before.std > 20 * floor


def test_fly_by_improves_against_interferometer(clean_result) -> None:
    _, result = clean_result
    pos = result.stat("position_y", "flyby")
    assert pos.after.std < 0.2 * pos.before.std
    theta_y = result.stat("theta_y", "flyby")
    assert theta_y.after.std < 0.2 * theta_y.before.std


LATERAL = [(0.006, -0.003), (-0.004, 0.005), (0.002, 0.006), (-0.005, -0.002)]


@pytest.mark.parametrize(("scale", "min_ratio"), [
    (1.0, 1.05), pytest.param(2.0, 1.2, marks=pytest.mark.slow)])
def test_hidden_lateral_effect_keeps_residual_above_floor(scale, min_ratio) -> None:
    """Eq. (9) lateral terms of 2-7 µm (scale 1) stay above the noise floor of g_p.

    They stay only a little above it: in this geometry a segment's lateral coordinate is,
    to first order, the reading of a perpendicular segment, whose own harmonics absorb
    most of the effect (the paper's §3.1.2 remark; measured ratios 1.09 and 1.27).  The
    floor's own sampling spread at N = 1000 is about 2.3 %, so 1.05 is a clear margin.
    The interferometer exposes what g_p hides: the stationary pair's angle on the fly-by.
    """
    lateral = [courier_scenarios.lateral(i + 1, k9 * scale, k10 * scale)
               for i, (k9, k10) in enumerate(LATERAL)]
    scenario = _clean(*lateral)
    result = _solve(scenario, seed=12)
    floor = _floor(scenario) * np.sqrt((N - RANK) / N)
    ratio = result.stat("g_p", unit="mm").after.std / floor
    assert ratio > min_ratio, ratio
    clean = _solve(_clean(), seed=12).stat("theta_x", "flyby")
    assert result.stat("theta_x", "flyby").after.std > 5 * clean.after.std
