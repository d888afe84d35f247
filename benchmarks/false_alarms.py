"""How often `symcal diagnose` names a significant candidate on data that lack every
effect of its library: the family-wise false-alarm rate of the candidate tests (issue 23
item 4), and how often the global test calls a dataset above its floor, over many seeds.

Each system is simulated without a hidden effect (its scenario as the model states it),
solved and diagnosed in this process.  The candidate tests are Bonferroni-corrected at
``--alpha`` (0.01): the share of seeds with any significant candidate should be at most
that level (Bonferroni is conservative where candidates are correlated), within binomial
noise.

    python benchmarks/false_alarms.py [--seeds 100] [--alpha 0.01] [--out FALSE_ALARMS.md]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import courier_scenarios  # noqa: E402

import symcal  # noqa: E402
from symcal.data.dataset import make_dataset  # noqa: E402
from symcal.simulation import Scenario, load_scenario, simulate_run  # noqa: E402

BATH = ROOT / "tests" / "data" / "bath"
ACCEPTANCE = ROOT / "tests" / "acceptance"


def _bath_declared() -> Path:
    """The bath with sensor 1's reading declared a candidate variable of sensor 2 (errors
    in the variables: the case that made every clean seed a false alarm)."""
    path = ROOT / "build" / "false_alarms" / "bath_declared.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"problem: bath_declared\nextends: {(BATH / 'problem.yaml').as_posix()}\n"
                    "instances:\n  s2: {candidates: {variables: [raw2, t, raw1]}}\n")
    return path


DATA = ROOT / "tests" / "data"
EXAMPLES = ROOT / "examples"


def _held_out(folder: Path, problem: str = "problem.yaml"
              ) -> tuple[Path, Scenario, tuple[str, ...]]:
    """A system kept in ``folder``: its problem, its ``scenario.yaml``, and a calibration
    and a validation run."""
    return folder / problem, load_scenario(folder / "scenario.yaml"), ("calibration",
                                                                        "validation")


SYSTEMS: dict[str, Callable[[], tuple[Path, Scenario, tuple[str, ...]]]] = {
    "platen (implicit), courier": lambda: (
        ROOT / "problems" / "platen_self_calibration_implicit.yaml",
        courier_scenarios.platen(model=False), ("calibration", "flyby")),
    "dual (implicit), courier": lambda: (
        ROOT / "problems" / "dual_sensor_calibration_implicit.yaml",
        courier_scenarios.dual(), ("calibration", "flyby")),
    "two thermometers in one bath": lambda: _held_out(BATH),
    "two thermometers, the other's reading declared": lambda: (
        _bath_declared(), load_scenario(BATH / "scenario.yaml"),
        ("calibration", "validation")),
    "accelerometer triad": lambda: _held_out(EXAMPLES / "accelerometer_triad",
                                             "problem_fixed.yaml"),
    "two NTC thermistors in one bath (noise 1-25 mK across the range)":
        lambda: _held_out(ACCEPTANCE / "thermistor_bath"),
    "magnetometer tumbled by hand": lambda: _held_out(ACCEPTANCE / "magnetometer"),
    "differential drive": lambda: _held_out(EXAMPLES / "diff_drive", "problem_fixed.yaml"),
    "DC power bench, two channels and two references (tests/data/power_bench)":
        lambda: _held_out(DATA / "power_bench"),
    "robot joint, two encoders and a tracker (tests/data/joint)":
        lambda: _held_out(DATA / "joint"),
    "weighing platform, three load cells, test masses and a crane scale "
    "(tests/data/platform)": lambda: _held_out(DATA / "platform", "prob-v2.yaml"),
    "drone altimeter, two barometers, a thermometer and GNSS (tests/data/altimeter)":
        lambda: _held_out(DATA / "altimeter"),
    "industrial oven, thermocouple, Pt100 under a stepped current, pyrometer "
    "(tests/data/oven)": lambda: _held_out(DATA / "oven"),
    "wind mast, cup, Pitot-static and sonic anemometers (tests/data/mast)":
        lambda: _held_out(DATA / "mast"),
    "clock lab, two oscillators against a GNSS PPS (tests/data/clock)":
        lambda: _held_out(DATA / "clock"),
}


def run(name: str, seeds: range, alpha: float) -> dict:
    """Diagnose one system on every seed: how many name a significant candidate, how
    many a significant coupling outside the search spaces, how many datasets lie above
    their floor."""
    path, scenario, runs = SYSTEMS[name]()
    problem = symcal.load_problem(path)
    alarms, outside, above, datasets, tested = 0, 0, 0, 0, 0
    started = time.process_time()
    for seed in seeds:
        data = {r: make_dataset(r, "simulated", simulate_run(scenario, r, seed), [])
                for r in runs}
        result = symcal.solve(problem, data)
        diag = symcal.diagnose(result, alpha, report=False)
        alarms += bool(diag.significant)
        outside += bool(diag.outside)
        tested = diag.tested
        for test in result.floor_tests:
            datasets += 1
            above += test.verdict == "above"
    return {"name": name, "seeds": len(seeds), "alarms": alarms, "outside": outside,
            "tested": tested,
            "above": above, "datasets": datasets,
            "cpu": time.process_time() - started}


def _limit(n: int, p: float) -> float:
    """The nominal count plus three binomial standard deviations."""
    return n * p + 3 * math.sqrt(n * p * (1 - p))


def table(rows: list[dict], alpha: float) -> str:
    """The rows as Markdown."""
    lines = ["| system | seeds | candidates tested | seeds with a significant candidate "
             f"(level {alpha:g}) | seeds naming a coupling outside the search spaces "
             f"(level {alpha:g}, tested where nothing in them is significant) | datasets "
             "above their floor (level 0.05) | CPU s |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['name']} | {r['seeds']} | {r['tested']} | {r['alarms']} "
            f"({r['alarms'] / r['seeds']:.1%}; nominal at most {alpha:.0%}, 3 sd: "
            f"{_limit(r['seeds'], alpha):.1f}) | {r['outside']} "
            f"({r['outside'] / r['seeds']:.1%}) | {r['above']} of {r['datasets']} "
            f"({r['above'] / max(r['datasets'], 1):.1%}) | {r['cpu']:.0f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=100)
    parser.add_argument("--first", type=int, default=5000, help="the first seed")
    parser.add_argument("--alpha", type=float, default=0.01)
    parser.add_argument("--systems", nargs="*", default=list(SYSTEMS))
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    rows = []
    for name in args.systems:
        rows.append(run(name, range(args.first, args.first + args.seeds), args.alpha))
        print(table(rows[-1:], args.alpha), end="", flush=True)
    text = table(rows, args.alpha)
    if args.out is not None:
        args.out.write_text("# False alarms on clean data\n\n"
                            "`python benchmarks/false_alarms.py` (seeds "
                            f"{args.first}..{args.first + args.seeds - 1}): every system "
                            "simulated without a hidden effect, solved and diagnosed.\n\n"
                            + text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
