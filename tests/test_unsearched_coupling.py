"""What is left points at another sensor's reading that no search space holds: a
crosstalk from a current channel's reading into a voltage channel's (a new user's DC
power bench: ``v_raw += 0.2 mV/A * I``).  The loop ended honestly not quiet, but only
named ``i_raw`` under "what is left"; nothing said that a coupling into the voltage
channel is never tested by default, nor how to test it.  Now it says so, and the
sentence applied literally ends at the floor with every parameter within 3 SE."""

from __future__ import annotations

import pytest
from conftest import ROOT

import symcal
from symcal.data.dataset import make_dataset
from symcal.report.text import diagnosis_report
from symcal.simulation import load_scenario, simulate_run, truth

BENCH = ROOT / "tests" / "data" / "power_bench"
SAID = ("i_raw, along which what is left of g_P, g_V lies most, is read by ich and is in "
        "no search space of vch: a coupling of it into that sensor is not tested; to test "
        "one, name i_raw in vch's `candidates: variables` beside its own readings (the "
        "list replaces the default)")


def _data(seed: int) -> tuple[dict, dict]:
    scenario = load_scenario(BENCH / "scenario.yaml").overlay(
        {"effects": {"crosstalk": {"on": True}}})
    data = {name: make_dataset(name, "simulated", simulate_run(scenario, name, seed), [])
            for name in ("calibration", "validation")}
    return data, truth(scenario)["parameters"]


def test_the_diagnosis_says_how_to_test_a_coupling_no_space_holds() -> None:
    data, _ = _data(2)
    diag = symcal.diagnose(symcal.solve(BENCH / "problem.yaml", data))
    assert not diag.significant
    assert diag.unsearched == (SAID,), diag.unsearched
    assert SAID in diagnosis_report(diag)


@pytest.mark.slow
def test_applied_literally_the_loop_reaches_the_floor(tmp_path) -> None:
    data, true = _data(5)
    (tmp_path / "problem_xt.yaml").write_text(
        "problem: power_bench_xt\n"
        f"extends: {BENCH / 'problem.yaml'}\n"
        "instances:\n"
        "  vch:\n"
        "    candidates: {variables: [v_raw, i_raw, T, t]}\n")
    out = symcal.improve(tmp_path / "problem_xt.yaml", tmp_path / "out", data, max_rounds=2)
    assert out.quiet and out.at_floor
    assert [r.added for r in out.rounds[1:]] == ["vch.V += a term linear in i_raw"]
    final = out.rounds[-1].result
    for name in ("vch.off_v", "vch.k_v", "ich.off_i", "ich.g_i"):
        p = final.params[name]
        assert abs(p.value - true[name]) < 3 * p.se, (name, p.value, p.se, true[name])
