"""The benchmark harness runs end to end: ``benchmarks/run.py --quick`` (every job at a
tiny N, in fresh processes) exits 0, prints a row for each job and writes nothing."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
from conftest import ROOT

JOBS = ("starts", "startup", "assemble", "data", "profile", "blas", "fleet", "hugelog",
        "improve", "solve")
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
    # a guard against a hang, not a time limit: the quick run takes 2.4 min alone on 2
    # slow cores (2026-11-29) and more beside the suite's other worker on a busy machine
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "run.py"), "--quick"],
                          cwd=ROOT, capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    out = proc.stdout
    for job in JOBS:
        row = re.search(rf"^\| {job} \| (\d+) \| (\d+) \| ", out, re.MULTILINE)
        assert row, (job, out[-2000:])
        assert int(row.group(1)) > 0 and int(row.group(2)) == 0, row.group(0)
    # one table row per method of each problem (11 linear, 12 dual), none failed; the
    # exact-Jacobian peers are skipped only where the bench extra is not installed
    assert len(re.findall(r"^\| 200 \| ", out, re.MULTILINE)) == 23
    skipped = re.findall(r"\*\*skipped\*\*: (.*) \|$", out, re.MULTILINE)
    assert all(why.startswith("not installed") for why in skipped), skipped
    assert "nothing written" in out
    assert results.stat().st_mtime_ns == before


def test_a_partial_run_replaces_only_its_sections() -> None:
    """--jobs: the sections the run rendered replace theirs, the others stay, the targets
    are merged and the header says which sections are new."""
    _bench_cli()       # the benchmarks' folder on the path, whichever test ran first
    from bench.report import splice

    old = ("# symcal benchmarks\n\nProduced by `make bench` on 2026-01-01; it took 10 min.\n\n"
           "## Machine\n\n- old machine\n\n## Kept\n\nold kept\n\n## Redone: 1e6\n\nold\n\n"
           "## Targets\n\n| target | measured | verdict |\n|---|---|---|\n| a | 1 | met |\n"
           "| b | 2 | met |\n\n## Tail\n\nold tail\n\n## Late: x\n\nold late\n")
    new = ("# symcal benchmarks\n\nProduced by `run.py --jobs x` on 2026-02-02.\n\n"
           "## Machine\n\n- new machine\n\n## Redone: 1e3\n\nnew\n\n## Added\n\nnew too\n\n"
           "## Late: y\n\nnew late\n\n"
           "## Targets\n\n| target | measured | verdict |\n|---|---|---|\n| b | 3 | missed |\n")
    text = splice(old, new, {"date": "2026-02-02"})
    assert "old kept" in text and "old tail" in text and "\nold\n" not in text
    assert "## Redone: 1e3\n\nnew" in text and "new too" in text
    assert "- new machine" in text and "## Machine of the earlier run" in text
    assert "| b | 3 | missed |" in text and "| a | 1 | met (earlier run) |" in text
    assert "| b | 2 |" not in text
    assert text.index("## Added") < text.index("## Targets")
    # a section after the targets in the old file is replaced where it was, once
    assert text.count("## Late") == 1 and text.index("## Late: y") > text.index("old tail")
    assert "old late" not in text
    # a second partial run of the same sections: what the first kept is still from the
    # run before it, and says so (it was named after the first partial run)
    again = splice(text, new.replace("2026-02-02", "2026-03-03"), {"date": "2026-03-03"})
    assert "from the earlier run (produced by `make bench` on 2026-01-01)" in again
    assert "## Machine of the earlier run\n\n- old machine" in again
    assert again.count("## Machine") == 2 and "old kept" in again
    # a partial run of other sections after a partial run: the first partial run's
    # sections say they come from it, the rest is still from the run before both
    other = ("# symcal benchmarks\n\nProduced by `run.py --jobs z` on 2026-04-04.\n\n"
             "## Machine\n\n- newest machine\n- **symcal measured**: commit ccc\n\n"
             "## Kept\n\nkept anew\n\n"
             "## Targets\n\n| target | measured | verdict |\n|---|---|---|\n")
    third = splice(text.replace("- new machine", "- new machine\n- **symcal measured**: "
                                "commit bbb"), other, {"date": "2026-04-04"})
    assert "from the earlier run (produced by `make bench` on 2026-01-01)" in third
    assert "## Machine of the earlier run\n\n- old machine" in third
    assert ("## Redone: 1e3\n\n*This section comes from the partial run produced by "
            "`run.py --jobs x` on 2026-02-02: symcal measured: commit bbb.*") in third
    assert "## Added\n\n*This section comes from the partial run" in third
    assert "kept anew" in third and "old kept" not in third
    assert "## Kept\n\n*This section" not in third
