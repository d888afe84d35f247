"""The ``symcal design`` command line a verdict prints: paths quoted for a shell, and
whether the scenario can be designed as it is (it declares a ``design`` section)."""

from __future__ import annotations

from pathlib import Path

from symcal.base.errors import SymcalError
from symcal.base.files import command_path


def design_command(problem: str | Path, scenario: str | Path | None, options: str) -> str:
    """``symcal design PROBLEM --scenario SCENARIO OPTIONS``, each path as a shell takes
    it (``SCENARIO.yaml`` where the data were not simulated)."""
    where = command_path(scenario) if scenario is not None else "SCENARIO.yaml"
    return f"symcal design {command_path(problem)} --scenario {where} {options}"


def designable(scenario: str | Path | None) -> bool:
    """Whether ``symcal design`` can vary the scenario's motion as it is written (it has
    a ``design`` section); True where it cannot be read here (the command says why)."""
    if scenario is None:
        return True
    from symcal.simulation import load_scenario

    try:
        return load_scenario(scenario).design is not None
    except (SymcalError, OSError):
        return True


def design_sentence(problem: str | Path, scenario: str | Path | None, options: str) -> str:
    """The command, preceded where the scenario has no ``design`` section by what to
    declare first."""
    command = design_command(problem, scenario, options)
    if designable(scenario):
        return command
    return (f"declare which run may change and its limits in {command_path(scenario or '')} "
            f"(a 'design:' section), then: {command}")
