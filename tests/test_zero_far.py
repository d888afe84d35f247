"""A term in a temperature is written about the run's own temperature, not about 0 K: a
new user's gyro whose bias follows the temperature ended quiet with the bias 74
standard errors from its value in the run (written ``lin_T*T``, the bias became the
bias at 0 K, nine times less determined; in degC, at 0 degC)."""

from __future__ import annotations

import numpy as np
import pytest

import symcal
from symcal.data.dataset import make_dataset

SENSOR = """model: manometer
inputs:
  raw: {unit: kPa}
parameters:
  bias: {value: 0, unit: kPa, scale: 0.1}
outputs:
  p: {expr: raw - bias, unit: kPa}
"""
PROBLEM = """problem: pair
columns:
  t: {unit: s, role: time}
  ra: {unit: kPa, noise: 0.002 kPa}
  rb: {unit: kPa, noise: 0.01 kPa}
  T: {unit: UNIT, role: state, noise: 0.02 K}
instances:
  ref: {model: sensor.yaml, inputs: {raw: ra}, parameters: {bias: {fixed: true}}}
  dut: {model: sensor.yaml, inputs: {raw: rb}}
constraints:
  g: {expr: ref.p - dut.p, unit: kPa}
datasets:
  calibration: {path: calibration.csv}
  validation: {path: validation.csv}
"""
BIAS, SLOPE, TREF = 0.35, -0.004, 296.0       # kPa, kPa/K, K: the bias at TREF


def _run(name: str, seed: int, n: int, kelvin: bool) -> symcal.Dataset:
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=float)
    temp = 293.15 + 10 * (1 - np.cos(2 * np.pi * t / n)) + rng.normal(0, 0.3, n)
    p = 100 + 5 * np.sin(2 * np.pi * t / 97.0)
    rb = p + BIAS + SLOPE * (temp - TREF)
    return make_dataset(name, "test", {
        "t": t, "ra": p + rng.normal(0, 0.002, n), "rb": rb + rng.normal(0, 0.01, n),
        "T": (temp if kelvin else temp - 273.15) + rng.normal(0, 0.02, n)}, [])


@pytest.mark.slow
@pytest.mark.parametrize("unit", ["K", "delta_degC"])
def test_the_bias_stays_the_bias_in_the_run(tmp_path, unit: str) -> None:
    (tmp_path / "sensor.yaml").write_text(SENSOR)
    (tmp_path / "problem.yaml").write_text(PROBLEM.replace("UNIT", unit))
    data = {"calibration": _run("calibration", 5, 1500, unit == "K"),
            "validation": _run("validation", 15, 600, unit == "K")}
    out = tmp_path / "out"
    result = symcal.improve(tmp_path / "problem.yaml", out, data)
    assert result.quiet
    assert [r.added for r in result.rounds[1:]] == ["dut.p += a term linear in T"]
    model = next((out / "models").glob("*.yaml")).read_text()
    assert "lin_T*(v_T - c_lin_T)" in model, model
    centre = float(np.mean(data["calibration"].columns["T"]))
    centre += 0.0 if unit == "K" else 273.15
    params = result.rounds[-1].result.params
    bias = params["dut.bias"]                # the bias at the run's centre
    assert abs(bias.value - (BIAS + SLOPE * (centre - TREF))) < 4 * bias.se
    # determined as well as an offset in the run is, not as an extrapolation to zero
    assert bias.se < 2 * result.rounds[0].result.params["dut.bias"].se
    slope = params["dut.lin_T"]
    assert abs(slope.value + SLOPE) < 4 * slope.se     # the model takes it back out
