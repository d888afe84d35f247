"""Leads that pay are compared on their BIC within a round.  A new user's linear axis:
its glass scale expands with the air temperature.  The most significant lead (tested
beyond its simpler terms) was the encoder's product with the temperature, a stand-in
that, with the interferometer's coefficient moved 700 standard errors, reached the
floor after one more stand-in; added alone, the scale's own product fits better by a
BIC of about 500, and the diagnosis predicts it."""

from __future__ import annotations

import numpy as np
import pytest

import symcal
from symcal.analysis.discovery import Design, bic_change
from symcal.data.dataset import make_dataset

ENCODER = """model: rotary_encoder
inputs:
  enc: {unit: turn, period: 1 turn, noise: 2.887e-5 turn}
parameters:
  lead: {value: 5.0, unit: mm/turn, scale: 5.0}
outputs:
  x: {expr: lead*enc, unit: mm}
"""
SCALE = """model: glass_scale
inputs:
  xs: {unit: um, noise: 0.2 um}
parameters:
  k: {value: 0, scale: 1e-5}
  o: {value: 0, unit: mm, scale: 0.1}
outputs:
  x: {expr: xs*(1 + k) + o, unit: mm}
"""
IFM = """model: interferometer
constants:
  T0: {value: 293.15, unit: K}
inputs:
  xi: {unit: m, noise: 0.05 um}
  T: {unit: K, noise: 0.01 K}
parameters:
  kT: {value: 0, unit: 1/K, scale: 1e-6}
  o: {value: 0, unit: mm, scale: 1}
outputs:
  x: {expr: xi*(1 + kT*(T - T0)) + o, unit: mm}
"""
PROBLEM = """problem: axis
columns:
  t: {unit: s, role: time}
  enc: {unit: turn, role: axis}
  xs: {unit: um}
  xi: {unit: m}
  T: {unit: K, role: state}
instances:
  encoder: {model: encoder.yaml, inputs: {enc: enc}}
  scale: {model: scale.yaml, inputs: {xs: xs}}
  ifm: {model: ifm.yaml, inputs: {xi: xi, T: T}}
constraints:
  g_es: {expr: encoder.x - scale.x, unit: um}
  g_is: {expr: ifm.x - scale.x, unit: um}
datasets:
  calibration: {path: calibration.csv}
  validation: {path: validation.csv}
"""
T0 = 293.15
LEAD, K, O_S, KT, O_I, ALPHA = 4.998, 15e-6, 0.35, 1e-6, 12.5, 8e-6


def _run(name: str, seed: int, validation: bool) -> symcal.Dataset:
    """The axis moving (x mm) while the air warms; the scale reads short by α(T - T0)x."""
    rng = np.random.default_rng(seed)
    n = 800 if validation else 2000
    t = np.arange(n, dtype=float)
    if validation:
        x, temp = 400 + 380 * np.sin(2 * np.pi * t / 97.37), T0 + 3 - 3 * t / n
    else:
        x, temp = 400 - 399 * np.cos(2 * np.pi * t / 211.3), T0 - 1 + 4 * t / n
    enc = np.round(x / LEAD, 4)
    xs = ((x - O_S) / (1 + K) - ALPHA * (temp - T0) * x) * 1e3 + rng.normal(0, 0.2, n)
    xi = (x - O_I) / (1 + KT * (temp - T0)) * 1e-3 + rng.normal(0, 0.05e-6, n)
    return make_dataset(name, "test", {"t": t, "enc": enc, "xs": xs, "xi": xi,
                                       "T": temp + rng.normal(0, 0.01, n)}, [])


@pytest.mark.slow
@pytest.mark.parametrize("seed", [4, 5])
def test_the_scale_expands_not_the_encoder(tmp_path, seed: int) -> None:
    for name, text in {"encoder.yaml": ENCODER, "scale.yaml": SCALE, "ifm.yaml": IFM,
                       "problem.yaml": PROBLEM}.items():
        (tmp_path / name).write_text(text)
    data = {"calibration": _run("calibration", seed, False),
            "validation": _run("validation", seed + 10, True)}
    result = symcal.improve(tmp_path / "problem.yaml", tmp_path / "out", data)
    assert [r.added for r in result.rounds[1:]] == ["scale.x += the product of xs and T"]
    params = result.rounds[-1].result.params
    assert abs(params["ifm.kT"].value - KT) < 4 * params["ifm.kT"].se
    assert abs(params["encoder.lead"].value - LEAD) < 4 * params["encoder.lead"].se
    why = dict(result.rejected)["encoder.x += the product of encoder.enc and T"]
    assert why.startswith("scale.x += the product of xs and T fits these data better (BIC")
    # the stand-in's files are gone; the kept revision is the round's only one
    assert sorted(p.name for p in (tmp_path / "out").glob("*.yaml")) == [
        "final.yaml", "problem_round1.yaml"]
    assert [p.name for p in (tmp_path / "out" / "models").glob("*.yaml")] == [
        "glass_scale_x_prod_xs_T.yaml"]
    # data given in memory: final.yaml cannot name them, and says so
    final = (tmp_path / "out" / "final.yaml").read_text().replace("\n  ", " ")
    assert ("fitted on data given in memory (calibration, validation), not on the datasets "
            "the problem file names" in final)


def test_bic_change_is_the_refit_bic() -> None:
    """The predicted change equals the BIC of two least-squares fits done by numpy (the
    nuisance alone, then with the columns; one of them a copy of a nuisance column, which
    adds no parameter)."""
    rng = np.random.default_rng(3)
    a = rng.normal(size=(300, 4))
    x = np.column_stack([rng.normal(size=300), a[:, 1]])
    r = a @ rng.normal(size=4) + 0.6 * x[:, 0] + rng.normal(size=300)
    r = r - a @ np.linalg.lstsq(a, r, rcond=None)[0]      # at the nuisance's optimum

    def bic(m: np.ndarray) -> float:
        left = r - m @ np.linalg.lstsq(m, r, rcond=None)[0]
        rank = np.linalg.matrix_rank(m)
        return 300 * np.log(float(left @ left) / 300) + rank * np.log(300)

    design = Design(r, a, tuple("abcd"), ())
    expected = bic(np.column_stack([a, x])) - bic(a)
    assert bic_change(design, x) == pytest.approx(expected, rel=1e-9)
    assert expected < -10           # the term is there: its BIC falls
