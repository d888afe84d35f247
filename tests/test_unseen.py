"""What the noise floor cannot vouch for (Baarda's external reliability): a candidate the
parameters nearly absorb can be present below its detectable size and move them by
hundreds of standard errors while every test is quiet (a new user's turbine meter: a
coupling on the ultrasonic reading left ``tur.k`` 141 SE off, and nothing said so)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import symcal
from symcal.analysis.discovery import (
    Design,
    _nuisance,
    _project,
    _reach_bound,
    noncentrality,
    unseen_bias,
)
from symcal.data.dataset import make_dataset
from symcal.report.text import diagnosis_report, unvouched
from symcal.revise.diagnose import diagnose
from symcal.revise.reliability import UNSEEN


def _toy(seed: int, m: int) -> tuple[Design, np.ndarray]:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(200, 3))
    x = a @ rng.normal(size=(3, m)) + 0.05 * rng.normal(size=(200, m))
    return Design(rng.normal(size=200), a, ("p0", "p1", "p2"), ()), x


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_reach_is_the_shift_of_a_term_at_its_detectable_size(seed: int) -> None:
    """Inject the term the test detects with its stated power, in the direction that
    moves parameter k most, and fit the nuisance to it with numpy: k moves by the reach
    times its standard error, and the term's non-centrality is λ*."""
    design, x = _toy(seed, 1)
    level = 0.01 / 30
    reach = unseen_bias(design, x, level)
    a = design.nuisance
    inv = np.linalg.inv(a.T @ a)
    xp = x - a @ np.linalg.lstsq(a, x, rcond=None)[0]
    lam = noncentrality(1, level)
    gamma = np.sqrt(lam) / np.linalg.norm(xp)            # |x_p γ|² = λ* (σ = 1)
    shift = np.linalg.lstsq(a, x[:, 0] * gamma, rcond=None)[0]
    np.testing.assert_allclose(np.abs(shift) / np.sqrt(np.diag(inv)), reach, rtol=1e-8)
    assert float(np.sum((xp[:, 0] * gamma) ** 2)) == pytest.approx(lam)


@pytest.mark.parametrize("seed", [4, 5, 6, 7])
def test_the_bound_is_never_below_a_parameters_reach(seed: int) -> None:
    for m in (1, 2, 3):
        design, x = _toy(seed, m)
        level = 1e-3
        xp = _project(x, _nuisance(design).u)
        reach = unseen_bias(design, x, level)
        assert _reach_bound(x, xp, level) >= float(reach.max()) * (1 - 1e-9)


MODELS = {
    "ref.yaml": """\
model: ref
inputs:
  m: {unit: kg/s, noise: 0.002 kg/s}
outputs:
  mdot: {expr: m, unit: kg/s}
""",
    "vol.yaml": """\
model: vol
constants:
  rho: {value: 1, unit: kg/L}
inputs:
  q: {unit: L/min, noise: 0.5 L/min}
parameters:
  k: {value: 1.0, scale: 0.01}
  b: {value: 0, unit: L/min, scale: 1}
outputs:
  mdot: {expr: rho*(k*q + b), unit: kg/s}
""",
    "problem.yaml": """\
problem: loop
columns:
  t: {unit: s, role: time}
  m_c: {unit: kg/s}
  q_t: {unit: L/min}
  u_us: {unit: m**3/h, noise: 0.05 m**3/h}
instances:
  cor: {model: ref.yaml, inputs: {m: m_c}, candidates: {none: true}}
  tur:
    model: vol.yaml
    inputs: {q: q_t}
    candidates: {variables: [q_t, u_us], kinds: [linear]}
constraints:
  g: {expr: tur.mdot - cor.mdot, unit: g/s}
datasets:
  calibration: {path: calibration.csv}
  validation: {path: validation.csv}
""",
}
K, B = 1.012, -0.8          # the turbine's gain and offset (L/min)
COUPLING = 0.3              # L/min per m³/h of the ultrasonic meter's reading


def _run(name: str, seed: int, n: int, u_noise: float = 0.05) -> symcal.Dataset:
    """Mass flow 1-10 kg/s; the turbine reads ``q`` with k q + b + c u = its flow in
    L/min; an ultrasonic meter reads the same flow in m³/h (the coupling's source)."""
    rng = np.random.default_rng(seed)
    m = rng.uniform(1, 10, n)
    u = m * 3.6 + rng.normal(0, u_noise, n)       # 1 kg/s of water ≈ 3.6 m³/h here
    q = (m * 60 - B - COUPLING * u) / K
    return make_dataset(name, "test", {"t": np.arange(n, dtype=float),
                                       "m_c": m + rng.normal(0, 0.002, n),
                                       "q_t": q + rng.normal(0, 0.5, n), "u_us": u}, [])


@pytest.mark.slow
def test_a_nearly_absorbed_coupling_is_named_with_the_gain_it_moves(tmp_path) -> None:
    for name, text in MODELS.items():
        (tmp_path / name).write_text(text)
    data = {"calibration": _run("calibration", 1, 400), "validation": _run("validation", 2,
                                                                          200)}
    result = symcal.solve(tmp_path / "problem.yaml", data=data)
    diag = diagnose(result)
    assert result.at_floor and not diag.significant       # quiet: the floor is reached
    k = result.params["tur.k"]
    off = abs(k.value - K) / k.se
    assert off > UNSEEN                  # and yet the gain is far off its truth
    reach = dict(unvouched(diag))
    assert set(reach) == {"tur.k"} and reach["tur.k"] >= off
    named = {c.label: dict(c.unseen) for c in diag.candidates if c.unseen}
    assert named == {"tur.mdot += a term linear in u_us": {"tur.k": reach["tur.k"]}}
    text = diagnosis_report(diag)
    assert (f"what the floor cannot vouch for: tur.k (up to {reach['tur.k']:.0f} SE): "
            "effects the parameters absorb, or nearly, would move them that far unseen "
            '("Absorbed" and "Nearly absorbed" below)') in text
    assert "  tur.mdot += a term linear in u_us: unseen up to " in text
    nearly = json.loads(json.dumps(diag.to_dict()))["nearly_absorbed"]
    assert [n["label"] for n in nearly] == ["tur.mdot += a term linear in u_us"]
    assert nearly[0]["moves"] == {"tur.k": pytest.approx(reach["tur.k"])}


@pytest.mark.slow
def test_the_courier_platen_problem_names_nothing() -> None:
    """277 candidates on the bundled §3.1 problem: none is nearly absorbed."""
    diag = diagnose(symcal.solve("problems/platen_self_calibration.yaml"), report=False)
    assert len(diag.candidates) > 200 and unvouched(diag) == []


@pytest.mark.slow
def test_improve_says_what_the_floor_cannot_vouch_for(tmp_path, capsys) -> None:
    from symcal.cli import main

    for name, text in MODELS.items():
        (tmp_path / name).write_text(text)
    for name, seed, n in (("calibration", 1, 400), ("validation", 2, 200)):
        ds = _run(name, seed, n)
        np.savetxt(tmp_path / f"{name}.csv", np.column_stack(
            [ds.columns[c] for c in ("t", "m_c", "q_t", "u_us")]), delimiter=",",
            header="t,m_c,q_t,u_us", comments="")
    problem = str(tmp_path / "problem.yaml")
    assert main(["improve", problem, "--out", str(tmp_path / "a"), "--quiet"]) == 0
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if "cannot vouch" in ln)
    assert line.startswith("  what the floor cannot vouch for: tur.k (up to ")
    assert line.endswith("SE): effects the parameters absorb, or nearly, would move them "
                         "that far unseen (symcal diagnose of the final problem names them)")
    assert main(["improve", problem, "--out", str(tmp_path / "b"), "--json", "--quiet"]) == 0
    unvouched_ = json.loads(capsys.readouterr().out)["unvouched"]
    assert [u["parameter"] for u in unvouched_] == ["tur.k"] and unvouched_[0]["reach_se"] > 100


@pytest.mark.slow
def test_an_absorbed_coupling_is_not_vouched_for_at_any_size(tmp_path) -> None:
    """The ultrasonic reading exactly proportional to the flow: the coupling is absorbed
    by the gain, the verdict says so; the term linear in the turbine's own reading (its
    gain, restated) is not named."""
    for name, text in MODELS.items():
        (tmp_path / name).write_text(text.replace("noise: 0.05 m**3/h", "noise: 0 m**3/h"))
    data = {"calibration": _run("calibration", 1, 400, 0.0),
            "validation": _run("validation", 2, 200, 0.0)}
    diag = diagnose(symcal.solve(tmp_path / "problem.yaml", data=data))
    absorbed = {c.label for c in diag.candidates if c.absorbed}
    assert {"tur.mdot += a term linear in u_us", "tur.mdot += a term linear in q_t"} <= absorbed
    assert unvouched(diag) == [("tur.k", float("inf"))]
    text = diagnosis_report(diag)
    assert ("what the floor cannot vouch for: tur.k (by any amount: an effect it absorbs)"
            in text)
    assert json.loads(json.dumps(diag.to_dict()))["nearly_absorbed"] == []
