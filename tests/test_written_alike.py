"""A term's reach is the smaller of the term as written and beyond its lower orders only
where the two are one term to its test (their difference is what the parameters
absorb).  A new user's flow meters in series: the turbine's K-factor grows with the
temperature, which the density's expansion coefficient ``beta`` absorbs whole; beyond
its linear parts (a temperature's linear part is seen by the test) the product reached
beta by 1.8 SE, as written by 1482.  The loop ended quiet with beta 51 SE off and named
only the turbine's offset as what the floor cannot vouch for."""

from __future__ import annotations

from conftest import ROOT

import symcal
from symcal.data.dataset import make_dataset
from symcal.report.text import unvouched
from symcal.revise.diagnose import diagnose
from symcal.revise.reliability import UNSEEN
from symcal.simulation import load_scenario, simulate_run, truth

FLOW = ROOT / "tests" / "data" / "flow"


def test_an_effect_a_parameter_absorbs_whole_is_named_with_it() -> None:
    scenario = load_scenario(FLOW / "scenario.yaml").overlay(
        {"effects": {"ktemp": {"on": True}}})
    data = {name: make_dataset(name, "simulated", simulate_run(scenario, name, 1), [])
            for name in ("calibration", "validation")}
    result = symcal.solve(FLOW / "problem_beta.yaml", data)
    diag = diagnose(result)
    assert result.at_floor and not diag.significant       # quiet: the floor is reached
    beta = result.params["beta"]
    # K growing by aK per degC is beta growing by aK (first order): beta takes it whole
    expected = truth(scenario)["parameters"]["tur.aK"] + 2.1e-4
    assert abs(beta.value - expected) < 3 * beta.se             # beta absorbed it ...
    off = abs(beta.value - 2.1e-4) / beta.se
    assert off > UNSEEN                                         # ... far off its truth
    reach = dict(unvouched(diag))
    assert reach.get("beta", 0.0) >= off, reach                 # and it is named
    product = next(c for c in diag.candidates
                   if c.label == "tur.Qv += the product of f_tur and T")
    assert dict(product.unseen)["beta"] >= off

