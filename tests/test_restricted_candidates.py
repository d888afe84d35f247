"""A revision of a problem whose ``candidates:`` lists the constants (or fixed
parameters) the search may test: the constant it makes a parameter (the parameter it
frees) leaves the list, which the overlay restates.  A new user's oven, which listed
its constants as the docs advise (leaving out 273.15 K), stopped ``symcal improve`` on an
internal error when the loop freed the pyrometer's emissivity: "symcal wrote a revision
it cannot read (... candidates.constants.5: 'pyr.eps' matches no constant ...)"."""

from __future__ import annotations

from conftest import ROOT

import symcal
from symcal.data.dataset import make_dataset
from symcal.revise.effects import write_revision
from symcal.simulation import load_scenario, simulate_run

ALTIMETER = ROOT / "tests" / "data" / "altimeter"


def _data() -> dict:
    sc = load_scenario(ALTIMETER / "scenario.yaml")
    return {k: make_dataset(k, "simulated", simulate_run(sc, k, 1), [])
            for k in ("calibration", "validation")}


def test_a_constant_made_a_parameter_leaves_the_listed_constants(tmp_path) -> None:
    listed = tmp_path / "listed.yaml"
    listed.write_text(f"problem: listed\nextends: {(ALTIMETER / 'problem.yaml').as_posix()}\n"
                      "candidates: {constants: [Rd, p0], fixed: [gnss.bias]}\n")
    result = symcal.solve(listed, _data())
    assert result.problem.candidates.constants == ("p0", "Rd")
    diag = symcal.diagnose(result, report=False)
    rd = next(c for c in diag.candidates if c.basis.kind == "constant"
              and c.basis.targets == ("Rd",))
    revised = symcal.load_problem(write_revision(result.problem, rd, tmp_path, "rd"))
    assert "Rd" in revised.parameter_names
    assert revised.candidates.constants == ("p0",)
    assert revised.candidates.fixed == ("gnss.bias",)
    freed = next(c for c in diag.candidates if c.basis.kind == "fixed")
    assert freed.basis.targets == ("gnss.bias",)
    unfixed = symcal.load_problem(write_revision(result.problem, freed, tmp_path, "bias"))
    assert unfixed.candidates.fixed == ()
    assert unfixed.candidates.constants == ("p0", "Rd")
    assert symcal.solve(unfixed, result.data).success


def test_a_zero_that_sets_a_gauge_is_named_as_a_claim_or_a_definition() -> None:
    """Two thermometers in one bath, the first's offset fixed at 0 K: the second's
    offset is only as right as that zero.  A zero was skipped as "a definition" (a
    frame's origin); a new user's thermocouple offset ended 97 SE off, quiet, where the
    connector thermistor it shared a gauge with, fixed at 0 K, read 0.8 K high."""
    from symcal.report.text import declared_gauges_line

    diag = symcal.diagnose(symcal.solve(ROOT / "tests" / "data" / "bath" / "problem.yaml"),
                           report=False)
    assert set(diag.gauge_fixes) == {"s1.a", "s1.b"}
    assert declared_gauges_line(diag) == (
        "the estimates are only as right as the declared values the data cannot check: "
        "s1.b = 1 (fixed, it sets a gauge: the parameters that share it follow its value "
        "unseen); s1.a = 0 K (fixed at zero, it sets a gauge: a definition where it orients "
        "or places a frame, else a sensor's zero the data cannot check)")
