"""The benchmark harness runs end to end: ``benchmarks/run.py --quick`` (every job at a
tiny N, in fresh processes) exits 0, prints a row for each job and writes nothing."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
from conftest import ROOT

JOBS = ("starts", "assemble", "data", "profile", "blas", "solve")


@pytest.mark.slow
def test_quick_run_prints_every_job() -> None:
    results = ROOT / "benchmarks" / "RESULTS.md"
    before = results.stat().st_mtime_ns
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "run.py"), "--quick"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    out = proc.stdout
    for job in JOBS:
        row = re.search(rf"^\| {job} \| (\d+) \| (\d+) \| ", out, re.MULTILINE)
        assert row, (job, out[-2000:])
        assert int(row.group(1)) > 0 and int(row.group(2)) == 0, row.group(0)
    # one table row per method of each problem, none of them failed or skipped
    assert len(re.findall(r"^\| 200 \| ", out, re.MULTILINE)) == 9
    assert "**skipped**" not in out
    assert "nothing written" in out
    assert results.stat().st_mtime_ns == before
