"""A cubic dependence: odd about the data's centre (an amplifier's S-curve about
mid-scale).  Neither the gain nor a quadratic takes it, and before the library had the
shape, the power bench's current amplifier with a 1 mV S-curve at the ends of its range
(ten times the channel's noise) ended "not there yet: structure remains that no
candidate explains", 45 % of the excess along i_raw, the physicist's next term never
offered.  Now the diagnosis names it, and the loop keeps it and ends at the floor with
the channel's gain and offset at the truth."""

from __future__ import annotations

import pytest
import yaml
from conftest import ROOT

import symcal
from symcal.base.units import DISPLAY_UNITS
from symcal.data.dataset import make_dataset
from symcal.simulation import load_scenario, simulate_run, truth

BENCH = ROOT / "tests" / "data" / "power_bench"
CUBIC = "ich.I += a cubic dependence on i_raw"
QUADRATIC = "ich.I += a quadratic dependence on i_raw"
#: The S-curve: 1e-9 mV/mV³ about 1000 mV, 1 mV at the ends of the 0-2000 mV range.
S_CURVE = {"amp_s": {"doc": "current amplifier S-curve about mid-scale",
                     "values": {"amp.c3": {"value": 1.0e-9, "unit": "1/mV**2"},
                                "amp.mid": {"value": 1000, "unit": "mV"}},
                     "add": {"i_raw": "amp.c3*(ich.g_i*I - amp.mid)**3"}}}


def _data(seed: int, effects: dict) -> tuple[dict, dict]:
    scenario = load_scenario(BENCH / "scenario.yaml").overlay({"effects": effects})
    data = {k: make_dataset(k, "simulated", simulate_run(scenario, k, seed), [])
            for k in ("calibration", "validation")}
    return data, truth(scenario)["parameters"]


def test_the_diagnosis_names_an_s_curve_the_library_had_no_shape_for() -> None:
    data, _ = _data(2, S_CURVE)
    diag = symcal.diagnose(symcal.solve(BENCH / "problem.yaml", data), report=False)
    assert [c.label for c in diag.significant][:1] == [CUBIC]
    cubic = diag.significant[0]
    # the linear part is the gain already: the term is the cube alone, about the centre
    assert cubic.basis.columns == ("cub",)
    assert cubic.basis.terms == ("({v} - {centre})**3",)
    centre = cubic.basis.centre / DISPLAY_UNITS["mV"]       # the data's centre
    assert 900 < centre < 1100, centre


def test_a_quadratic_is_still_a_quadratic() -> None:
    """The even curve leads with the quadratic: the cubic (odd) does not take its place."""
    data, _ = _data(2, {"amp_quadratic": {"on": True}})
    diag = symcal.diagnose(symcal.solve(BENCH / "problem.yaml", data), report=False)
    labels = [c.label for c in diag.significant]
    assert labels[:1] == [QUADRATIC], labels
    assert CUBIC not in labels


@pytest.mark.slow
@pytest.mark.parametrize("seed", [3, 7])
def test_the_loop_keeps_the_cubic_and_ends_at_the_floor(tmp_path, seed: int) -> None:
    """The revision as written (the cube about the data's centre; the gain the slope
    there): the channel's gain and offset within 3 SE of the truth, whose S-curve is
    centred at 1000 mV, not at the data's centre (the difference is a 10⁻⁵ mV
    quadratic)."""
    data, true = _data(seed, S_CURVE)
    done = symcal.improve(BENCH / "problem.yaml", tmp_path / "out", data, max_rounds=3)
    assert done.quiet and done.at_floor
    assert [r.added for r in done.rounds[1:]] == [CUBIC]
    final = done.rounds[-1].result
    for name in ("ich.g_i", "ich.off_i", "vch.k_v", "vch.off_v"):
        p = final.params[name]
        assert abs(p.value - true[name]) < 3 * p.se, (name, p.value, p.se, true[name])
    model = yaml.safe_load((tmp_path / "out" / "models" / "ichan_I_cub_i_raw.yaml").read_text())
    assert model["outputs"]["I"] == "base.I + cub_i_raw*(i_raw - c_cub_i_raw)**3"
    assert model["parameters"]["cub_i_raw"]["unit"] == "A/mV^3"
    # I = (i_raw - off)/g: the S-curve on i_raw is -c3/g on I, to its standard error
    cub = final.params["ich.cub_i_raw"]
    assert abs(cub.value - (-1.0e-9 / 99.2)) < 3 * cub.se, (cub.value, cub.se)


def test_a_cube_is_tested_beyond_both_lower_terms_whatever_their_scales(tmp_path) -> None:
    """A crosstalk linear in the current channel's reading (0.002 mV/A, in vch's declared
    space).  The reading is in nV internally: its linear term's column is 10⁹ times
    smaller than its square's, and the basis of the simpler terms dropped it as rounding,
    so the cube was tested beyond the square alone, stood for the linear term (F 93
    against 90) and was kept in its place.  Each simpler column is now normalised first."""
    scenario = load_scenario(BENCH / "scenario.yaml").overlay(
        {"effects": {"crosstalk": {"on": True, "values": {
            "xt.c": {"value": 0.002, "unit": "mV/A"}}}}})
    data = {k: make_dataset(k, "simulated", simulate_run(scenario, k, 2), [])
            for k in ("calibration", "validation")}
    path = tmp_path / "xt.yaml"
    path.write_text(f"problem: power_bench_xt\nextends: {BENCH / 'problem.yaml'}\n"
                    "instances:\n  vch: {candidates: {variables: [v_raw, t, T, i_raw]}}\n")
    diag = symcal.diagnose(symcal.solve(path, data), report=False)
    assert [c.label for c in diag.significant] == ["vch.V += a term linear in i_raw"]
    cube = next(c for c in diag.candidates if c.label == "vch.V += a cubic dependence on i_raw")
    assert cube.p_value > 0.01
