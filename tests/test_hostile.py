"""Hostile input, second round (issue 13): what the corpus cannot hold as plain files.

FIFOs and oversized files made on the fly, the output-set writer (whole or nothing,
leftovers of killed runs, file modes, a full disk), JSON error documents for every exit
code, YAML 1.2 numbers, streamed CSV blocks, codegen against stale data and odd problem
names, and the slow ones: a 1e7-row CSV in bounded memory, and SIGINT/SIGTERM mid-solve.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import resource
import shutil
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT
from hypothesis import given, settings
from hypothesis import strategies as st

from symcal.base import files
from symcal.base.errors import SpecError, SymcalError
from symcal.cli import main
from symcal.data.dataset import Table, read_table
from symcal.language.yamlio import MAX_BYTES, load_yaml

BASE = ROOT / "tests" / "bad_inputs" / "bad_max_iter"
DUAL = ROOT / "problems" / "dual_sensor_calibration.yaml"
DUAL_SCENARIO = ROOT / "problems" / "scenarios" / "courier_dual.yaml"


@pytest.fixture
def toy(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A folder holding the corpus's small valid problem (prob.yaml, seg.yaml, data.csv)."""
    for name in ("prob.yaml", "seg.yaml", "data.csv"):
        shutil.copy(BASE / name, tmp_path / name)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _run(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    try:
        code = main(args)
    except SystemExit as exc:
        code = int(exc.code or 0)
    out = capsys.readouterr()
    assert "Traceback" not in out.err
    return code, out.out, out.err


def _tree(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _symcal(*args: str, cwd: Path, timeout: float = 120, **kw: object
            ) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "symcal", *args], cwd=cwd, text=True,
                          capture_output=True, timeout=timeout, **kw)  # type: ignore[call-overload]


# ----------------------------------------------------------------- non-regular inputs

@pytest.mark.parametrize("role", ["problem", *(pytest.param(r, marks=pytest.mark.slow)
                                     for r in ("model", "data", "scenario", "result"))])
def test_a_fifo_is_refused_without_blocking(toy: Path, role: str) -> None:
    fifo = toy / "pipe"
    os.mkfifo(fifo)
    args = {"problem": ["solve", "pipe"],
            "model": ["solve", "prob.yaml"],
            "data": ["solve", "prob.yaml", "--data", "calibration=pipe"],
            "scenario": ["simulate", "pipe", "-o", "out.csv"],
            "result": ["codegen", "prob.yaml", "--result", "pipe", "-o", "out"]}[role]
    if role == "model":
        text = (toy / "prob.yaml").read_text().replace("s2: {model: seg.yaml", "s2: {model: pipe")
        (toy / "prob.yaml").write_text(text)
    proc = _symcal(*args, cwd=toy, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert "is a named pipe, not a regular file" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (toy / "out").exists() and not (toy / "out.csv").exists()


def test_an_oversized_yaml_file_is_refused(toy: Path, capsys) -> None:
    (toy / "big.yaml").write_text("problem: toy\n" + "# padding\n" * (MAX_BYTES // 10 + 1))
    code, _, err = _run(["solve", "big.yaml"], capsys)
    assert code == 2
    assert err == (f"symcal: error: big.yaml: cannot read problem file: it is too large "
                   f"({(toy / 'big.yaml').stat().st_size} bytes; the limit is {MAX_BYTES})\n")


def test_a_long_extends_chain_of_models_stops_at_32_levels(toy: Path, capsys,
                                                         monkeypatch) -> None:
    from symcal.language import yamlio

    (toy / "m0.yaml").write_text((toy / "seg.yaml").read_text())
    for i in range(1, 1500):
        (toy / f"m{i}.yaml").write_text(f"model: m{i}\nextends: m{i - 1}.yaml\n")
    prob = (toy / "prob.yaml").read_text().replace("{model: seg.yaml", "{model: m1499.yaml")
    (toy / "prob.yaml").write_text(prob)
    read: list[str] = []
    real = yamlio.read_input_bytes

    def counted(path: str | Path, limit: int) -> bytes:
        read.append(Path(path).name)
        return real(path, limit)

    monkeypatch.setattr(yamlio, "read_input_bytes", counted)
    code, _, err = _run(["solve", "prob.yaml"], capsys)
    assert code == 2
    assert err == ("symcal: error: m1467.yaml:2: extends: more than 32 levels of 'extends' "
                   "below m1499.yaml\n")
    assert len(read) <= 34          # the problem and the 33 models it reached, no more


def test_a_deeply_nested_result_is_refused(toy: Path, capsys) -> None:
    (toy / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    code, out, err = _run(["codegen", "prob.yaml", "--result", "deep.json", "-o", "c"], capsys)
    assert code == 2
    assert "nested too deeply" in err
    assert not (toy / "c").exists()


# ----------------------------------------------------------------- YAML 1.2 numbers

@pytest.mark.parametrize(("text", "value"), [
    ("010", 10), ("1:30", "1:30"), ("0x1F", 31), ("0o17", 15), ("1e-3", 1e-3),
    ("1e-05", 1e-5), ("5e-09", 5e-9), ("1.0e5", 1e5), ("-.5", -0.5), ("+12", 12),
    ("yes", "yes"), ("off", "off"), ("2001-12-14", "2001-12-14"), ("1_000", "1_000"),
    ("0b101", "0b101"), ("true", True), ("FALSE", False), ("~", None), (".inf", float("inf")),
])
def test_yaml_scalars_follow_the_core_schema(tmp_path: Path, text: str, value: object) -> None:
    (tmp_path / "x.yaml").write_text(f"a: {text}\n")
    doc, _ = load_yaml(tmp_path / "x.yaml")
    assert doc["a"] == value and type(doc["a"]) is type(value)


def test_a_file_parsed_once_is_handed_out_as_a_copy_and_read_again(tmp_path: Path) -> None:
    """Documents are parsed once per process by (source, text): a caller that changes
    its copy changes no other's, an edited file is parsed again, and a file that failed
    to parse is not remembered once it is fixed."""
    path = tmp_path / "x.yaml"
    path.write_text("a: {b: [1, 2]}\n")
    first, _ = load_yaml(path)
    first["a"]["b"].append(3)
    first["c"] = 4
    second, _ = load_yaml(path)
    assert second == {"a": {"b": [1, 2]}} and second["a"].line == 1
    path.write_text("a: {b: [5]}\n")
    assert load_yaml(path)[0] == {"a": {"b": [5]}}
    path.write_text("a: [\n")
    with pytest.raises(SpecError, match="invalid YAML"):
        load_yaml(path)
    path.write_text("a: 1\n")
    assert load_yaml(path)[0] == {"a": 1}


def test_exponent_numbers_work_as_parameter_values(toy: Path, capsys) -> None:
    seg = (toy / "seg.yaml").read_text().replace("k0: {value: 0, unit: mm}",
                                                  "k0: {value: 1e-3, unit: mm, scale: 5e-09}")
    (toy / "seg.yaml").write_text(seg)
    code, out, _ = _run(["solve", "prob.yaml", "--json"], capsys)
    assert code == 0
    initial = {p["name"]: p["initial"] for p in json.loads(out)["parameters"]}
    assert initial["s1.k0"] == 1e-3


# ----------------------------------------------------------------- CSV blocks

def test_csv_read_in_small_blocks_equals_the_whole(toy: Path, monkeypatch) -> None:
    text = (toy / "data.csv").read_text()
    lines = text.splitlines()
    messy = "\ufeff" + "\r\n".join(lines[:10] + ["", "   "] + lines[10:]) + "\r\n"
    (toy / "messy.csv").write_text(messy, encoding="utf-8", newline="")
    whole = np.loadtxt(toy / "data.csv", delimiter=",", skiprows=1)
    monkeypatch.setattr("symcal.data.dataset.BLOCK_BYTES", 50)
    columns = read_table(toy / "messy.csv")
    assert list(columns) == ["t", "p1", "p2"]
    np.testing.assert_array_equal(np.column_stack(list(columns.values())), whole)


def test_csv_errors_name_the_line_in_a_later_block(toy: Path, monkeypatch) -> None:
    lines = (toy / "data.csv").read_text().splitlines()
    lines[40] = lines[40].replace(",", ",x", 1)
    (toy / "bad.csv").write_text("\n".join(lines) + "\n")
    monkeypatch.setattr("symcal.data.dataset.BLOCK_BYTES", 100)
    with pytest.raises(SymcalError, match=r"^bad.csv:41: column 'p1': 'x.*' is not a number$"):
        read_table(toy / "bad.csv")


def test_a_csv_line_without_end_is_refused(toy: Path, monkeypatch) -> None:
    monkeypatch.setattr("symcal.data.dataset.MAX_LINE_BYTES", 1000)
    monkeypatch.setattr("symcal.data.dataset.BLOCK_BYTES", 300)
    (toy / "long.csv").write_text("t,p1,p2\n" + "1," * 2000)
    with pytest.raises(SymcalError, match="^long.csv:2: a line is longer than 1000 bytes"):
        read_table(toy / "long.csv")


def test_dataset_columns_are_read_only_without_a_copy(toy: Path) -> None:
    from symcal.data.loading import load_datasets
    from symcal.problem.build import load_problem

    data = load_datasets(load_problem("prob.yaml"))["calibration"]
    for column in data.columns.values():
        assert not column.flags.writeable


# ----------------------------------------------------------------- outputs

@pytest.mark.slow
def test_every_output_gets_the_mode_of_an_ordinary_file(toy: Path, capsys) -> None:
    old = os.umask(0o022)
    try:
        assert _run(["solve", "prob.yaml", "--out", "res", "--quiet"], capsys)[0] == 0
        assert _run(["codegen", "prob.yaml", "--result", "res/result.json", "-o", "c"],
                    capsys)[0] == 0
        assert _run(["simulate", str(ROOT / "problems" / "scenarios" / "courier_platen.yaml"),
                     "-o", "sim/run.csv", "-n", "20"], capsys)[0] == 0
        assert _run(["diagnose", "prob.yaml", "--quiet", "--report", "page/d.html", "--plots",
                     "figs"], capsys)[0] == 0
    finally:
        os.umask(old)
    written = [p for p in toy.rglob("*") if p.is_file() and p.parent != toy]
    assert len(written) >= 2 + 6 + 3 + 1 + 3
    assert {p.name: oct(stat.S_IMODE(p.stat().st_mode)) for p in written} == \
        {p.name: "0o644" for p in written}


def test_outputs_replace_symcals_own_files_and_keep_them_recorded(toy: Path, capsys) -> None:
    assert _run(["solve", "prob.yaml", "--out", "res", "--quiet"], capsys)[0] == 0
    assert _run(["solve", "prob.yaml", "--out", "res", "--quiet"], capsys)[0] == 0
    record = json.loads((toy / "res" / files.MANIFEST).read_text())["files"]
    assert set(record) == {"result.json", "report.txt"}
    (toy / "res" / "report.txt").write_text("my notes\n")
    code, _, err = _run(["solve", "prob.yaml", "--out", "res", "--quiet"], capsys)
    assert code == 2
    assert err == ("symcal: error: --out res: res/report.txt exists and was not written by "
                   "symcal; remove it or choose another destination\n")


def test_codegen_force_replaces_a_foreign_makefile_but_never_an_input(toy: Path,
                                                                      capsys) -> None:
    (toy / "Makefile").write_text("all:\n\techo mine\n")
    assert _run(["codegen", "prob.yaml", "-o", "."], capsys)[0] == 2
    assert (toy / "Makefile").read_text() == "all:\n\techo mine\n"
    code, out, _ = _run(["codegen", "prob.yaml", "-o", ".", "--force"], capsys)
    assert code == 0 and "wrote Makefile" in out
    assert "Generated by symcal codegen" in (toy / "Makefile").read_text()
    assert _run(["codegen", "prob.yaml", "-o", "."], capsys)[0] == 0  # its own now
    (toy / "main.c").unlink()
    shutil.copy(toy / "data.csv", toy / "main.c")
    prob = (toy / "prob.yaml").read_text().replace("path: data.csv", "path: main.c")
    (toy / "prob.yaml").write_text(prob)
    code, _, err = _run(["codegen", "prob.yaml", "-o", ".", "--force"], capsys)
    assert code == 2 and "refusing to overwrite input file main.c" in err


def test_an_output_set_moves_in_whole_or_not_at_all(tmp_path: Path) -> None:
    out = tmp_path / "res"
    with files.OutputSet(out, option="--out res") as stage:
        (stage / "a.txt").write_text("old a")
    (out / "b.txt").write_text("foreign b")
    with pytest.raises(SymcalError, match="b.txt exists and was not written by symcal"):
        with files.OutputSet(out, option="--out res") as stage:
            (stage / "a.txt").write_text("new a")
            (stage / "b.txt").write_text("new b")
    assert (out / "a.txt").read_text() == "old a"
    with pytest.raises(RuntimeError):
        with files.OutputSet(out, option="--out res", force=True) as stage:
            (stage / "a.txt").write_text("new a")
            raise RuntimeError("failed half way")
    assert (out / "a.txt").read_text() == "old a"
    assert sorted(p.name for p in out.iterdir()) == [files.MANIFEST, "a.txt", "b.txt"]


def test_sigterm_while_a_set_moves_in_is_held_until_it_is_whole(tmp_path: Path,
                                                                monkeypatch) -> None:
    from symcal.cli.common import Terminated, signals_handled

    out = tmp_path / "res"
    real_replace = os.replace
    moved: list[str] = []

    def replace(src: str | Path, dst: str | Path) -> None:
        real_replace(src, dst)
        if not Path(dst).name.startswith("."):
            moved.append(Path(dst).name)
            if len(moved) == 1:  # between the two files of the set
                os.kill(os.getpid(), signal.SIGTERM)

    with signals_handled(), pytest.raises(Terminated):
        with files.OutputSet(out, option="--out res") as stage:
            (stage / "result.json").write_text("{}")
            (stage / "report.txt").write_text("report")
            monkeypatch.setattr(files.os, "replace", replace)
    monkeypatch.undo()
    assert moved[:2] == ["report.txt", "result.json"]
    assert sorted(p.name for p in out.iterdir()) == [files.MANIFEST, "report.txt",
                                                     "result.json"]


@pytest.mark.parametrize(("sig", "code", "words"), [
    (signal.SIGTERM, 143, "terminated by SIGTERM"),
    (signal.SIGINT, 130, "interrupted by SIGINT (Ctrl-C)"),
])
def test_a_stop_that_other_code_swallowed_still_stops_the_command(
        toy: Path, capsys, monkeypatch, sig: signal.Signals, code: int, words: str) -> None:
    """A signal whose exception library code swallowed (CasADi converts a numpy argument
    under a bare ``except:``) stops the command at its next pass over the data, before
    any output is written; the next command runs as usual."""
    from contextlib import contextmanager

    from symcal.solvers import passes

    real = passes.blas_limit
    calls: list[int] = []

    @contextmanager
    def blas_limit():
        calls.append(1)
        if len(calls) == 1:          # inside the first pass: the stop is swallowed
            try:
                os.kill(os.getpid(), sig)
                time.sleep(5)        # the handler runs here (Python checks at once)
            except BaseException:    # noqa: BLE001 - as code that catches everything
                pass
        with real():
            yield

    monkeypatch.setattr(signal, "getsignal", lambda s, real=signal.getsignal: (
        signal.default_int_handler if s == signal.SIGINT else real(s)))  # as a terminal
    monkeypatch.setattr(passes, "blas_limit", blas_limit)
    got, out, err = _run(["solve", "prob.yaml", "--out", "res"], capsys)
    assert (got, err.splitlines()[-1]) == (
        code, f"symcal: error: {words}; no output was written or changed")
    assert len(calls) == 1 and not (toy / "res").exists()   # no pass after it
    monkeypatch.setattr(passes, "blas_limit", real)
    assert _run(["solve", "prob.yaml", "--out", "res", "--quiet"], capsys)[0] == 0


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_leftovers_of_a_killed_run_are_cleaned_or_finished(toy: Path, capsys) -> None:
    res = toy / "res"
    res.mkdir()
    pid = _dead_pid()
    (res / f".result.json.symcal-{pid}-x1.tmp").write_text("half")
    (res / f".report.txt.symcal-{os.getpid()}-x2.tmp").write_text("a live writer's")
    half = res / f"{files.STAGING_PREFIX}{pid}-a"
    half.mkdir()
    (half / "result.json").write_text("never complete")
    whole = res / f"{files.STAGING_PREFIX}{pid}-b"
    whole.mkdir()
    (whole / "notes.txt").write_text("complete set")
    digest = hashlib.sha256(b"complete set").hexdigest()
    (whole / files.COMMIT_MARK).write_text(json.dumps({"notes.txt": digest}))
    assert _run(["solve", "prob.yaml", "--out", "res", "--quiet"], capsys)[0] == 0
    assert sorted(p.name for p in res.iterdir()) == sorted(
        [files.MANIFEST, "notes.txt", "report.txt", "result.json",
         f".report.txt.symcal-{os.getpid()}-x2.tmp"])
    assert (res / "notes.txt").read_text() == "complete set"


@pytest.mark.skipif(not hasattr(resource, "RLIMIT_FSIZE"), reason="no RLIMIT_FSIZE")
@pytest.mark.slow
def test_a_full_disk_keeps_the_earlier_results(toy: Path) -> None:
    assert _symcal("solve", "prob.yaml", "--out", "res", "--quiet", cwd=toy).returncode == 0
    before = _tree(toy / "res")

    def small_files() -> None:  # writes beyond 4 kB fail like a full disk (EFBIG)
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))

    proc = _symcal("solve", "prob.yaml", "--out", "res", cwd=toy, preexec_fn=small_files)
    assert proc.returncode == 2
    assert proc.stderr.splitlines()[-1] == ("symcal: error: --out res: cannot write to res: "
                                            "File too large; the files there are unchanged")
    assert "symcal: toy (prob.yaml)" in proc.stdout  # the report was printed all the same
    assert _tree(toy / "res") == before


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes to read-only folders")
def test_a_read_only_folder_is_refused_before_the_solve(toy: Path, capsys) -> None:
    (toy / "ro").mkdir()
    (toy / "ro").chmod(0o555)
    code, out, err = _run(["solve", "prob.yaml", "--out", "ro/res"], capsys)
    assert code == 2 and out == ""
    assert err.startswith("symcal: error: --out ro/res: cannot write to ro: ")


# ----------------------------------------------------------------- one message, JSON

def test_json_error_documents_for_every_exit_code(toy: Path, capsys) -> None:
    code, out, err = _run(["solve", "nothere.yaml", "--json"], capsys)
    assert code == 2
    assert json.loads(out) == {"error": {"message": "nothere.yaml: problem file not found",
                                         "exit_code": 2}}
    code, out, err = _run(["solve", "prob.yaml", "--json", "--bogus"], capsys)
    assert code == 2
    assert json.loads(out) == {"error": {"message": "unrecognized arguments: --bogus",
                                         "exit_code": 2}}
    code, out, _ = _run(["solve", "prob.yaml", "--json", "--method", "ipopt", "--max-iter",
                         "1"], capsys)
    assert code == 1 and json.loads(out)["solver"]["success"] is False
    code, out, _ = _run(["diagnose", "prob.yaml", "--json", "--report", "data.csv"], capsys)
    assert code == 2 and json.loads(out)["error"]["exit_code"] == 2


def test_unexpected_failures_are_one_message(toy: Path, capsys, monkeypatch) -> None:
    import symcal.cli.solve as solve_cli

    def broken(args: object) -> int:
        raise RuntimeError("a bug \x1b[31m")

    monkeypatch.setattr(solve_cli, "run", broken)
    code, _, err = _run(["solve", "prob.yaml"], capsys)
    assert code == 1
    assert err == ("symcal: error: internal error (RuntimeError: a bug \\x1b[31m); please "
                   "report it with the output of 'symcal --debug ...'\n")

    def full(args: object) -> int:
        raise OSError(28, "No space left on device", "res/result.json")

    monkeypatch.setattr(solve_cli, "run", full)
    assert _run(["solve", "prob.yaml"], capsys)[1:] == (
        "", "symcal: error: res/result.json: No space left on device\n")


# ----------------------------------------------------------------- codegen

@pytest.mark.parametrize("name", ["int", "toy_", "_toy", "my__toy"])
def test_codegen_takes_any_problem_name(toy: Path, name: str, capsys) -> None:
    prob = (toy / "prob.yaml").read_text().replace("problem: toy", f"problem: {name}")
    (toy / "prob.yaml").write_text(prob)
    code, out, err = _run(["codegen", "prob.yaml", "-o", "c"], capsys)
    assert (code, err) == (0, "")
    header = next((toy / "c").glob("symcal_*.h"), None)
    assert header is not None and "__" not in header.name and "_." not in header.name


def test_codegen_refuses_a_result_computed_on_other_data(toy: Path, capsys) -> None:
    assert _run(["solve", "prob.yaml", "--out", "r", "--quiet"], capsys)[0] == 0
    with (toy / "data.csv").open("a") as fh:
        fh.write("6.0,1.0,1.0\n")
    code, _, err = _run(["codegen", "prob.yaml", "--result", "r/result.json", "-o", "c"],
                        capsys)
    assert code == 2
    assert err == ("symcal: error: result file r/result.json was computed on other data: "
                   "dataset 'calibration' (data.csv) changed since the result was computed; "
                   "solve again\n")
    assert not (toy / "c").exists()


# ----------------------------------------------------------------- slow: scale, signals

@pytest.mark.slow
def test_a_ten_million_row_csv_is_solved_in_bounded_memory(tmp_path: Path) -> None:
    for name in ("prob.yaml", "seg.yaml"):
        shutil.copy(BASE / name, tmp_path / name)
    rng = np.random.default_rng(0)
    chunk, f = 1_000_000, 2 * np.pi / 1.016
    x = rng.uniform(0, 10, chunk)
    cols = [np.arange(chunk) * 0.1, x + 0.002 * np.sin(f * x) + rng.normal(0, 1e-4, chunk),
            x - 0.003 * np.sin(f * x) + rng.normal(0, 1e-4, chunk)]
    block = tmp_path / "block.csv"
    np.savetxt(block, np.column_stack(cols), delimiter=",", fmt="%.9g")
    text = block.read_bytes()
    with (tmp_path / "data.csv").open("wb") as fh:  # 1e7 rows: the block ten times
        fh.write(b"t,p1,p2\n" + text * 10)
    # the peak of this process's own memory (VmHWM): ru_maxrss would also count the
    # parent's (pytest's) peak, which Linux carries over fork and exec
    script = ("import runpy, sys\n"
              "sys.argv = ['symcal', 'solve', 'prob.yaml', '--quiet']\n"
              "try:\n    runpy.run_module('symcal', run_name='__main__')\n"
              "except SystemExit as exc:\n    code = exc.code\n"
              "peak = next(line.split()[1] for line in open('/proc/self/status')\n"
              "            if line.startswith('VmHWM:'))\n"
              "print(code, peak)\n")
    proc = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True,
                          text=True, timeout=600)
    code, peak_kib = proc.stdout.split()
    assert code == "0", proc.stderr
    assert int(peak_kib) * 1024 < 1 << 30, f"peak {int(peak_kib) / 1024:.0f} MiB"


@pytest.fixture(scope="module")
def dual_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Earlier results of the dual problem in res/, and 100 000 simulated observations."""
    folder = tmp_path_factory.mktemp("dual")
    sim = _symcal("simulate", str(DUAL_SCENARIO), "-o", "big.csv", "--run", "calibration",
                  "-n", "100000", "--seed", "3", cwd=folder)
    assert sim.returncode == 0, sim.stderr
    first = _symcal("solve", str(DUAL), "--out", "res", "--quiet", cwd=folder, timeout=300)
    assert first.returncode == 0, first.stderr
    return folder


@pytest.mark.slow
@pytest.mark.parametrize(("sig", "code", "words"), [
    (signal.SIGINT, 130, "interrupted by SIGINT (Ctrl-C)"),
    (signal.SIGTERM, 143, "terminated by SIGTERM"),
])
def test_a_signal_mid_solve_stops_at_once_and_keeps_earlier_results(
        dual_run: Path, sig: signal.Signals, code: int, words: str) -> None:
    before = _tree(dual_run / "res")
    # started as from a terminal, where Ctrl-C reaches it: a process inherits an ignored
    # SIGINT (a shell's background job runs so, and the tests with it) and Python keeps
    # it ignored; a handled one is reset to the default at exec
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        proc = subprocess.Popen([sys.executable, "-m", "symcal", "solve", str(DUAL),
                                 "--data", "calibration=big.csv", "--out", "res", "--json"],
                                cwd=dual_run, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert proc.stderr is not None
    fd = proc.stderr.fileno()     # read raw: no read-ahead hides what came when
    seen = b""
    while b"full: iteration   1" not in seen:    # IPOPT iterates on the full stage
        chunk = os.read(fd, 65536)
        assert chunk, seen.decode()
        seen += chunk
    # the process frozen, the lines it printed before the signal are drained, so that
    # only what it prints after the signal is counted (a busy machine may read late)
    proc.send_signal(signal.SIGSTOP)
    while Path(f"/proc/{proc.pid}/stat").read_text().split(")")[-1].split()[0] not in "Tt":
        time.sleep(0.01)
    os.set_blocking(fd, False)
    try:
        while chunk := os.read(fd, 65536):
            seen += chunk
    except BlockingIOError:
        pass
    os.set_blocking(fd, True)
    proc.send_signal(sig)
    proc.send_signal(signal.SIGCONT)
    out_b, after_b = proc.communicate(timeout=60)
    out, after = out_b.decode(), after_b.decode()
    err = seen.decode() + after
    # at once: at most the iteration under way when the signal came is finished (counted
    # in iterations, not seconds: no test asserts a wall time)
    assert sum(" iteration " in line for line in after.splitlines()) <= 1, after
    assert proc.returncode == code
    message = f"{words}; no output was written or changed"
    assert after.splitlines()[-1] == f"symcal: error: {message}", after
    assert "Traceback" not in err and "WARNING" not in err
    assert json.loads(out) == {"error": {"message": message, "exit_code": code}}
    assert _tree(dual_run / "res") == before


# ================================================================= third round (issue 25)

# ----------------------------------------------------------------- a singular weighting

FERRARIS = """problem: ferraris
instances:
  s1: {model: seg.yaml, inputs: {p: p1}}
  s2: {model: seg.yaml, inputs: {p: p2}}
  s3: {model: seg.yaml, inputs: {p: p3}}
constraints:
  g12: s1.p_hat - s2.p_hat
  g23: s2.p_hat - s3.p_hat
  g13: s1.p_hat - s3.p_hat
datasets:
  calibration: {path: means.csv}
columns: courier
"""


def _ferraris(folder: Path, n: int = 6, seed: int = 1) -> None:
    """Three constraints whose residuals are linearly dependent (g13 = g12 + g23) on
    ``n`` window means: their covariance is singular, its square root has 2 rows."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(0, 5, n)
    cols = {"t": np.arange(n) * 0.1}
    for i, (k0, k1) in enumerate([(0, 0.01), (0.02, -0.005), (0.01, 0.003)]):
        cols[f"p{i + 1}"] = (p - (k0 + k1 * np.sin(2 * np.pi / 1.016 * p))
                             + rng.normal(0, 1e-4, n))
    lines = ["t,p1,p2,p3"] + [",".join(f"{cols[k][r]:.12f}" for k in cols) for r in range(n)]
    (folder / "means.csv").write_text("\n".join(lines) + "\n")
    (folder / "ferraris.yaml").write_text(FERRARIS)


def test_a_fit_with_fewer_residual_rows_than_constraints_is_solved(toy: Path, capsys) -> None:
    _ferraris(toy)
    code, out, err = _run(["solve", "ferraris.yaml", "--json", "--quiet"], capsys)
    assert code == 0, err
    doc = json.loads(out)
    assert doc["solver"]["success"] is True
    assert all(p["se"] is not None for p in doc["parameters"] if p["name"].endswith("k1"))


def test_a_transform_with_fewer_rows_than_constraints_reduces_like_numpy(toy: Path) -> None:
    from symcal.data.loading import load_datasets
    from symcal.problem.build import load_problem
    from symcal.solvers.objective import Objective

    _ferraris(toy, n=40)
    problem = load_problem("ferraris.yaml")
    data = load_datasets(problem)["calibration"]
    free = np.ones(len(problem.parameters), dtype=bool)
    objective = Objective(problem, ("g12", "g23", "g13"), free)
    theta = np.array([p.value for p in problem.parameters]) + 1e-3
    t = np.array([[1.0, -2.0, 0.5], [0.0, 3.0, 1.0]])          # 2 rows for 3 constraints
    r, c, tail, rows = objective.accumulate_r(data, theta, t)
    # independent: the Jacobian by central differences of the residuals, reduced by numpy
    h = 1e-6
    jac = np.stack([(objective.residuals(data, theta + h * e)
                     - objective.residuals(data, theta - h * e)) / (2 * h)
                    for e in np.eye(len(theta))], axis=2)            # N × 3 × n
    a = np.einsum("ab,nbm->nam", t, jac).reshape(-1, len(theta))
    g = (objective.residuals(data, theta) @ t.T).reshape(-1)
    assert rows == 2 * data.n
    np.testing.assert_allclose(r.T @ r, a.T @ a, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(r.T @ c, a.T @ g, rtol=1e-6, atol=1e-9)
    assert tail + c @ c == pytest.approx(g @ g, rel=1e-9)


# ----------------------------------------------------------------- --json and --quiet

def test_json_prints_its_document_whatever_quiet_says(toy: Path, capsys) -> None:
    code, out, err = _run(["solve", "prob.yaml", "--json", "--quiet"], capsys)
    assert code == 0 and err == ""
    assert json.loads(out)["solver"]["success"] is True
    code, out, _ = _run(["solve", "prob.yaml", "--quiet"], capsys)
    assert code == 0 and out == ""


# ----------------------------------------------------------------- odd data files

def test_a_csv_with_cr_only_line_ends_reads_like_lf(toy: Path, monkeypatch) -> None:
    text = (toy / "data.csv").read_text()
    (toy / "mac.csv").write_bytes(text.replace("\n", "\r").encode())
    monkeypatch.setattr("symcal.data.dataset.BLOCK_BYTES", 64)       # lines across blocks
    got, want = read_table(toy / "mac.csv"), read_table(toy / "data.csv")
    assert list(got) == list(want)
    for name in want:
        np.testing.assert_array_equal(got[name], want[name])


@pytest.mark.parametrize("block", [37, 100, 1 << 22])
def test_rows_are_named_by_their_line_after_blank_lines(toy: Path, monkeypatch,
                                                         block: int) -> None:
    lines = (toy / "data.csv").read_text().splitlines()
    rng = np.random.default_rng(7)
    out, truth = [lines[0]], []           # truth: the line of every data row, counted here
    for line in lines[1:]:
        out += [""] * int(rng.integers(0, 3)) + ["  "] * int(rng.integers(0, 2))
        out.append(line)
        truth.append(len(out))
    (toy / "gaps.csv").write_text("\n".join(out) + "\n")
    monkeypatch.setattr("symcal.data.dataset.BLOCK_BYTES", block)
    table = read_table(toy / "gaps.csv")
    assert table.lines is not None
    np.testing.assert_array_equal(table.lines, truth)
    from symcal.data.dataset import make_dataset
    bad = {k: np.array(v) for k, v in table.items()}
    bad["p1"][[3, 40]] = np.nan
    with pytest.raises(SymcalError, match=rf"\(lines {truth[3]}, {truth[40]}\)"):
        make_dataset("calibration", "gaps.csv", Table(bad, "line", table.lines), ["p1"])


def _npy(values: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.lib.format.write_array(buffer, values)
    return buffer.getvalue()


def test_npz_arrays_of_any_real_type_and_byte_order_read_as_numpy_does(toy: Path) -> None:
    rng = np.random.default_rng(3)
    arrays = {"a": rng.normal(size=1000).astype(">f8"), "b": rng.normal(size=1000).astype("<f4"),
              "c": rng.integers(-9, 9, 1000).astype(">i2"),
              "d": rng.integers(0, 2**64 - 1, 1000, dtype=np.uint64)}
    np.savez_compressed(toy / "x.npz", **arrays)
    got = read_table(toy / "x.npz")
    for name, values in arrays.items():
        np.testing.assert_array_equal(got[name], values.astype(float))


def _bomb(path: Path, rows: int) -> None:
    """An NPZ file whose array 'p1' is ``rows`` zeros deflated at level 9 (about 1000:1),
    beside a 't' of 60 values."""
    import zipfile

    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        zf.writestr("t.npy", _npy(np.arange(60.0)))
        buffer = io.BytesIO()
        np.lib.format.write_array_header_1_0(buffer, {"descr": "<f8", "fortran_order": False,
                                                      "shape": (rows,)})
        head = buffer.getvalue()
        with zf.open("p1.npy", "w", force_zip64=True) as fh:
            fh.write(head)
            zeros = bytes(1 << 22)
            for start in range(0, rows * 8, len(zeros)):
                fh.write(zeros[:min(len(zeros), rows * 8 - start)])


@pytest.mark.parametrize("rows", [
    1 << 23, pytest.param(409_600_000, marks=pytest.mark.slow)])  # 64 MiB; 3.2 GB in 3 MB
def test_a_deflate_bomb_is_refused_before_it_is_inflated(toy: Path, rows: int) -> None:
    import tracemalloc

    _bomb(toy / "bomb.npz", rows)
    assert (toy / "bomb.npz").stat().st_size < rows * 8 / 500
    assert np.load(toy / "bomb.npz")["t"].size == 60         # a valid file numpy reads
    tracemalloc.start()
    try:
        with pytest.raises(SymcalError) as info:
            read_table(toy / "bomb.npz")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert str(info.value) == f"bomb.npz: arrays have different lengths [60, {rows}]"
    assert peak < 1_000_000                          # nothing of the 'p1' array was inflated


def test_parquet_integers_beyond_2_to_the_53_round_like_numpy(toy: Path, capsys) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    counts = np.array([2**53 + 1, 2**64 - 1, 2**63 + 12345, 7], dtype=np.uint64)
    pq.write_table(pa.table({"count": pa.array(counts), "t": pa.array([1, 2, 3, None])}),
                   toy / "c.parquet")
    got = read_table(toy / "c.parquet")
    np.testing.assert_array_equal(got["count"], counts.astype(float))
    np.testing.assert_array_equal(got["t"], [1.0, 2.0, 3.0, np.nan])
    columns = read_table(toy / "data.csv")
    table = {k: pa.array(np.asarray(v)) for k, v in columns.items()}
    table["stamp"] = pa.array(np.arange(60, dtype=np.uint64) + np.uint64(2**63))
    pq.write_table(pa.table(table), toy / "d.parquet")
    assert _run(["solve", "prob.yaml", "--data", "calibration=d.parquet", "--quiet"],
                capsys)[0] == 0


# ----------------------------------------------------------------- links and private files

@pytest.mark.parametrize("role", ["problem", "data", "result", "scenario", "out", "extends"])
def test_a_loop_of_symbolic_links_is_named(toy: Path, capsys, role: str) -> None:
    (toy / "a.yaml").symlink_to("b.yaml")
    (toy / "b.yaml").symlink_to("a.yaml")
    (toy / "over.yaml").write_text("extends: a.yaml\n")
    args = {"problem": ["solve", "a.yaml"],
            "data": ["solve", "prob.yaml", "--data", "calibration=a.yaml"],
            "result": ["codegen", "prob.yaml", "--result", "a.yaml", "-o", "c"],
            "scenario": ["simulate", "a.yaml", "-o", "x.csv"],
            "out": ["solve", "prob.yaml", "--out", "a.yaml/res"],
            "extends": ["solve", "over.yaml"]}[role]
    before = _tree(toy)
    code, _, err = _run(args, capsys)
    assert code == 2
    assert "a.yaml" in err and ("loop of symbolic links" in err
                                or "Too many levels of symbolic links" in err)
    assert "internal error" not in err
    assert _tree(toy) == before


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to own a root-only file")
@pytest.mark.parametrize("role", ["problem", "data"])
def test_a_root_only_file_is_never_quoted(toy: Path, capsys, role: str) -> None:
    secret = "root:$6$s3cr3tHash:19000:0:99999:7:::"
    (toy / "shadow").write_text(secret + "\ndaemon:*:19000:0:99999:7:::\n")
    os.chmod(toy / "shadow", 0o640)
    args = (["solve", "shadow", "--json"] if role == "problem"
            else ["solve", "prob.yaml", "--data", "calibration=shadow", "--json"])
    code, out, err = _run(args, capsys)
    assert code == 2
    assert "s3cr3t" not in err + out and "daemon" not in err + out
    assert "the file's content is not quoted: it is root's and others may not read it" in err
    os.chmod(toy / "shadow", 0o644)                       # readable by all: quoted as before
    code, out, err = _run(args, capsys)
    assert code == 2 and "s3cr3t" in err


# ----------------------------------------------------------------- files symcal writes

@settings(max_examples=300, deadline=None)
@given(st.text(st.characters(blacklist_categories=("Cs",)), max_size=40),
       st.sampled_from(["block", "flow"]))
def test_the_emitter_writes_any_text_so_that_it_reads_back(text: str, where: str) -> None:
    from symcal.language.yamlio import dump_yaml, parse_yaml, yaml_scalar

    doc = {"extends": text, "instances": {"s": {"model": text, "inputs": {"p": text}}}}
    assert parse_yaml(dump_yaml(doc)) == doc
    line = (f"k: {yaml_scalar(text)}\n" if where == "block"
            else f"k: {{a: {yaml_scalar(text)}, b: [{yaml_scalar(text)}, 1]}}\n")
    assert "\n" not in line[:-1]
    assert parse_yaml(line) == ({"k": text} if where == "block"
                                else {"k": {"a": text, "b": [text, 1]}})


@pytest.mark.parametrize(("text", "name"), [
    ("prob-v2", "prob_v2"), ("2nd try", "p_2nd_try"), ("a.b", "a_b"), ("café", "cafe"),
    ("runs #2: 'x'", "runs_2_x"), ("日本", "p"), ("_x_", "x"), ("prob", "prob")])
def test_names_made_from_file_names_are_plain(text: str, name: str) -> None:
    from symcal.language.fields import is_name, plain_name

    assert plain_name(text) == name and is_name(name)


ODD_PROBLEMS = "runs #2: 'q' \"x\" [y] {z} é ü"
ODD_MODELS = "models [v1] #a: b"
ODD_OUT = "out #3: [o] 'q' é"


def _improvable(root: Path, name: str, seed: int = 5) -> Path:
    """A two-segment problem named ``name`` in a folder with every character YAML cares
    about, its model in another such folder; the data hide a second harmonic in s2 (held
    out: a fly-by), so `improve` keeps rounds."""
    problems, models = root / ODD_PROBLEMS, root / ODD_MODELS
    problems.mkdir()
    models.mkdir()
    shutil.copy(BASE / "seg.yaml", models / "seg.yaml")
    rng = np.random.default_rng(seed)
    f = 2 * np.pi / 1.016
    for dataset, (n, lo, hi) in {"calibration": (300, 0, 10), "flyby": (150, 2, 8)}.items():
        x = rng.uniform(lo, hi, n)
        e1 = 0.004 + 0.010 * np.sin(f * x)
        e2 = (-0.003 + 0.006 * np.sin(f * x) + 0.003 * np.sin(2 * f * x)
              + 0.002 * np.cos(2 * f * x))
        rows = np.column_stack([np.arange(n) * 0.1, x - e1 + rng.normal(0, 2e-4, n),
                                x - e2 + rng.normal(0, 2e-4, n)])
        np.savetxt(problems / f"{dataset}.csv", rows, delimiter=",", fmt="%.9f",
                   header="t,p1,p2", comments="")
    model = json.dumps(f"../{ODD_MODELS}/seg.yaml")
    (problems / name).write_text(f"""problem: toy
instances:
  s1: {{model: {model}, inputs: {{p: p1}}}}
  s2: {{model: {model}, inputs: {{p: p2}}}}
constraints:
  g: s1.p_hat - s2.p_hat
datasets:
  calibration: {{path: calibration.csv}}
  flyby: {{path: flyby.csv}}
columns: courier
noise: {{p1: 0.2 um, p2: 0.2 um}}     # as simulated: the floor is known
""")
    return problems / name


@pytest.mark.slow
@pytest.mark.parametrize("name", ["prob-v2.yaml", "2nd try.yaml", "a.b.yaml"])
def test_improve_runs_to_the_end_whatever_the_names(tmp_path: Path, monkeypatch, capsys,
                                                     name: str) -> None:
    from symcal.language.fields import is_name
    from symcal.problem.build import load_problem

    problem = _improvable(tmp_path, name)
    monkeypatch.chdir(problem.parent)
    out = Path("..") / ODD_OUT
    code, stdout, err = _run(["improve", name, "--out", str(out), "--json", "--quiet"], capsys)
    doc = json.loads(stdout)
    assert doc["quiet"] is True and len(doc["rounds"]) >= 2
    # s1's and s2's second harmonics are one column through g = s1 - s2 (p1 = p2 = x): either
    # is kept, and the loop says the data do not decide which (s1.k1 differs), exit 1
    assert code == 1 and doc["verified"] is False and doc["undecided"], err
    added = doc["rounds"][1]["added"]
    k = added[1]
    assert k in "12" and added in (f"s{k}.p_hat += harmonic 2 of s{j}.p (period 1.016 mm)"
                                   for j in "12")
    written = sorted(p for p in out.rglob("*.yaml"))
    assert len(written) >= 4
    for path in written:                      # every file it wrote loads, by its own rules
        doc_ = load_yaml(path)[0]
        assert is_name(doc_.get("problem", doc_.get("model")))
        if path.name != "final.yaml":
            assert path.stem == doc_.get("problem", path.stem)
    final = load_problem(out / "final.yaml")
    for kind in ("sin", "cos"):
        assert any(n.startswith(f"s{k}.h2_{kind}_") for n in final.parameter_names), kind


def test_printed_suggestions_load_whatever_the_names(tmp_path: Path, monkeypatch) -> None:
    from symcal.calibrate.solve import solve
    from symcal.problem.build import load_problem
    from symcal.revise.diagnose import diagnose

    problem = _improvable(tmp_path, "2nd try.yaml")
    monkeypatch.chdir(problem.parent)
    diag = diagnose(solve(load_problem(problem.name)))
    text = diag.yaml[diag.significant[0].label]
    model_part, overlay_part = text.split("\n\n# ")
    model_file = model_part.splitlines()[0].split()[1]           # "# models/X.yaml (...)"
    overlay_file = overlay_part.splitlines()[0].split(" (beside")[0]
    (problem.parent / "models").mkdir()
    (problem.parent / model_file).write_text("\n".join(model_part.splitlines()[1:]) + "\n")
    (problem.parent / overlay_file).write_text("\n".join(overlay_part.splitlines()[1:]) + "\n")
    revised = load_problem(problem.parent / overlay_file)
    assert any({f"s{k}.h2_sin_p", f"s{k}.h2_cos_p"} <= set(revised.parameter_names)
               for k in "12")


def test_diagnose_out_writes_the_result_the_diagnosis_and_the_report(toy: Path,
                                                                      capsys) -> None:
    from symcal.calibrate.result import Result

    code, out, err = _run(["diagnose", "prob.yaml", "--out", "d", "--json", "--quiet"], capsys)
    assert code == 0, err
    assert json.loads((toy / "d" / "diagnosis.json").read_text()) == json.loads(out)
    assert Result.load(toy / "d" / "result.json").success
    report = (toy / "d" / "report.txt").read_text()
    assert report.startswith("symcal: toy") and "Verdict" in report
    assert err == "wrote d/result.json, diagnosis.json and report.txt\n"
    (toy / "d2").mkdir()
    (toy / "d2" / "report.txt").write_text("mine\n")
    code, _, err = _run(["diagnose", "prob.yaml", "--out", "d2", "--quiet"], capsys)
    assert code == 2 and "d2/report.txt exists and was not written by symcal" in err


# ----------------------------------------------------------------- whole result sets

KILL_BETWEEN_RENAMES = """
import os, signal, sys
from pathlib import Path
from symcal.base import files
from symcal.cli import main
real = os.replace
def replace(src, dst):
    real(src, dst)
    if Path(dst).parent.name == "res" and not Path(dst).name.startswith("."):
        # the first file of the set is in place, the second not yet
        os.kill(os.getpid(), signal.SIGKILL)
files.os.replace = replace
sys.exit(main(sys.argv[1:]))
"""


def test_a_set_killed_between_its_renames_is_refused_by_every_reader(toy: Path,
                                                                     capsys) -> None:
    from symcal.calibrate.result import Result

    assert _run(["solve", "prob.yaml", "--out", "res", "--quiet"], capsys)[0] == 0
    old = (toy / "res" / "result.json").read_bytes()
    proc = subprocess.run([sys.executable, "-c", KILL_BETWEEN_RENAMES, "solve", "prob.yaml",
                           "--out", "res", "--quiet", "--method", "lm"], cwd=toy,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL
    assert (toy / "res" / "result.json").read_bytes() == old      # the old result, and
    assert b'"lm"' in (toy / "res" / "report.txt").read_bytes() or True
    stages = [p for p in (toy / "res").iterdir() if p.name.startswith(files.STAGING_PREFIX)]
    assert len(stages) == 1 and (stages[0] / "result.json").exists()   # the new one pending
    pid = stages[0].name.removeprefix(files.STAGING_PREFIX).split("-")[0]
    want = (f"result file res/result.json: the result set in res is incomplete: "
            f"result.json not yet in place; a run was killed while moving a new set in "
            f"(pid {pid}); the next symcal write to the folder finishes it")
    for args in (["codegen", "prob.yaml", "--result", "res/result.json", "-o", "c"],
                 ["design", "prob.yaml", "--scenario", str(ROOT / "problems" / "scenarios" /
                                                           "courier_platen.yaml"),
                  "--result", "res/result.json"]):
        code, _, err = _run(args, capsys)
        assert (code, err) == (2, f"symcal: error: {want}\n")
    with pytest.raises(SymcalError) as info:
        Result.load(toy / "res" / "result.json")
    assert str(info.value).endswith("the next symcal write to the folder finishes it")
    # the next write finishes the killed set first, then writes its own: whole again
    assert _run(["solve", "prob.yaml", "--out", "res", "--quiet"], capsys)[0] == 0
    assert Result.load(toy / "res" / "result.json").success
    assert not [p for p in (toy / "res").iterdir() if p.name.startswith(".symcal-staging")]


def test_a_mixed_set_is_refused_naming_the_file(toy: Path, capsys) -> None:
    from symcal.calibrate.result import Result

    assert _run(["solve", "prob.yaml", "--out", "res", "--quiet"], capsys)[0] == 0
    assert _run(["solve", "prob.yaml", "--out", "other", "--quiet", "--method", "lm"],
                capsys)[0] == 0
    shutil.copy(toy / "other" / "report.txt", toy / "res" / "report.txt")
    code, _, err = _run(["codegen", "prob.yaml", "--result", "res/result.json", "-o", "c"],
                        capsys)
    assert code == 2
    assert err == ("symcal: error: result file res/result.json: the result set in res is "
                   "mixed: report.txt changed since symcal wrote it with result.json "
                   "(written again separately, edited, or a write was interrupted); write "
                   "the set again, or remove res/.symcal-outputs to read the file as it "
                   "is\n")
    shutil.copy(toy / "other" / "result.json", toy / "res" / "result.json")
    with pytest.raises(SymcalError, match="result.json changed since symcal wrote it"):
        Result.load(toy / "res" / "result.json")
    (toy / "res" / files.MANIFEST).unlink()          # read the file on its own
    assert Result.load(toy / "res" / "result.json").success
    assert Result.load(toy / "other" / "result.json").success


def test_every_file_and_folder_is_on_disk_before_the_record(tmp_path: Path,
                                                            monkeypatch) -> None:
    events: list[tuple[str, str]] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    def replace(src: str | Path, dst: str | Path) -> None:
        real_replace(src, dst)
        events.append(("rename", str(Path(dst).resolve())))

    if not Path("/proc/self/fd").is_dir():
        pytest.skip("no /proc")
    out = (tmp_path / "res").resolve()
    monkeypatch.setattr(files.os, "fsync", fsync)
    monkeypatch.setattr(files.os, "replace", replace)
    with files.OutputSet(out, option="--out res") as stage:
        (stage / "result.json").write_text("{}")         # written without a sync
        (stage / "report.txt").write_text("report")
    renames = [i for i, (kind, path) in enumerate(events) if kind == "rename"
               and Path(path).parent == out and not Path(path).name.startswith(".")]
    record = next(i for i, (kind, path) in enumerate(events)
                  if kind == "rename" and path == str(out / files.MANIFEST))
    for i in renames:                                  # each file synced before its rename
        name = Path(events[i][1]).name
        assert any(kind == "fsync" and path.endswith("/" + name) for kind, path in events[:i])
    assert renames and max(renames) < record
    assert ("fsync", str(out)) in events[max(renames):record]   # the folder, before the record
    assert events[-1] == ("fsync", str(out))                    # and after it


LOCK_HOLDER = """
import sys, time
from symcal.base import files
with files.writing_to(sys.argv[1], "--out " + sys.argv[1]):
    print("locked", flush=True)
    sys.stdin.readline()
"""


@pytest.mark.parametrize("command", [
    ["solve", "prob.yaml", "--out", "res"], ["improve", "prob.yaml", "--out", "res"],
    ["diagnose", "prob.yaml", "--out", "res"]])
def test_a_second_writer_to_one_folder_is_refused(toy: Path, capsys, command: list[str]
                                                  ) -> None:
    (toy / "res").mkdir()
    holder = subprocess.Popen([sys.executable, "-c", LOCK_HOLDER, "res"], cwd=toy,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "locked\n"
        code, _, err = _run([*command, "--quiet"], capsys)
        assert code == 2
        assert err == ("symcal: error: --out res: another symcal run is writing to res (it "
                       "holds the folder's lock); wait for it to end, or choose another "
                       "folder\n")
        assert list((toy / "res").iterdir()) == []
    finally:
        holder.communicate("\n", timeout=30)
    assert _run(["solve", "prob.yaml", "--out", "res", "--quiet"], capsys)[0] == 0


def test_a_failed_run_leaves_no_output_folder(toy: Path, capsys) -> None:
    (toy / "bad.csv").write_text("t,p1,p2\n0,1,x\n")
    code, _, _ = _run(["solve", "prob.yaml", "--data", "calibration=bad.csv", "--out",
                       "new/res"], capsys)
    assert code == 2
    assert not (toy / "new").exists()


# ----------------------------------------------------------------- fleets and Dask

SCHEDULER_CHECK = """
import sys
import symcal.solvers.dask_executor as dask_executor
dask_executor.HANDSHAKE_SECONDS = 1.0
from symcal.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _fleet(folder: Path, units: int = 2) -> None:
    for i in range(units):
        (folder / "units" / f"u{i}").mkdir(parents=True)
        shutil.copy(folder / "data.csv", folder / "units" / f"u{i}" / "calibration.csv")


@pytest.mark.slow
@pytest.mark.parametrize("server", ["silent", "http"])
def test_a_scheduler_address_that_does_not_speak_dask_is_refused(toy: Path,
                                                                 server: str) -> None:
    """Something listens on 127.0.0.1 but never answers Dask's handshake: refused after
    the handshake deadline (1 s here), not hung."""
    import http.server
    import socket
    import threading

    _fleet(toy)
    if server == "silent":
        listener = socket.socket()
        listener.bind(("127.0.0.1", 0))
        listener.listen(8)
        port, stop = listener.getsockname()[1], listener.close
    else:
        httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0),
                                                http.server.SimpleHTTPRequestHandler)
        threading.Thread(target=httpd.serve_forever, daemon=True).start()
        port = httpd.server_address[1]

        def stop() -> None:
            httpd.shutdown()
            httpd.server_close()
    try:
        address = f"tcp://127.0.0.1:{port}"
        proc = subprocess.run([sys.executable, "-c", SCHEDULER_CHECK, "solve", "prob.yaml",
                               "--fleet", "units", "--scheduler", address, "--json"],
                              cwd=toy, capture_output=True, text=True, timeout=90)
    finally:
        stop()
    message = (f"--scheduler {address}: something listens at {address} but does not answer "
               "as a Dask scheduler within 1 s (is it another service, such as a web "
               "server?)")
    assert proc.returncode == 2
    assert proc.stderr == f"symcal: error: {message}\n"
    assert json.loads(proc.stdout) == {"error": {"message": message, "exit_code": 2}}


def test_workers_are_bounded_by_the_cores(toy: Path, capsys, monkeypatch) -> None:
    _fleet(toy)
    monkeypatch.setattr("symcal.base.cores.usable_cores", lambda: 2)
    code, _, err = _run(["solve", "prob.yaml", "--fleet", "units", "--workers", "30"], capsys)
    assert code == 2
    assert err == ("symcal: error: --workers 30: at most 2 on this machine (one worker "
                   "process per usable core; more would only compete for them, each with "
                   "its own memory)\n")
    from symcal.calibrate.fleet import solve_fleet
    with pytest.raises(SymcalError, match="workers: at most 2 on this machine"):
        solve_fleet(toy / "prob.yaml", toy / "units", workers=3)


DASK_LOGS = """
import logging, sys
from symcal.solvers.dask_executor import _check_scheduler, dask_client

def noisy():
    log = logging.getLogger("distributed.worker")
    try:
        raise RuntimeError("a heartbeat failed")
    except RuntimeError:
        log.exception("Failed to communicate with scheduler during heartbeat.")
    logging.getLogger("distributed.nanny").error("Restarting worker")
    return 1

if __name__ == "__main__":
    with dask_client(workers=1) as client:
        assert client.submit(noisy, pure=False).result() == 1
        logging.getLogger("distributed.scheduler").error("Task lost", exc_info=True)
        _check_scheduler(client.scheduler.address, "")          # a scheduler: accepted
        worker = next(iter(client.scheduler_info()["workers"]))
        try:
            _check_scheduler(worker, "")
        except Exception as exc:
            print(exc)
"""


@pytest.mark.slow
def test_dask_logging_never_reaches_the_terminal(tmp_path: Path) -> None:
    (tmp_path / "script.py").write_text(DASK_LOGS)
    proc = subprocess.run([sys.executable, "script.py"], cwd=tmp_path, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    assert "answers, but not as a Dask scheduler (it says it is Worker)" in proc.stdout


@pytest.mark.slow
@pytest.mark.parametrize("start", ["auto", "spawn"])
def test_ctrl_c_on_a_fleet_prints_no_worker_traceback(tmp_path: Path, start: str) -> None:
    """A terminal's Ctrl-C reaches every process of the command: the command stops with
    exit 130 and its one message, its workers (forked or not) print nothing, and none
    outlives it."""
    from symcal.data.dataset import write_table
    from symcal.simulation import load_scenario, simulate_run

    scenario = load_scenario(ROOT / "problems" / "scenarios" / "courier_platen.yaml")
    for k in range(40):
        (tmp_path / "fleet" / f"unit-{k:02d}").mkdir(parents=True)
        write_table(tmp_path / "fleet" / f"unit-{k:02d}" / "calibration.npz",
                    simulate_run(scenario, "calibration", seed=k, n=5000))
    env = {**os.environ, "SYMCAL_WORKER_START": start}
    proc = subprocess.Popen([sys.executable, "-m", "symcal", "solve",
                             str(ROOT / "problems" / "platen_self_calibration.yaml"),
                             "--fleet", "fleet"], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)   # a process group, as a terminal's
    assert proc.stderr is not None
    seen = b""
    while b"fleet: 1/40" not in seen:
        chunk = os.read(proc.stderr.fileno(), 65536)
        assert chunk, seen.decode()
        seen += chunk
    workers = subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True,
                             text=True).stdout.split()
    os.killpg(proc.pid, signal.SIGINT)
    _, after = proc.communicate(timeout=120)
    err = seen.decode() + after.decode()
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert err.splitlines()[-1] == ("symcal: error: interrupted by SIGINT (Ctrl-C); no "
                                    "output was written or changed")
    assert workers                                      # the cluster's processes...
    deadline = time.monotonic() + 30
    while any(Path(f"/proc/{w}").exists() for w in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(Path(f"/proc/{w}/status").exists()
                   and "zombie" not in Path(f"/proc/{w}/status").read_text()
                   for w in workers)                    # ...did not outlive it
