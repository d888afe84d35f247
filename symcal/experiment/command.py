"""The ``symcal design`` command line a verdict prints: paths quoted for a shell, and
whether the scenario can be designed as it is (it declares a ``design`` section)."""

from __future__ import annotations

import shlex
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
    return _kinds(scenario)[0]


def _kinds(scenario: str | Path | None) -> tuple[bool, bool]:
    """Whether the scenario declares a ``design`` section, and whether any of its runs is
    a motion ``symcal design`` can vary (a scatter or dwells run); both True where it
    cannot be read here (the command then says why)."""
    if scenario is None:
        return True, True
    from symcal.simulation import load_scenario
    from symcal.simulation.scenario import DESIGNABLE

    try:
        found = load_scenario(scenario)
    except (SymcalError, OSError):
        return True, True
    return (found.design is not None,
            any(run.motion.kind in DESIGNABLE for run in found.runs))


def design_sentence(problem: str | Path, scenario: str | Path | None, options: str) -> str:
    """The command, preceded where the scenario has no ``design`` section by what to
    declare first, where none of its runs can be varied (series and lines only) by the
    run to add, and where the data were not simulated (no scenario) by the scenario to
    write (a placeholder, ``SCENARIO.yaml``, alone read as a file that should exist)."""
    command = design_command(problem, scenario, options)
    if scenario is None:
        return ("with the data not simulated, write a scenario of the experiment as "
                "SCENARIO.yaml (symcal simulate's format, with a run of scattered poses or "
                f"dwells and a 'design:' section naming it and its limits), then: {command}")
    declared, variable = _kinds(scenario)
    if declared:
        return command
    where = command_path(scenario or "")
    if not variable:
        return (f"the runs of {where} are series or lines, which symcal design cannot "
                "vary: add a run of scattered poses or dwells (a 'scatter:' or 'dwells:' "
                f"motion) and declare it and its limits in a 'design:' section, then: "
                f"{command}")
    return (f"declare which run may change and its limits in {where} "
            f"(a 'design:' section), then: {command}")


def target_arg(name: str, value: float, unit: str) -> str:
    """``NAME=VALUEUNIT`` as a shell takes it: the unit joined where it starts with a
    letter (``l_y=0.31mm``), else after a space and quoted (``'ifm.kT=3.3e-09 1/K'``:
    ``3.3e-091/K`` would read as another number)."""
    unit = unit.replace(" ", "")
    if not unit or unit[0].isalpha() or unit[0] in "µ°Ω":
        return f"{name}={value:.2g}{unit}"
    return shlex.quote(f"{name}={value:.2g} {unit}")
