"""``symcal simulate``: simulate a scenario's runs to CSV or NPZ files, and its truth."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from symcal.base.errors import SymcalError
from symcal.cli.common import debug_option, inputs_of

HELP = "simulate a scenario (any system) to CSV or NPZ, with its truth"


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
    """Simulate every run (or ``--run``), write the tables and the truth file.

    The outputs are checked before anything is simulated (none may be an input, such as
    the scenario or a file it extends, or a file symcal did not write) and are written as
    one output set.
    """
    from symcal.base.files import OutputSet, atomic_write_text, check_outputs
    from symcal.data.dataset import write_table
    from symcal.language.fields import MAX_SAMPLES
    from symcal.simulation import load_scenario, simulate_run, truth

    if args.n is not None and not 1 <= args.n <= MAX_SAMPLES:
        raise SymcalError(f"-n {args.n}: the number of samples must be between 1 and "
                          f"{MAX_SAMPLES}")
    if args.seed < 0:
        raise SymcalError(f"--seed {args.seed}: the seed must not be negative")
    out = Path(args.output)
    if out.suffix.lower() not in (".csv", ".npz"):
        raise SymcalError(f"-o {args.output}: the output must end in .csv or .npz")
    scenario = load_scenario(args.scenario)
    runs = list(scenario.run_names)
    if args.run is not None:
        scenario.run_index(args.run)  # raises with a did-you-mean for an unknown run
        runs = [args.run]
    stem = out.with_suffix("")
    targets = {name: out if len(runs) == 1 else stem.with_name(f"{stem.name}.{name}"
                                                                f"{out.suffix}")
               for name in runs}
    truth_path = stem.with_name(f"{stem.name}.truth.yaml")
    option = f"-o {args.output}"
    inputs = inputs_of(args)
    check_outputs([*targets.values(), truth_path], inputs, option)
    with OutputSet(out.parent, inputs, option) as stage:
        for name, target in targets.items():
            write_table(stage / target.name, simulate_run(scenario, name, seed=args.seed,
                                                          n=args.n))
        doc = truth(scenario, args.seed, args.n)
        doc["seed"] = args.seed
        import yaml  # here, not at the top: ``symcal --help`` does not need it

        atomic_write_text(stage / truth_path.name, yaml.safe_dump(doc, sort_keys=False))
    for target in targets.values():
        print(f"wrote {target}")
    print(f"wrote {truth_path}")
    return 0
