"""A coupling of another sensor's reading that no search space holds: a crosstalk from a
current channel's reading into a voltage channel's (a new user's DC power bench:
``v_raw += c * I``).  By default a sensor's candidates use its own readings, so the
coupling was never tested: at 0.2 mV/A the loop ended honestly not quiet, but only named
``i_raw`` under "what is left"; at 0.002 mV/A it ended quiet at the floor on 2 of 6
seeds with the voltage offset 7.8-8.8 SE off.  The couplings outside every search space
are now tested as a family of their own where nothing in the spaces is significant: the
diagnosis and the loop name the term and the exact ``candidates:`` line that tests it,
and that line applied literally ends at the floor with every parameter within 3 SE.
Where the user declared the sensor's variables (so the family does not test them), what
is left still says how to test a coupling it points at."""

from __future__ import annotations

import re

import pytest
from conftest import ROOT

import symcal
from symcal.data.dataset import make_dataset
from symcal.report.text import diagnosis_report, outcome_text
from symcal.simulation import load_scenario, simulate_run, truth

BENCH = ROOT / "tests" / "data" / "power_bench"
LABEL = "vch.V += a term linear in i_raw"
LINE = "candidates: {variables: [v_raw, t, T, i_raw]}"
SAID = ("i_raw, along which what is left of g_P, g_V lies most, is read by ich and is in "
        "no search space of vch: a coupling of it into that sensor is not tested; to test "
        "one, name i_raw in vch's `candidates: variables` beside its own readings (the "
        "list replaces the default)")
PHYSICAL = ("vch.off_v", "vch.k_v", "ich.off_i", "ich.g_i")


def _overlay(folder, name: str, line: str):
    """A problem that extends the bench's with ``line`` on the instance vch."""
    path = folder / f"{name}.yaml"
    path.write_text(f"problem: power_bench_{name}\n"
                    f"extends: {BENCH / 'problem.yaml'}\n"
                    f"instances:\n  vch: {{{line}}}\n")
    return path


def _data(seed: int, coupling: float = 0.2) -> tuple[dict, dict]:
    scenario = load_scenario(BENCH / "scenario.yaml").overlay(
        {"effects": {"crosstalk": {"on": True, "values": {
            "xt.c": {"value": coupling, "unit": "mV/A"}}}}})
    data = {name: make_dataset(name, "simulated", simulate_run(scenario, name, seed), [])
            for name in ("calibration", "validation")}
    return data, truth(scenario)["parameters"]


def test_the_diagnosis_tests_a_coupling_no_space_holds() -> None:
    data, _ = _data(2)
    diag = symcal.diagnose(symcal.solve(BENCH / "problem.yaml", data))
    assert not diag.significant
    assert [c.label for c in diag.outside] == [LABEL]
    assert diag.outside[0].p_value < diag.alpha / 4     # at most four couplings tested
    assert diag.unsearched == ()        # tested, so not called untested
    text = diagnosis_report(diag)
    assert "what to add: nothing of the search spaces; outside them: " + LABEL in text
    assert f"add `{LINE}` to the instance vch in the problem file" in text


def test_a_declared_space_still_says_how_to_test_what_is_left(tmp_path) -> None:
    """The user declared vch's variables without i_raw: the outside family leaves that
    sensor to its declaration, and what is left names the coupling as before."""
    data, _ = _data(2)
    declared = _overlay(tmp_path, "declared", "candidates: {variables: [v_raw, T, t]}")
    diag = symcal.diagnose(symcal.solve(declared, data))
    assert diag.outside == ()
    assert diag.unsearched == (SAID,), diag.unsearched


@pytest.mark.slow
def test_a_weak_coupling_is_not_called_quiet_and_the_printed_line_fixes_it(tmp_path) -> None:
    """0.002 mV/A, seed 2: the loop used to end quiet at the floor with vch.off_v 8.8 SE
    off.  Now it is not quiet and prints the line; written into the problem as printed,
    the loop keeps the coupling and ends quiet at the floor, every parameter within 3 SE
    (vch.off_v measured 2.4 SE)."""
    data, true = _data(2, 0.002)
    out = symcal.improve(BENCH / "problem.yaml", tmp_path / "before", data, max_rounds=2)
    assert out.at_floor and not out.quiet
    assert [c.label for c in out.last.outside] == [LABEL]
    said = outcome_text(out)
    assert said.startswith("the diagnosis is not quiet: no candidate of the search spaces "
                           "is significant, but a coupling outside them is: " + LABEL)
    assert out.to_dict()["outside"][0]["label"] == LABEL
    line = re.search(r"add `(candidates: \{[^`]*\})` to the instance vch", said)
    assert line is not None and line.group(1) == LINE
    _reaches_the_floor(_overlay(tmp_path, "xt", line.group(1)), tmp_path / "after", data,
                       true)


def _reaches_the_floor(problem, out, data: dict, true: dict) -> None:
    """The loop on ``problem`` keeps the coupling and ends quiet at the floor with every
    physical parameter within 3 SE of the truth."""
    done = symcal.improve(problem, out, data, max_rounds=2)
    assert done.quiet and done.at_floor
    assert [r.added for r in done.rounds[1:]] == [LABEL]
    final = done.rounds[-1].result
    for name in PHYSICAL:
        p = final.params[name]
        assert abs(p.value - true[name]) < 3 * p.se, (name, p.value, p.se, true[name])


@pytest.mark.slow
def test_applied_literally_the_loop_reaches_the_floor(tmp_path) -> None:
    data, true = _data(5)
    _reaches_the_floor(_overlay(tmp_path, "xt", LINE), tmp_path / "out", data, true)


def test_clean_data_raise_no_outside_coupling() -> None:
    """False alarms of the outside family on clean data: none on seeds 100-159 (measured;
    the level is 1 % family-wise); here ten seeds."""
    scenario = load_scenario(BENCH / "scenario.yaml")
    alarms = 0
    for seed in range(100, 110):
        data = {k: make_dataset(k, "simulated", simulate_run(scenario, k, seed), [])
                for k in ("calibration", "validation")}
        diag = symcal.diagnose(symcal.solve(BENCH / "problem.yaml", data), report=False)
        alarms += bool(diag.outside)
    assert alarms <= 1


def test_a_coupling_is_offered_only_into_a_sensor_the_residual_reads(tmp_path) -> None:
    """A new user's manifold: what was left of g_B (B against the reference) lay along B's
    own reading, and the diagnosis asked to name it in A's candidates, a sensor g_B does
    not read (applied, nothing changed).  A coupling is now offered only into a sensor
    whose outputs the residual reads."""
    from types import SimpleNamespace

    from symcal.revise.diagnose import unsearched
    from symcal.revise.library import spaces

    problem = symcal.load_problem(
        _overlay(tmp_path, "declared", "candidates: {variables: [v_raw, T, t]}"))
    found = spaces(problem)
    view = SimpleNamespace(dataset="calibration", name="g_P",
                           left=(SimpleNamespace(variables=("i_raw",)),))
    said = unsearched(problem, found, [view], set(), {("calibration", "g_P"): {"vch", "ich"}})
    assert len(said) == 1 and said[0].startswith("i_raw, along which what is left of g_P")
    assert unsearched(problem, found, [view], set(), {("calibration", "g_P"): {"ich"}}) == ()
