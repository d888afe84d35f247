"""A delay the data put below zero is said to be the other readings lagging: no sensor
reads ahead (a new user's flow pair kept the Coriolis meter, the reference, 0.2 s early
where the turbine was 0.2 s late, and said nothing of it)."""

from __future__ import annotations

from conftest import ROOT

import symcal
from symcal.data.dataset import make_dataset
from symcal.simulation import load_scenario, simulate_run

FLOW = ROOT / "tests" / "data" / "flow"


def test_a_negative_delay_is_said_to_be_the_other_sensor_lagging(tmp_path) -> None:
    """The turbine's pulse rate is 0.2 s late; on this draw the loop keeps the Coriolis
    meter's delay instead, -0.2 s (the reference reading ahead: one fit, to first order,
    with a better BIC here), and said nothing of it.  The round now says that no sensor
    reads ahead and that it is the other readings lagging."""
    scenario = load_scenario(FLOW / "scenario_lag.yaml")
    data = {name: make_dataset(name, "simulated", simulate_run(scenario, name, 3), [])
            for name in ("calibration", "validation")}
    result = symcal.improve(FLOW / "problem.yaml", tmp_path / "out", data, max_rounds=2)
    kept = result.rounds[1]
    name = next(n for n in kept.result.params if n.startswith("tau_"))
    tau = kept.result.params[name]
    assert abs(abs(tau.value) - 0.2) < 3 * tau.se
    if tau.value < 0:
        assert any(note.startswith(f"cor's delay {name} is negative: its readings come ")
                   and "the other readings of its constraints lagging by" in note
                   for note in kept.notes()), kept.notes()
    else:
        assert not any("is negative" in note for note in kept.notes())
    assert tau.value < 0      # the draw the new user met
