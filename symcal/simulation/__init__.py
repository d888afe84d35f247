"""Courier simulator: scenario YAML -> synthetic datasets with known truth.

Public API::

    load_scenario(path) -> Scenario
    simulate_run(scenario, run, seed=0, n=None) -> {column: array}
    simulate(scenario, seed=0, n=None) -> {run: {column: array}}
    truth(scenario, seed=None, n=None) -> dict  # true parameters, effects (slipped rows)
    slipped_rows(scenario, run, seed=0, n=None) -> {segment: rows}  # count slips
    noise_floor(scenario) -> dict    # standard deviations noise alone leaves
    input_noise(scenario) -> dict    # standard deviation of each column's noise
"""

from symcal.simulation.courier import (
    COORDINATION_COLUMNS,
    PLATEN_COLUMNS,
    REFERENCE_COLUMNS,
    SEGMENTS,
    columns,
    fourier_error,
    input_noise,
    noise_floor,
    simulate,
    simulate_run,
    slipped_rows,
    truth,
)
from symcal.simulation.scenario import Scenario, load_scenario, parse_scenario

__all__ = [
    "COORDINATION_COLUMNS",
    "PLATEN_COLUMNS",
    "REFERENCE_COLUMNS",
    "SEGMENTS",
    "Scenario",
    "columns",
    "fourier_error",
    "input_noise",
    "load_scenario",
    "noise_floor",
    "parse_scenario",
    "simulate",
    "simulate_run",
    "slipped_rows",
    "truth",
]
