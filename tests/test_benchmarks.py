"""The benchmark harness runs end to end: ``benchmarks/run.py --quick`` (every job at a
tiny N, in fresh processes) exits 0, prints a row for each job and writes nothing."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
from conftest import ROOT

JOBS = ("starts", "startup", "assemble", "data", "profile", "blas", "fleet", "hugelog",
        "solve")
BENCHMARKS = ROOT / "benchmarks"


def _bench_cli():
    if str(BENCHMARKS) not in sys.path:
        sys.path.insert(0, str(BENCHMARKS))
    from bench import cli

    return cli


def test_quick_settings_and_job_order() -> None:
    """--quick: tiny sizes, one run, nothing written unless --out; the jobs in order."""
    cli = _bench_cli()
    quick = cli.settings_from(cli.parse_args(["--quick"]))
    assert (quick.sizes, quick.repeats, quick.out, quick.quick) == ((200,), 1, None, True)
    assert cli.settings_from(cli.parse_args(["--quick", "--out", "x.md"])).out.name == "x.md"
    full = cli.settings_from(cli.parse_args([]))
    assert full.sizes == (1_000, 10_000, 100_000, 1_000_000)
    assert full.out == BENCHMARKS / "RESULTS.md"
    assert tuple(job.NAME for job in cli.JOBS) == JOBS


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
    # one table row per method of each problem (5 linear, 6 dual), none failed or skipped
    assert len(re.findall(r"^\| 200 \| ", out, re.MULTILINE)) == 11
    assert "**skipped**" not in out
    assert "nothing written" in out
    assert results.stat().st_mtime_ns == before
