"""A candidate on the problem's reference (every parameter of the sensor fixed: a
certified load cell) is said to be one: a new user's stack of load cells, one of them
not linear, had the same quadratic on the reference as the diagnosis's second
suggestion, which reached the floor with the other cells' parameters 5-9 standard
errors off."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from conftest import ROOT

import symcal
from symcal.data.dataset import make_dataset

CELL = """model: load_cell
inputs:
  r: {unit: mV/V}
parameters:
  zero: {value: 0, unit: mV/V, scale: 0.01}
  sens: {value: 0.4, unit: mV/V/kN, scale: 0.4}
outputs:
  F: {expr: (r - zero)/sens, unit: kN}
"""
PROBLEM = """problem: stack
columns:
  t: {unit: s, role: time}
  rA: {unit: mV/V, noise: 0.0002 mV/V}
  rB: {unit: mV/V, noise: 0.0005 mV/V}
  rC: {unit: mV/V, noise: 0.0005 mV/V}
instances:
  A: {model: cell.yaml, inputs: {r: rA},
      parameters: {sens: {value: 0.40012, fixed: true}, zero: {value: 0.012, fixed: true}}}
  B: {model: cell.yaml, inputs: {r: rB}}
  C: {model: cell.yaml, inputs: {r: rC}}
constraints:
  g_AB: {expr: A.F - B.F, unit: N}
  g_AC: {expr: A.F - C.F, unit: N}
datasets:
  calibration: {path: calibration.csv}
"""
WARNING = ("Every parameter of A is fixed: the problem trusts it as its reference, and "
           "this candidate says the reference itself reads wrong.")


def test_a_term_on_the_reference_says_so(tmp_path) -> None:
    (tmp_path / "cell.yaml").write_text(CELL)
    (tmp_path / "problem.yaml").write_text(PROBLEM)
    rng = np.random.default_rng(7)
    force = np.tile(np.linspace(0, 5, 200), 6)           # kN, six load cycles
    n = force.size
    columns = {"t": 2.0 * np.arange(n),
               "rA": 0.012 + 0.40012 * force + rng.normal(0, 0.0002, n),
               "rB": -0.0083 + 0.3987 * force + rng.normal(0, 0.0005, n),
               "rC": 0.0215 + 0.4021 * force + 1e-3 * force**2 + rng.normal(0, 0.0005, n)}
    data = {"calibration": make_dataset("calibration", "test", columns, [])}
    diag = symcal.diagnose(symcal.solve(tmp_path / "problem.yaml", data))
    texts = {c.label: diag.candidate_text(c) for c in diag.significant}
    on_c = "C.F += a quadratic dependence on rC"
    assert next(iter(texts)) == on_c and WARNING not in texts[on_c]
    on_a = [label for label in texts if label.startswith("A.F += ")]
    assert on_a and all(WARNING in texts[label] for label in on_a), texts


def test_freeing_the_references_fixed_parameter_says_so(tmp_path) -> None:
    """Flow meters in series, the Coriolis meter the reference (its zero fixed), the
    density law trusted (no constant tested): with the turbine's K-factor growing with
    the temperature, the diagnosis's lead was the Coriolis zero freed, which said nothing
    of its being the reference (a new user applied it: the zero came out at 145 % of the
    mean flow).  It now says so, and a calibrated sensor's member leads its group; the
    turbine's product with the temperature says nothing of a reference."""
    from conftest import ROOT

    from symcal.simulation import load_scenario, simulate_run

    flow = ROOT / "tests" / "data" / "flow"
    (tmp_path / "problem-nc.yaml").write_text(
        f"problem: flow_pair_nc\nextends: {(flow / 'problem.yaml').as_posix()}\n"
        "candidates:\n  constants: false\n")
    scenario = load_scenario(flow / "scenario.yaml").overlay(
        {"effects": {"ktemp": {"on": True}}})
    data = {name: make_dataset(name, "simulated", simulate_run(scenario, name, 1), [])
            for name in ("calibration", "validation")}
    diag = symcal.diagnose(symcal.solve(tmp_path / "problem-nc.yaml", data))
    zero = next(c for c in diag.candidates
                if c.label.startswith("the fixed parameter cor.zero"))
    assert zero.significant
    assert ("Every parameter of cor is fixed: the problem trusts it as its reference, and "
            "this candidate says the reference itself reads wrong.") in \
        diag.candidate_text(zero)
    # it no longer leads its group: a calibrated sensor's member does
    lead = next(c for c in diag.significant if zero.label in c.indistinguishable)
    assert lead.output.startswith("tur.") and lead is diag.significant[0]
    product = next(c for c in diag.significant
                   if c.label == "tur.Qv += the product of f_tur and T")
    assert "Every parameter of" not in diag.candidate_text(product)


BENCH = """problem: bench
columns:
  t: {unit: s, role: time}
  v_sh: {unit: mV, noise: 0.01 mV}
  v_hall: {unit: V, noise: 0.005 V}
  T: {unit: delta_degC, role: state, noise: 0.05 delta_degC}
instances:
  sh: {model: shunt.yaml, inputs: {v: v_sh, T: T}}
  hall: {model: hall.yaml, inputs: {v: v_hall}}
constraints:
  g: {expr: sh.I - hall.I, unit: A}
datasets:
  calibration: {path: calibration.csv}
"""


def write_bench(folder: Path) -> None:
    """The shunt and Hall sensor of tests/data/hall and ``BENCH`` (one calibration CSV,
    no held-out data) into ``folder``."""
    models = ROOT / "tests" / "data" / "hall" / "models"
    for name in ("shunt.yaml", "hall.yaml"):
        (folder / name).write_text((models / name).read_text())
    (folder / "bench.yaml").write_text(BENCH)


def test_a_calibrated_sensors_term_leads_before_the_references_own_input(tmp_path) -> None:
    """A shunt (the reference, its resistance's temperature its own input) and a Hall
    sensor in series; the Hall sensor's offset drifts with the temperature.  A term
    linear in T on the shunt is the same fit, and it led the group as a term in the
    shunt's own input: a new user applying it got a Hall model with no temperature
    compensation.  The calibrated sensor's member leads now."""
    write_bench(tmp_path)
    rng = np.random.default_rng(11)
    n = 3000
    t = np.arange(n, dtype=float)
    current = 50.0 * np.sin(2 * np.pi * t / 400.0)
    temp = 32.5 - 12.5 * np.cos(2 * np.pi * t / n)
    columns = {"t": t, "T": temp + rng.normal(0, 0.05, n),
               "v_sh": current * (1 + 5e-5 * (temp - 25)) + rng.normal(0, 0.01, n),
               "v_hall": 2.5 + 0.0398 * current + 4e-4 * (temp - 25)
               + rng.normal(0, 0.005, n)}
    data = {"calibration": make_dataset("calibration", "test", columns, [])}
    diag = symcal.diagnose(symcal.solve(tmp_path / "bench.yaml", data))
    lead = diag.significant[0]
    assert lead.label == "hall.I += a term linear in T", lead.label
    assert "sh.I += a term linear in T" in lead.indistinguishable
