"""Running an example's README walkthrough as written, for the examples' tests."""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from conftest import ROOT

from symcal.cli import main

CC = shutil.which("cc") or shutil.which("gcc")


def commands(readme: str) -> list[str]:
    """The command lines of a README's ``sh`` blocks, in order."""
    blocks = re.findall(r"```sh\n(.*?)```", readme, re.DOTALL)
    return [ln for block in blocks for ln in block.splitlines() if ln.strip()]


def run(readme: Path, tmp_path: Path, monkeypatch: Any, capsys: Any,
        codes: Mapping[str, int] | None = None) -> dict[str, str]:
    """Run every command of ``readme`` from a folder that sees the repository's
    ``examples/``, as a user at the repository root would; ``symcal`` through its
    ``main`` (exit code as in ``codes``, by the start of the line, else 0), the rest as
    processes that must succeed without warnings.  Returns each line's output."""
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    monkeypatch.chdir(tmp_path)
    outputs: dict[str, str] = {}
    for line in commands(readme.read_text()):
        argv = shlex.split(line)
        if argv[0] == "symcal":
            code = main(argv[1:])
            out = capsys.readouterr().out
            want = next((c for start, c in (codes or {}).items() if line.startswith(start)), 0)
            assert code == want, (line, code, out[-2000:])
        else:
            if argv[0] == "python":
                argv[0] = sys.executable
            if argv[0] == "make" and CC is None:
                break
            done = subprocess.run(argv, capture_output=True, text=True, timeout=300)
            assert done.returncode == 0, (line, done.stderr)
            assert "warning" not in done.stderr.lower()
            out = done.stdout
        outputs[line] = out
    return outputs


def text_blocks(readme: Path) -> list[str]:
    """The README's ``text`` blocks, in order."""
    return re.findall(r"```text\n(.*?)```", readme.read_text(), re.DOTALL)


def printed_residuals(example_output: str) -> dict[str, tuple[float, str]]:
    """``residual NAME = VALUE UNIT`` lines of a generated C example's output."""
    return {m[0]: (float(m[1]), m[2]) for m in
            re.findall(r"^residual\s+(\S+) = (\S+) (\S+)$", example_output, re.MULTILINE)}
