"""One progress seam (issue 21 item 3): ``progress=`` and ``bars=`` mean the same in every
public function that works for a while.  ``progress`` receives the lines; ``bars`` makes
one meter per counted piece of work; what a meter counts is shown on it, not written as
a line, and every other line still goes to ``progress``."""

from __future__ import annotations

import inspect
import tempfile

import courier_scenarios
import numpy as np
import pytest
from conftest import ROOT
from test_hugelog import write_shards

import symcal
from symcal.base.progress import is_step, reporting
from symcal.data.dataset import make_dataset
from symcal.simulation import simulate_run

TRIAD = ROOT / "examples" / "accelerometer_triad" / "problem_fixed.yaml"
LONG = ("solve", "solve_partitioned", "solve_fleet", "improve", "design")


class Recorder:
    """A :data:`~symcal.base.progress.Bars` factory that records its meters."""

    def __init__(self) -> None:
        self.made: list[tuple[str, int | None, str]] = []
        self.count = 0
        self.notes: list[str] = []
        self.closed = 0

    def __call__(self, label: str, total: int | None, unit: str) -> Recorder:
        self.made.append((label, total, unit))
        return self

    def advance(self, n: int = 1) -> None:
        self.count += n

    def note(self, text: str) -> None:
        self.notes.append(text)

    def close(self) -> None:
        self.closed += 1


@pytest.mark.parametrize("name", LONG)
def test_every_long_function_takes_the_same_two_arguments(name: str) -> None:
    """The same names, keyword arguments defaulting to None, documented with the same
    words."""
    fn = getattr(symcal, name)
    params = inspect.signature(fn).parameters
    for arg in ("progress", "bars"):
        assert arg in params and params[arg].default is None, (name, arg)
        assert params[arg].kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                    inspect.Parameter.KEYWORD_ONLY)
    doc = " ".join((fn.__doc__ or "").split())
    assert "progress Called with each line of progress" in doc, name
    assert "bars Progress bars (:func:`symcal.base.progress.terminal_bars`): one meter " \
           "counting" in doc, name
    assert "(then not passed to ``progress``). None: no bars." in doc, name


def test_the_seam_routes_counted_steps_to_the_bar_and_the_rest_to_lines() -> None:
    lines: list[str] = []
    with reporting(lines.append, None, "x") as report:
        report.step("  a: iteration 1")
        report.line("a note")
        report("  a: iteration 2  cost 1")
    assert lines == ["  a: iteration 1", "a note", "  a: iteration 2  cost 1"]
    bars, lines = Recorder(), []
    with reporting(lines.append, bars, "x", total=3, unit="it") as report:
        report.step("  a: iteration 1")
        report.line("a note")
        report("  a: iteration 2  cost 1")
        report("a gauge")
    assert lines == ["a note", "a gauge"]
    assert bars.made == [("x", 3, "it")] and bars.count == 2 and bars.closed == 1
    assert bars.notes == ["a: iteration 1", "a: iteration 2  cost 1"]
    with reporting(None, None, "x") as report:
        assert report.silent and report.callback() is None
    assert is_step("  calibration: iteration   3  cost 1") and not is_step("a gauge")


def test_solve_counts_its_iterations_on_a_bar() -> None:
    """Without bars every line goes to ``progress``; with them the solver's iterations
    advance the bar, the last one beside it, and the other lines still go to
    ``progress``."""
    plain: list[str] = []
    first = symcal.solve(TRIAD, progress=plain.append)
    steps = [line for line in plain if is_step(line)]
    assert len(steps) == first.stages[-1].iterations >= 2
    bars, lines = Recorder(), []
    again = symcal.solve(TRIAD, progress=lines.append, bars=bars)
    assert lines == [line for line in plain if not is_step(line)]
    assert bars.made == [("solve", None, "it")] and bars.closed == 1
    assert bars.count == len(steps) and bars.notes[-1] == steps[-1].strip()
    silent = Recorder()
    symcal.solve(TRIAD, bars=silent)           # bars alone: the same count, no lines
    assert silent.count == len(steps)
    assert again.theta.tolist() == first.theta.tolist()


def test_a_log_kept_as_shards_counts_its_shards_on_a_bar(tmp_path) -> None:
    """solve_partitioned: the bar counts the shards every pass has done; the solver's
    iteration lines are shown beside it (with the stage), not written."""
    problem = symcal.load_problem(TRIAD)
    data = symcal.load_datasets(problem)
    cols = {k: np.asarray(v) for k, v in data["calibration"].columns.items()}
    folder = write_shards(tmp_path / "log", cols, "npz", (300, 300, cols["ax"].size - 600))
    plain: list[str] = []
    symcal.solve_partitioned(problem, folder, data={k: v for k, v in data.items()
                                                    if k != "calibration"},
                             progress=plain.append)
    steps = [line for line in plain if is_step(line)]
    assert steps
    bars, lines = Recorder(), []
    symcal.solve_partitioned(problem, folder, data={k: v for k, v in data.items()
                                                    if k != "calibration"},
                             progress=lines.append, bars=bars)
    assert lines == [line for line in plain if not is_step(line)]
    assert bars.made == [("log", None, "shard")]
    assert bars.count > 0 and bars.count % 3 == 0           # three shards per pass
    assert [s.strip() for s in steps] == [n for n in bars.notes if is_step(n)]


@pytest.mark.slow
def test_design_reports_its_rounds() -> None:
    problem = symcal.load_problem(ROOT / "problems" / "dual_sensor_calibration.yaml")
    scenario = symcal.load_scenario(ROOT / "problems" / "scenarios" / "courier_dual.yaml")
    plain: list[str] = []
    symcal.design(problem, scenario, criterion="D", progress=plain.append)
    assert plain[0] == "design: the baseline run 'calibration' predicted (1000 observations)"
    assert plain[1].startswith("design: round 1: IPOPT: ")
    bars, lines = Recorder(), []
    symcal.design(problem, scenario, criterion="D", progress=lines.append, bars=bars)
    assert lines == plain[:1] and bars.made == [("design", 2, "round")]
    assert bars.count == len(plain) - 1 and bars.notes == plain[1:]


@pytest.mark.slow
def test_improve_counts_its_rounds_on_a_bar() -> None:
    scenario = courier_scenarios.platen(model=False)
    data = {name: make_dataset(name, "simulated", simulate_run(scenario, name, 61), [])
            for name in ("calibration", "flyby")}
    problem = ROOT / "problems" / "platen_self_calibration.yaml"
    plain: list[str] = []
    first = symcal.improve(problem, tempfile.mkdtemp(), data, progress=plain.append)
    kept = [line for line in plain if ": added " in line]
    assert len(kept) == len(first.rounds) - 1 >= 1
    bars, lines = Recorder(), []
    symcal.improve(problem, tempfile.mkdtemp(), data, progress=lines.append, bars=bars)
    assert lines == [line for line in plain if ": added " not in line]
    assert bars.made == [("improve", 5, "round")] and bars.count == len(kept)
    assert bars.notes == kept


@pytest.mark.slow
def test_a_fleet_reports_each_unit(tmp_path) -> None:
    """solve_fleet: one line per unit done (the command line's lines), or a bar that
    counts them."""
    problem = symcal.load_problem(ROOT / "problems" / "platen_self_calibration.yaml")
    scenario = symcal.load_scenario(ROOT / "problems" / "scenarios" / "courier_platen.yaml")
    from symcal.data.dataset import write_table

    for k, seed in enumerate((1, 2)):
        (tmp_path / f"unit-{k}").mkdir()
        write_table(tmp_path / f"unit-{k}" / "calibration.npz",
                    simulate_run(scenario, "calibration", seed=seed, n=300))
    (tmp_path / "unit-bad").mkdir()
    (tmp_path / "unit-bad" / "calibration.csv").write_text("x\n1\n")
    lines: list[str] = []
    fleet = symcal.solve_fleet(problem, tmp_path, workers=1, progress=lines.append)
    assert [line.split(": ", 1)[0] for line in lines] == ["  fleet"] * 3   # as they finish
    assert [line.split(": ", 1)[1].split("/")[0] for line in lines] == ["1", "2", "3"]
    assert {line.rsplit(" unit ", 1)[1].split(":")[0] for line in lines} == \
        {"unit-0", "unit-1", "unit-bad"}
    assert any("unit-bad: FAILED: " in line for line in lines)
    assert len(fleet.results) == 2
    bars, quiet = Recorder(), []
    symcal.solve_fleet(problem, tmp_path, workers=1, progress=quiet.append, bars=bars)
    assert quiet == [] and bars.made == [("fleet", 3, "unit")] and bars.count == 3
    assert any("(failed=1)" in n for n in bars.notes)


def test_a_line_of_progress_is_one_write() -> None:
    """A line and its newline go out in one write, so that an interrupt cannot fall
    between them (the command's error message then continued the cut line)."""
    from symcal.base.progress import write_line

    class Stream:
        def __init__(self) -> None:
            self.writes: list[str] = []

        def write(self, text: str) -> int:
            self.writes.append(text)
            return len(text)

        def flush(self) -> None:
            pass

    stream = Stream()
    write_line("  fleet: 1/40 unit unit-00: solved", stream)  # type: ignore[arg-type]
    assert stream.writes == ["  fleet: 1/40 unit unit-00: solved\n"]
