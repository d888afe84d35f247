"""A new user's wind mast (``tests/data/mast``: a cup anemometer, a Pitot-static tube
whose air density comes from a barometer and a thermometer, a sonic anemometer; their
scenario and hidden effects).

The Pitot's coefficient grows at low speed (a Reynolds-number effect, ``C(1 + 0.03
m/s / V)``): to first order the reference reads 0.03 m/s low.  The loop kept a term on
the sonic that the data could not tell from one on the Pitot (BIC 198.6 and 198.1), said
so in the round, and ended "quiet: every dataset is at its noise floor", exit 0, with
the cup's offset 20 SE and the sonic's gain 41 SE off: the held-out run carries the same
offset and cannot decide.  It now ends saying the data do not decide the model, exit 1.
"""

from __future__ import annotations

import pytest
from conftest import ROOT, simulated, with_effect

import symcal
from symcal.report.text import outcome_text
from symcal.simulation import load_scenario

MAST = ROOT / "tests" / "data" / "mast"


@pytest.mark.slow
def test_a_choice_the_data_do_not_make_is_not_called_done(tmp_path) -> None:
    scenario = with_effect(MAST, "reynolds")
    data = simulated(scenario, 1)
    done = symcal.improve(MAST / "problem.yaml", tmp_path / "out", data, max_rounds=3)
    assert done.quiet and done.at_floor and not done.unverified   # a held-out run checked it
    assert not done.verified and done.undecided
    assert any("cup.b = " in s and "pitot.v += " in s for s in done.undecided)
    text = outcome_text(done)
    assert text.startswith("the diagnosis is quiet, but the data do not decide the model: "
                           "the data cannot tell ")
    assert done.to_dict()["verified"] is False


def test_clean_data_are_verified(tmp_path) -> None:
    data = simulated(load_scenario(MAST / "scenario.yaml"), 2)
    done = symcal.improve(MAST / "problem.yaml", tmp_path / "out", data, max_rounds=2)
    assert done.verified and done.undecided == () and done.unverified == ()
