"""The bad-input corpus: every case gets its exact message and exit code, no traceback.

Each folder under tests/bad_inputs/ holds the files of one case, ``args`` (the command
line after ``symcal``, run from that folder) and ``expected``: ``exit N`` on the first
line, then the exact text on stderr; a line ``stdout: TEXT`` asks for a line of stdout
instead (failed solves print their report there).
"""

from __future__ import annotations

import hashlib
import shlex
from pathlib import Path

import pytest

from symcal.cli import main

CORPUS = Path(__file__).parent / "bad_inputs"
CASES = sorted(p.name for p in CORPUS.iterdir() if p.is_dir())


def test_corpus_is_large_enough() -> None:
    assert len(CASES) >= 100


def _snapshot(folder: Path) -> dict[str, str]:
    """Every file below ``folder`` (hidden ones too) and the sha256 of its content."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("case", CASES)
def test_bad_input(case: str, monkeypatch, capsys) -> None:
    folder = CORPUS / case
    monkeypatch.chdir(folder)
    args = shlex.split((folder / "args").read_text())
    lines = (folder / "expected").read_text().splitlines()
    code = int(lines[0].split()[1])
    want_stdout = [ln[len("stdout: "):] for ln in lines[1:] if ln.startswith("stdout: ")]
    want_stderr = [ln for ln in lines[1:] if not ln.startswith("stdout: ")]
    before = _snapshot(folder)
    try:
        got = main(args)
    except SystemExit as exc:  # argparse usage errors
        got = exc.code
    out = capsys.readouterr()
    assert got == code
    assert "Traceback" not in out.err
    assert out.err.splitlines() == want_stderr
    for line in want_stdout:
        assert line in out.out.splitlines()
    if code == 2:  # refused: not a file of the case was written, changed or left behind
        assert _snapshot(folder) == before


def test_drop_invalid_drops_and_reports(monkeypatch, capsys) -> None:
    monkeypatch.chdir(CORPUS / "nan_rows")
    assert main(["solve", "prob.yaml", "--drop-invalid"]) == 0
    out = capsys.readouterr().out
    assert "59 observations  data.csv (1 invalid rows dropped)" in out


def test_out_never_overwrites_an_input(tmp_path, monkeypatch, capsys) -> None:
    for name in ("seg.yaml", "prob.yaml"):
        (tmp_path / name).write_text((CORPUS / "nan_rows" / name).read_text())
    (tmp_path / "res").mkdir()
    data = (CORPUS / "unknown_unit" / "data.csv").read_text()
    (tmp_path / "res" / "report.txt").write_text(data)
    monkeypatch.chdir(tmp_path)
    assert main(["solve", "prob.yaml", "--data", "calibration=res/report.txt", "--out",
                 "res"]) == 2
    assert capsys.readouterr().err == ("symcal: error: --out res: refusing to overwrite input "
                                       "file res/report.txt\n")
    assert (tmp_path / "res" / "report.txt").read_text() == data
