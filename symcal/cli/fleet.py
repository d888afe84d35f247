"""``symcal solve PROBLEM --fleet DIR``: every unit of a fleet folder on Dask, one result
per unit and the fleet summary (text, JSON, figure).

Exit code 0 when every unit solved, 1 when any unit failed (the others are still solved
and reported), 2 for bad input of the fleet as a whole (problem, fleet folder, options,
outputs).  Outlier units do not change the exit code.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from symcal.base.errors import SymcalError, escape_controls
from symcal.cli.common import data_map, inputs_of, out_lock, progress, progress_bars, write_stdout

#: What ``--out DIR`` holds for the fleet, beside one folder per unit.
FLEET_OUTPUTS = ("fleet.json", "fleet.txt", "fleet.png")
#: What ``--out DIR`` holds in each unit's folder.
UNIT_OUTPUTS = ("result.json", "report.txt")


def _check_out(out: Path, fleet: Path, units: list[str], inputs: Iterable[Path]) -> None:
    """Refuse outputs before any work: an input or a foreign file replaced, or a result
    folder that the next run would take for a unit."""
    from symcal.base.files import check_outputs, display_path

    option = f"--out {out}"
    if out.resolve().parent == fleet.resolve():
        raise SymcalError(f"{option}: a folder inside the fleet folder would be taken for a "
                          "unit by the next run; write the results elsewhere")
    for unit in units:
        if unit in FLEET_OUTPUTS:
            raise SymcalError(f"{option}: the unit folder {display_path(fleet / unit)} has the "
                              f"name of the fleet's own output {display_path(out / unit)}; "
                              "rename the unit folder")
    paths = [out / name for name in FLEET_OUTPUTS]
    paths += [out / unit / name for unit in units for name in UNIT_OUTPUTS]
    check_outputs(paths, inputs, option)


def _unit_writer(out: Path, inputs: Iterable[Path]) -> Any:
    """Write each unit's folder as it finishes: its ``result.json`` and ``report.txt``,
    or, for a unit without a result, ``{"error": MESSAGE}`` and the message."""
    from symcal.base.files import OutputSet, atomic_write_text, json_text

    def write(unit: str, doc: Mapping[str, Any], report: str | None) -> None:
        with OutputSet(out / unit, inputs, f"--out {out}") as stage:
            atomic_write_text(stage / "result.json", json_text(doc))
            text = report if report is not None else f"unit {unit}: {doc['error']}\n"
            atomic_write_text(stage / "report.txt", text)

    return write


def run_fleet(args: argparse.Namespace) -> int:
    """Solve the fleet of ``args.fleet``; print the summary (or ``--json``); write
    ``--out``; return the exit code."""
    from symcal.base.files import (
        OutputSet,
        atomic_write_bytes,
        atomic_write_text,
        json_text,
        resolved_paths,
    )
    from symcal.calibrate.fleet import find_units, solve_fleet
    from symcal.problem.build import load_problem
    from symcal.report.fleet import fleet_png, fleet_text
    from symcal.report.text import text_report

    if args.workers is not None and args.workers < 1:
        raise SymcalError(f"--workers {args.workers}: must be at least 1")
    if args.scheduler is not None and args.workers is not None:
        raise SymcalError("--workers applies to the local cluster, not with --scheduler")
    from symcal.base.cores import usable_cores

    cores = usable_cores()
    if args.workers is not None and args.workers > cores:
        raise SymcalError(f"--workers {args.workers}: at most {cores} on this machine (one "
                          "worker process per usable core; more would only compete for "
                          "them, each with its own memory)")
    problem = load_problem(args.problem)
    if args.weighting:
        problem = problem.with_weighting(args.weighting)
    options = problem.options.over(method=args.method, max_iter=args.max_iter)
    data = data_map(args)
    fleet = Path(args.fleet)
    units = find_units(problem, fleet)
    inputs = resolved_paths(inputs_of(args, [problem])
                            | {p for u in units for p in u.files.values()})
    out = Path(args.out) if args.out else None
    if out is not None:
        _check_out(out, fleet, [u.name for u in units], inputs)
    callbacks = []
    if out is not None:
        callbacks.append(_unit_writer(out, inputs))

    def on_unit(unit: str, doc: Mapping[str, Any], report: str | None) -> None:
        for call in callbacks:
            call(unit, doc, report)

    with out_lock(out, f"--out {out}"):
        result = solve_fleet(problem, fleet, data, options, drop_invalid=args.drop_invalid,
                             executor=args.scheduler, workers=args.workers,
                             bars=progress_bars(args), on_unit=on_unit, report=text_report,
                             progress=None if args.quiet else progress)
        document = json_text(result.to_dict())
        text = fleet_text(result.summary, str(fleet))
        if out is not None:
            with OutputSet(out, inputs, f"--out {out}") as stage:
                atomic_write_text(stage / "fleet.json", document)
                atomic_write_text(stage / "fleet.txt", text)
                atomic_write_bytes(stage / "fleet.png", fleet_png(result.summary))
    if args.json:  # the document always, whatever --quiet says
        write_stdout(document)
    elif not args.quiet or not result.success:
        write_stdout(text)
        if out is not None:
            write_stdout(f"\nwrote {len(result.units)} unit folder(s) and fleet.json, "
                         f"fleet.txt, fleet.png to {out}\n")
    if not args.quiet:
        print(escape_controls(f"symcal: fleet of {len(result.units)} unit(s) in "
                              f"{result.seconds:.1f} s"), file=sys.stderr)
    return 0 if result.success else 1
