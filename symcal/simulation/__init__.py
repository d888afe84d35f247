"""The simulator: a scenario file (any system) -> synthetic datasets with known truth.

Public API::

    load_scenario(path) -> Scenario          # scenario.overlay({...}) changes one
    simulate_run(scenario, run, seed=0, n=None) -> {column: array}
    simulate(scenario, seed=0, n=None) -> {run: {column: array}}
    truth(scenario, seed=None, n=None) -> dict   # true values, effects (slipped rows)
    slipped_rows(scenario, run, seed=0, n=None) -> {column: rows}
    input_noise(scenario) -> {column: standard deviation of its noise}
    quiet(scenario) -> the scenario without noise
"""

from symcal.simulation.engine import (
    input_noise,
    noise_streams,
    quiet,
    run_states,
    simulate,
    simulate_run,
    slipped_rows,
    true_values,
    truth,
)
from symcal.simulation.scenario import Scenario, load_scenario, parse_scenario

__all__ = [
    "Scenario",
    "input_noise",
    "load_scenario",
    "noise_streams",
    "parse_scenario",
    "quiet",
    "run_states",
    "simulate",
    "simulate_run",
    "slipped_rows",
    "true_values",
    "truth",
]
