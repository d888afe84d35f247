"""A reading's zero as a candidate: a data column the sensors read with a constant offset
(a transducer's or an ADC channel's zero that has moved).

An NTC thermistor in a divider (``tests/data/divider``) whose voltage channel reads 3 mV
high: the model has no offset of its own and the voltage reaches the temperature through
``R = Rf·Vth/(Vs − Vth)`` and a logarithm, so no term on the output stands in for it.
Before the candidate the loop kept four stand-ins (a cubic, a quadratic and a line in the
supply, a power), stopped at its round limit, and left R25 22 standard errors off.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from conftest import ROOT, divider_data

import symcal
from symcal.analysis.discovery import Basis, Candidate
from symcal.base.units import DISPLAY_UNITS
from symcal.language import expr
from symcal.language.problem_file import load_problem_spec
from symcal.problem.readings import bare_column
from symcal.revise.effects import revision
from symcal.revise.library import direct_columns

DIVIDER = ROOT / "tests" / "data" / "divider"
ZERO = "the zero of Vth (read by th) is off"


@pytest.mark.slow
@pytest.mark.parametrize(("seed", "zero"), [(1, 3e-3), (2, -2e-3)])
def test_a_voltage_channels_zero_is_found_in_the_first_round(tmp_path, seed, zero) -> None:
    """The loop keeps the zero in its first round, verified on the held-out run; R25 and
    β within 3 standard errors of the truth, the zero's parameter minus the offset."""
    data = divider_data(seed, zero=zero)
    done = symcal.improve(DIVIDER / "problem.yaml", tmp_path / "out", data, max_rounds=3)
    assert [r.added for r in done.rounds[1:]] == [ZERO]
    assert done.verified and done.quiet
    final = symcal.solve(done.final_problem, data)
    for name, true in (("th.R25", 10.03), ("th.beta", 3935.0), ("zero_Vth", -zero)):
        p = final.params[name]
        assert p.se is not None and abs(p.value - true) < 3 * p.se, (name, p.value, p.se)
    assert final.params["zero_Vth"].unit == "V"


def test_the_diagnosis_names_the_zero_and_its_size() -> None:
    """The first candidate, and its words: how far the readings are off, in the column's
    unit (3 mV high here)."""
    result = symcal.solve(DIVIDER / "problem.yaml", divider_data(1, zero=3e-3))
    diag = symcal.diagnose(result)
    lead = diag.candidates[0]
    assert lead.label == ZERO and lead.significant
    assert lead.basis.targets == ("th",) and lead.basis.unit == "V"
    volt = DISPLAY_UNITS["V"]                        # internal units per volt
    offset, se = -lead.coefficient[0] / volt, lead.coefficient_se[0] / volt
    assert abs(offset - 3e-3) < 3 * se, (offset, se)
    from symcal.report.text import diagnosis_report

    text = diagnosis_report(diag)
    assert f"{ZERO[0].upper()}{ZERO[1:]}: the data say its readings are +0.00" in text


def test_clean_data_name_no_zero() -> None:
    """Without an offset no zero is significant (nor anything else here)."""
    diag = symcal.diagnose(symcal.solve(DIVIDER / "problem.yaml", divider_data(4)))
    zeros = [c for c in diag.candidates if c.basis.kind == "zero"]
    assert zeros and not any(c.significant for c in zeros)


def test_the_revision_reads_the_column_plus_its_zero_and_keeps_its_noise() -> None:
    """Every sensor that reads the column reads ``Vth + zero_Vth``; the input keeps the
    column's declared noise (a column plus exact terms is still a reading of the column)."""
    problem = symcal.load_problem(DIVIDER / "problem.yaml")
    basis = Basis("zero", "Vth", ZERO, ("zero",), (), unit="V", scales=(1e-4,),
                  targets=("th",))
    rev = revision(problem, Candidate("", basis))
    assert rev.sections["instances"] == {"th": {"inputs": {"Vth": "Vth + zero_Vth"}}}
    assert rev.sections["parameters"]["zero_Vth"]["unit"] == "V"
    system = load_problem_spec(DIVIDER / "problem.yaml").system
    assert bare_column(system, expr.parse("Vth + zero_Vth")) is None   # not a parameter here
    assert bare_column(system, expr.parse("Vth + 0.002")) == "Vth"
    assert bare_column(system, expr.parse("Vth + Vs")) is None
    assert bare_column(system, expr.parse("Vth*2 + 1")) is None


def test_a_column_a_constraint_reads_itself_is_not_offered(tmp_path) -> None:
    """The revision adds the zero where the sensors read the column: a column a
    constraint reads by name would be left as it is, so it is not a candidate."""
    text = (DIVIDER / "problem.yaml").read_text()
    text = text.replace("g: {expr: th.T - ref.T, unit: K}", "g: {expr: th.T - Tr, unit: K}")
    text = text.replace("  ref: {model: models/ref.yaml, inputs: {Tr: Tr}}\n", "")
    (tmp_path / "models").mkdir()
    for f in (DIVIDER / "models").iterdir():
        (tmp_path / "models" / f.name).write_text(f.read_text())
    (tmp_path / "problem.yaml").write_text(text)
    problem = symcal.load_problem(tmp_path / "problem.yaml")
    assert direct_columns(problem) == {"Tr"}
    diag = symcal.diagnose(symcal.solve(problem, divider_data(1, zero=3e-3)))
    zeros = {c.basis.variable for c in diag.candidates if c.basis.kind == "zero"}
    assert zeros == {"Vth", "Vs"}
    assert np.isfinite(diag.candidates[0].f_stat)


def test_not_offered_where_the_sensor_has_an_offset_of_its_own() -> None:
    """The oven (``tests/data/oven``): the thermocouple's channel has a free offset ``o``
    (its calibration absorbs the EMF's zero) and the connector thermistor a fixed one
    (``cj.off``: "the fixed parameter cj.off is off" is the same candidate, named as the
    model names it); the RTD's resistance and the pyrometer's reading have none."""
    diag = symcal.diagnose(symcal.solve(ROOT / "tests" / "data" / "oven" / "problem.yaml"))
    zeros = {c.basis.variable for c in diag.candidates if c.basis.kind == "zero"}
    assert zeros == {"R_rtd", "T_pyr"}
    offsets = {p.name: p.fixed for p in diag.result.problem.parameters
               if p.name in ("tc.o", "cj.off")}
    assert offsets == {"tc.o": False, "cj.off": True}


def test_a_trusted_references_zero_is_not_something_the_floor_cannot_vouch_for() -> None:
    """The bath's reference thermometer (no free parameter) reads Tr: its zero is tested
    (a significant one would say the reference reads wrong) but, below the test, is not
    "what the floor cannot vouch for": the problem trusts its zero as it trusts its gain
    (it said "th.R25 (up to 779 SE)" on every clean run)."""
    from symcal.report.text import unvouched

    diag = symcal.diagnose(symcal.solve(DIVIDER / "problem.yaml", divider_data(4)))
    ref = [c for c in diag.candidates if c.label == "the zero of Tr (read by ref) is off"]
    assert ref and not ref[0].significant and not ref[0].absorbed
    assert not ref[0].unseen and unvouched(diag) == []


def test_not_offered_where_a_constant_of_the_sensor_is_that_zero() -> None:
    """A thermistor's lead resistance in series with the part (its model's constant
    ``r_lead``) is the zero of its resistance reading: "th2's resistance of the leads ...
    is off" is the candidate, named as the model names it, not the zero of R2 beside it
    (which the loop kept on one acceptance seed in its place)."""
    from conftest import simulated

    from symcal.simulation import load_scenario

    root = ROOT / "tests" / "acceptance" / "thermistor_bath"
    problem = symcal.load_problem(root / "problem.yaml")
    data = simulated(load_scenario(root / "scenario_lead.yaml"), 1001,
                     tuple(problem.datasets))
    diag = symcal.diagnose(symcal.solve(problem, data))
    assert diag.candidates[0].basis.kind == "constant"
    assert diag.candidates[0].basis.targets == ("th2.r_lead",)
    assert not [c for c in diag.candidates if c.basis.kind == "zero"]


def test_the_datasheet_example_fits_the_centres_unit() -> None:
    """A new user's orifice rig: the advice to have the parameters hold at a datasheet's
    reference offered "25 degC, say" for a centre in kPa."""
    from symcal.revise.watch import Watch

    watch = Watch(centres=(("orf.c_quad_dp", "dp", 13.46, "kPa"),
                           ("mag.c_gain_T", "T_w", 22.5, "delta_degC")))
    pressure, temperature = watch.words("a term")
    assert "to have them hold at one, write" in pressure and "degC" not in pressure
    assert "to have them hold at one (25 °C, say), write" in temperature



def test_a_terms_centre_tested_as_a_constant_is_labelled_as_one(tmp_path) -> None:
    """The constant a centred term brings (its doc :data:`CENTRE_DOC`) is named as the
    centre of that term, not by its doc string (the orifice rig: "orf's reference dp of
    the other parameters (the term is zero there; ...) c_quad_dp is off")."""
    from symcal.revise.effects import CENTRE_DOC

    shutil.copytree(DIVIDER, tmp_path / "d")
    model = tmp_path / "d" / "models" / "ntc.yaml"
    text = model.read_text()
    text = text.replace("  T25: {value: 298.15, unit: K}\n", "  T25: {value: 298.15, unit: K}\n"
                        f"  c_lin_Vs: {{value: 3.2, unit: V, doc: '{CENTRE_DOC.format('Vs')}'}}\n")
    text = text.replace("  beta: {value: 3950, unit: K, scale: 1}\n",
                        "  beta: {value: 3950, unit: K, scale: 1}\n"
                        "  lin_Vs: {value: 0, unit: K/V, scale: 0.01}\n")
    text = text.replace("log(R/R25)/beta), unit: K}",
                        "log(R/R25)/beta) + lin_Vs*(Vs - c_lin_Vs), unit: K}")
    model.write_text(text)
    diag = symcal.diagnose(symcal.solve(tmp_path / "d" / "problem.yaml", divider_data(4)))
    labels = [c.label for c in diag.candidates if c.basis.kind == "constant"]
    assert "th's c_lin_Vs, the centre of its term in Vs, is off" in labels


def test_a_zero_kept_is_not_offered_again(tmp_path) -> None:
    """Once kept, the zero is the problem's parameter ``zero_Vth`` that the sensor's input
    reads: the candidate is not offered again (it was, absorbed, "would bias zero_Vth")."""
    done = symcal.improve(DIVIDER / "problem.yaml", tmp_path / "out",
                          divider_data(1, zero=3e-3), max_rounds=1)
    assert [r.added for r in done.rounds[1:]] == [ZERO]
    assert not [c for c in done.last.candidates if c.basis.variable == "Vth"
                and c.basis.kind == "zero"]


def test_untested_couplings_come_after_a_lead_that_explains_most() -> None:
    """What is left lies along every variable that moves with the effect: the lines
    naming couplings no search space holds say that the leading candidate, which removes
    most of what the constraints cannot yet explain, comes first (a new user's orifice rig
    was pointed at couplings of the reference's flow while its pressure's zero took 97 %)."""
    diag = symcal.diagnose(symcal.solve(DIVIDER / "problem.yaml",
                                        divider_data(1, zero=3e-3)))
    assert diag.unsearched
    assert all(line.endswith(f"(first add the leading candidate, {ZERO}: it removes 97% of "
                             "what the constraints cannot yet explain, and what is left "
                             "here may go with it)") for line in diag.unsearched)
    clean = symcal.diagnose(symcal.solve(DIVIDER / "problem.yaml", divider_data(4)))
    assert not any("first add" in line for line in clean.unsearched)


def test_a_dimensionless_readings_detectable_zero_is_a_plain_number() -> None:
    """A zero of a column without a unit (a ratio) is shown as the number it is, as a
    dimensionless constant's is, not with a unit symbol after it."""
    from symcal.report.text import detectable_text

    cand = Candidate("", Basis("zero", "ratio", "the zero of ratio (read by r) is off",
                               ("zero",), (), unit="", targets=("r",)))
    cand.mde = 0.00125
    assert detectable_text(None, cand) == "0.00125"
