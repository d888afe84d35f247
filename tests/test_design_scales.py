"""`symcal design` states the standard errors a solve then reports, whatever the
parameters' scales: a new user's linear axis with an Abbe term (a gain in mm/rad on a
pitch of 2e-5 rad) was predicted 1.3e4 times too precise, because the sandwich's
middle matrix was formed in the parameters' units and cut at 1e-9 of its largest
eigenvalue; and a term's minimal detectable effect was 4.85 times too large."""

from __future__ import annotations

import numpy as np
import pytest

import symcal
from symcal.experiment.predict import predict
from symcal.simulation import load_scenario

GAUGE = """model: gauge
inputs:
  r: {unit: mm, noise: 10 um}
  w: {unit: rad}
parameters:
  c: {value: 0, unit: mm, scale: 0.1}
  k: {value: 0, unit: 1, scale: 0.01}
  d: {value: 0, unit: mm/rad, scale: 10}
outputs:
  x_hat: {expr: c + (1 + k)*r + d*w, unit: mm}
"""
PROBLEM = """problem: abbe
instances:
  s: {model: gauge.yaml, inputs: {r: b, w: w}}
constraints:
  g: {expr: s.x_hat - a, unit: um}
columns:
  a: {unit: mm, noise: 10 um}
  b: {unit: mm}
  w: {unit: rad}
datasets:
  calibration: {simulate: scenario.yaml, run: calibration, seed: SEED}
"""
SCENARIO = """scenario: abbe
truth:
  s.c: {value: 0.05, unit: mm}
  s.k: 0.002
  s.d: {value: 30, unit: mm/rad}
states:
  x: {unit: mm}
  p: {unit: rad}
columns:
  a: {expr: x, unit: mm, noise: 0.01}
  b: {expr: (x - s.c - s.d*p)/(1 + s.k), unit: mm, noise: 0.01}
  w: {expr: p, unit: rad}
runs:
  calibration:
    scatter: {n: 400, x: [-5, 5], p: [-2e-5, 2e-5]}
"""


@pytest.mark.slow
def test_predicted_errors_are_the_solves_and_the_spread_over_seeds(tmp_path) -> None:
    (tmp_path / "gauge.yaml").write_text(GAUGE)
    (tmp_path / "scenario.yaml").write_text(SCENARIO)
    names = ["s.c", "s.k", "s.d"]
    estimates, stated = [], []
    for seed in range(1, 9):
        (tmp_path / "p.yaml").write_text(PROBLEM.replace("SEED", str(seed)))
        result = symcal.solve(tmp_path / "p.yaml")
        estimates.append([result.params[n].value for n in names])
        stated.append([result.params[n].se for n in names])
    predicted = predict(symcal.load_problem(tmp_path / "p.yaml"),
                        load_scenario(tmp_path / "scenario.yaml"), "calibration").se
    # the solves' own standard errors (they vary by a few % with the draw)
    np.testing.assert_allclose([predicted[n] for n in names], np.median(stated, axis=0),
                               rtol=0.1)
    # and the estimates' spread over 8 seeds (a standard deviation from 8 draws: ±50 %)
    spread = np.std(estimates, axis=0, ddof=1)
    assert all(0.5 < spread[i] / predicted[n] < 1.6 for i, n in enumerate(names)), (
        spread, predicted)


@pytest.mark.slow
def test_the_predicted_mde_is_diagnoses_whatever_the_terms_size(tmp_path) -> None:
    """A term of this gauge is scaled by the diagnosis to about its output's noise (15 µm,
    not the 1 µm of a coefficient's unit term): the design's minimal detectable effect
    is what diagnose states on data of the motion (median of 5 draws within 10 %)."""
    from symcal.cli.design import _detectable
    from symcal.experiment.detectable import parse_mde
    from symcal.revise.diagnose import diagnose

    (tmp_path / "gauge.yaml").write_text(GAUGE)
    (tmp_path / "scenario.yaml").write_text(SCENARIO)
    (tmp_path / "p.yaml").write_text(PROBLEM.replace("SEED", "1"))
    problem = symcal.load_problem(tmp_path / "p.yaml")
    scenario = load_scenario(tmp_path / "scenario.yaml")
    label = "s.x_hat += a quadratic dependence on b"
    det = _detectable(parse_mde(f"mde({label})=5um"), problem, scenario, 0, 0.01,
                      tmp_path / "work")
    predicted = det.mde(predict(det.problem, scenario, "calibration"))
    stated = []
    for seed in range(1, 6):
        (tmp_path / "p.yaml").write_text(PROBLEM.replace("SEED", str(seed)))
        diag = diagnose(symcal.solve(tmp_path / "p.yaml"))
        stated.append(next(c.mde for c in diag.candidates if c.label == label))
    assert float(np.median(stated)) == pytest.approx(predicted, rel=0.1), (stated, predicted)
