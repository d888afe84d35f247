"""Monte Carlo of the standard errors (issue 22 item 3): with the weights propagated from
the declared noise (the bundled problems' default), 95 % intervals cover the truth 93-97 %
of the time on each bundled problem, on data its model is exact for, and the model is at
its noise floor.

The explicit models evaluate each segment's error at the raw reading: they are exact for a
courier simulated that way (``distortion_at: reading``, small-angle geometry), and biased
on the physical courier (their approximation, which ``symcal improve`` names); the implicit
models are exact on the physical clean courier.  Every interval a result states is
counted: each parameter with a standard error and each identifiable combination.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import ROOT

import symcal
from symcal.data.dataset import make_dataset
from symcal.simulation import load_scenario, simulate_run, truth

PROBLEMS = ROOT / "problems"
#: Seeds per problem: 60 × 33-47 intervals (30 for the implicit dual problem, whose
#: lm solves take most of this test's time); measured coverage below.
SEEDS = 60
Z95 = 1.959964

CASES = [   # problem, scenario, errors at the reading (the explicit model's courier)
    ("platen_self_calibration", "courier_platen_clean", True),
    ("platen_self_calibration_implicit", "courier_platen_clean", False),
    ("dual_sensor_calibration", "courier_dual_clean", True),
    pytest.param("dual_sensor_calibration_implicit", "courier_dual_clean", False,
                 id="dual_implicit_30_seeds"),
]


def _coverage(name: str, scenario_name: str, at_reading: bool
              ) -> tuple[float, int, list, int]:
    problem = symcal.load_problem(PROBLEMS / f"{name}.yaml")
    if at_reading:       # the model's own assumptions: errors at the readings, small angles
        scenario_name = scenario_name.replace("_clean", "") + "_model"
    scenario = load_scenario(PROBLEMS / "scenarios" / f"{scenario_name}.yaml")
    true = dict(truth(scenario)["parameters"])
    if "h" in true:
        true["cs.h"] = true.pop("h")
    inside, total, verdicts, failed = 0, 0, [], 0
    for seed in range(SEEDS // 2 if name == "dual_sensor_calibration_implicit" else SEEDS):
        data = {run: make_dataset(run, "simulated", simulate_run(scenario, run, 1000 + seed),
                                  []) for run in ("calibration", "flyby")}
        result = symcal.solve(problem, data)
        assert result.problem.weighting == "propagated"
        if not result.success:      # counted apart (see the test)
            failed += 1
            continue
        for p in result.params.values():
            if p.se is not None and p.name in true:
                total += 1
                inside += abs(p.value - true[p.name]) <= Z95 * p.se
        for combo in result.identifiability.identifiable_combinations:
            value = sum(k * true[n] for n, k in combo.coefficients.items())
            assert combo.se is not None and combo.value is not None
            total += 1
            inside += abs(combo.value - value) <= Z95 * combo.se
        verdicts += [t.verdict for t in result.floor_tests]
    return inside / total, total, verdicts, failed


@pytest.mark.slow
@pytest.mark.parametrize(("name", "scenario", "at_reading"), CASES)
def test_95_percent_intervals_cover_93_to_97_percent(name, scenario, at_reading) -> None:
    """Measured on seeds 1000-1059: platen explicit 94.3 % of 1980 intervals, implicit
    95.1 % of 1980, dual explicit 94.5 % of 2820, dual implicit 94.4 % of 2773 (seed 1032
    failed; on 1000-1029, as the test now runs it: 94.9 % of 1410); the mean square of
    (estimate - truth)/se is 1.06, 1.05, 1.00 and 1.02."""
    coverage, total, verdicts, failed = _coverage(name, scenario, at_reading)
    # the lm path stalls on one seed (1032) of the implicit dual problem, with these
    # weights and with 'estimated' ones alike: a failed solve states no interval
    assert failed <= 1
    assert 0.93 <= coverage <= 0.97, (coverage, total)
    # the model is exact: its datasets are at their floor but for the test's own level
    # (each dataset's band is a 95 % interval: about 1 in 20 falls outside)
    assert np.mean([v == "at" for v in verdicts]) > 0.85, verdicts
