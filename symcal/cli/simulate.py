"""``symcal simulate``: simulate a courier scenario's runs to CSV or NPZ files."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import yaml

from symcal.cli.common import debug_option
from symcal.errors import SymcalError

HELP = "simulate a courier scenario to CSV"


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``simulate`` command to ``subparsers``."""
    cmd = subparsers.add_parser("simulate", help=HELP)
    cmd.add_argument("scenario", help="scenario YAML file")
    cmd.add_argument("-o", "--output", required=True, metavar="OUT.csv",
                     help="output file (.csv or .npz); with several runs, OUT.<run>.csv")
    cmd.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    cmd.add_argument("--run", help="simulate only this run")
    cmd.add_argument("-n", type=int, help="number of samples per run (overrides the scenario)")
    debug_option(cmd)
    return cmd


def run(args: argparse.Namespace) -> int:
    """Simulate every run (or ``--run``), write the tables and the truth file."""
    from symcal.data import write_table
    from symcal.files import atomic_write_text
    from symcal.simulate import load_scenario, simulate_run, truth

    if args.n is not None and args.n < 1:
        raise SymcalError(f"-n {args.n}: the number of samples must be at least 1")
    if args.seed < 0:
        raise SymcalError(f"--seed {args.seed}: the seed must not be negative")
    scenario = load_scenario(args.scenario)
    runs = list(scenario.run_names)
    if args.run is not None:
        scenario.run_index(args.run)  # raises with a did-you-mean for an unknown run
        runs = [args.run]
    out = Path(args.output)
    if out.suffix.lower() not in (".csv", ".npz"):
        raise SymcalError(f"-o {args.output}: the output must end in .csv or .npz")
    if out.resolve() == Path(args.scenario).resolve():
        raise SymcalError(f"-o {args.output}: refusing to overwrite the scenario file")
    stem = out.with_suffix("")
    written = []
    for name in runs:
        target = out if len(runs) == 1 else stem.with_name(f"{stem.name}.{name}{out.suffix}")
        write_table(target, simulate_run(scenario, name, seed=args.seed, n=args.n))
        written.append(target)
    truth_path = stem.with_name(f"{stem.name}.truth.yaml")
    doc = truth(scenario)
    doc["seed"] = args.seed
    atomic_write_text(truth_path, yaml.safe_dump(doc, sort_keys=False))
    for target in written:
        print(f"wrote {target}")
    print(f"wrote {truth_path}")
    return 0
