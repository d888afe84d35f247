"""A quadratic candidate is written about the model's own centre (issue 26's new-user
round): a thermocouple's offset and gain written about Tc = 323.15 K (``o + k*(T -
Tc)``) keep their meaning when a quadratic is added about Tc; about 0 K (as it was), the
quadratic's linear and constant parts at 300 K moved them by hundreds of standard errors,
correlated -1.0000 with the new term."""

from __future__ import annotations

import numpy as np
import pytest

import symcal
from symcal.data.dataset import make_dataset

MODELS = {
    "ref.yaml": """\
model: ref
inputs:
  T_raw: {unit: K, noise: 0.002 K}
outputs:
  T: {expr: T_raw, unit: K}
""",
    "tc.yaml": """\
model: tc
constants:
  Tc: {value: 323.15, unit: K}
inputs:
  T_raw: {unit: K, noise: 0.002 K}
parameters:
  o: {value: 0, unit: K, scale: 0.1}
  k: {value: 0, scale: 0.001}
outputs:
  T: {expr: T_raw + o + k*(T_raw - Tc), unit: K}
""",
}


def _bath(column: str, unit: str, instance: str) -> str:
    """A bath of a reference thermometer and one sensor under test (``instance``, named
    as its model file, reading ``column``), their temperatures agreeing."""
    name = instance.split(":")[0]
    return (f"problem: bath\ncolumns:\n  t: {{unit: s, role: time}}\n  T_ref: {{unit: K}}\n"
            f"  {column}: {{unit: {unit}}}\ninstances:\n"
            f"  ref: {{model: ref.yaml, inputs: {{T_raw: T_ref}}, candidates: {{none: true}}}}\n"
            f"  {instance}\nconstraints:\n  g: {{expr: {name}.T - ref.T, unit: mK}}\n"
            f"datasets:\n  calibration: {{path: calibration.csv}}\n"
            f"  validation: {{path: validation.csv}}\n")


MODELS["problem.yaml"] = _bath("T_tc", "K", "tc: {model: tc.yaml, inputs: {T_raw: T_tc}}")
TRUTH = {"tc.o": 0.15, "tc.k": 0.002}
QUAD = 2e-5        # 1/K, about Tc: 0.05 K at the ends of 273-373 K


def _run(name: str, seed: int, n: int) -> symcal.Dataset:
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=float)
    temp = rng.uniform(273.15, 373.15, n)
    o, k, tc = TRUTH["tc.o"], TRUTH["tc.k"], 323.15
    # the reading that makes o + k (T_raw - Tc) + QUAD (T_raw - Tc)^2 + T_raw = T
    raw = temp.copy()
    for _ in range(6):
        raw = temp - o - k * (raw - tc) - QUAD * (raw - tc) ** 2
    return make_dataset(name, "test", {"t": t, "T_ref": temp + rng.normal(0, 0.002, n),
                                       "T_tc": raw + rng.normal(0, 0.002, n)}, [])


@pytest.mark.slow
def test_a_quadratic_is_written_about_the_models_centre(tmp_path) -> None:
    for name, text in MODELS.items():
        (tmp_path / name).write_text(text)
    data = {"calibration": _run("calibration", 1, 600), "validation": _run("validation", 2,
                                                                          300)}
    out = tmp_path / "out"
    result = symcal.improve(tmp_path / "problem.yaml", out, data)
    assert result.quiet and [r.added for r in result.rounds[1:]] == [
        "tc.T += a quadratic dependence on T_tc"]
    model = next((out / "models").glob("*.yaml")).read_text()
    assert "c_quad_T_tc: {value: 323.15, unit: K, doc: reference" in model
    assert "quad_T_tc*(T_raw - c_quad_T_tc)**2" in model
    final = result.rounds[-1].result
    for name, true in TRUTH.items():
        p = final.params[name]
        assert p.se is not None and abs(p.value - true) < 3 * p.se, (name, p.value, p.se)
    quad = final.params["tc.quad_T_tc"]
    assert quad.se is not None and abs(quad.value - QUAD) < 3 * quad.se


NTC = {
    "ref.yaml": MODELS["ref.yaml"],
    "ntc.yaml": """\
model: ntc
constants:
  T25: {value: 298.15, unit: K}
inputs:
  R: {unit: ohm, noise: 0.5 ohm}
parameters:
  R25: {value: 10000, unit: ohm, scale: 1000}
  beta: {value: 3900, unit: K, scale: 100}
outputs:
  T: {expr: 1/(1/T25 + log(R/R25)/beta), unit: K}
""",
    "problem.yaml": _bath("R_nt", "ohm", "nt: {model: ntc.yaml, inputs: {R: R_nt}}"),
}
NTC_TRUTH = {"nt.R25": 10050.0, "nt.beta": 3920.0}
HEAT = -1.25e-6     # K/ohm: self-heating proportional to the resistance, about zero


def _ntc_run(name: str, seed: int, n: int) -> symcal.Dataset:
    rng = np.random.default_rng(seed)
    temp = rng.uniform(273.15, 373.15, n)
    r25, beta = NTC_TRUTH["nt.R25"], NTC_TRUTH["nt.beta"]
    r = r25 * np.exp(beta * (1 / temp - 1 / 298.15))
    for _ in range(8):      # the reading whose model temperature plus HEAT*R is the bath's
        r = r25 * np.exp(beta * (1 / (temp - HEAT * r) - 1 / 298.15))
    return make_dataset(name, "test", {"t": np.arange(n, dtype=float),
                                       "T_ref": temp + rng.normal(0, 0.002, n),
                                       "R_nt": r + rng.normal(0, 0.5, n)}, [])


@pytest.mark.slow
def test_a_linear_term_nearly_absorbed_is_written_about_zero(tmp_path) -> None:
    # a new user's thermistor: centred at the data's mean, the term's value there went to
    # R25, 36 standard errors off; R25 absorbs a constant on T only nearly (its effect
    # varies as T^2 over 0-100 degC), and the term is now written about zero
    for name, text in NTC.items():
        (tmp_path / name).write_text(text)
    data = {"calibration": _ntc_run("calibration", 1, 600),
            "validation": _ntc_run("validation", 2, 300)}
    result = symcal.improve(tmp_path / "problem.yaml", tmp_path / "out", data)
    assert [r.added for r in result.rounds[1:]] == ["nt.T += a term linear in R_nt"]
    model = next((tmp_path / "out" / "models").glob("*.yaml")).read_text()
    assert "T: base.T + lin_R_nt*R" in model
    final = result.rounds[-1].result
    for name, true in NTC_TRUTH.items():
        p = final.params[name]
        assert p.se is not None and abs(p.value - true) < 3 * p.se, (name, p.value, p.se)
