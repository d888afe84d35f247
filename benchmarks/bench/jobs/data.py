"""Job ``data``: ``symcal simulate`` at the largest N, then reading what it wrote."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from ..children import run_child
from ..config import PROBLEMS, ROOT, SEED, Run
from ..fmt import fmt_n, say
from ..measure import child_env
from .base import JobSummary

NAME = "data"


def child(job: dict[str, Any]) -> dict[str, Any]:
    """``symcal.data.dataset.read_table`` on the CSV and on the NPZ of the same table."""
    from symcal.data.dataset import read_table

    out: dict[str, Any] = {}
    for kind in ("csv", "npz"):
        start = time.perf_counter()
        cols = read_table(job[kind])
        out[kind] = time.perf_counter() - start
        out[f"{kind}_rows"] = len(next(iter(cols.values())))
        del cols
    return out


def simulate(ctx: Run, suffix: str, n: int) -> dict[str, Any]:
    """The whole ``symcal simulate`` command (interpreter start included) to ``suffix``."""
    target = ctx.workdir / f"simulated.{suffix}"
    cmd = [sys.executable, "-m", "symcal", "simulate",
           str(ROOT / PROBLEMS["dual"]["scenario"]), "-o", str(target), "-n", str(n),
           "--run", "calibration", "--seed", str(SEED)]
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT,
                          env=child_env(ctx.settings.blas_threads))
    return {"seconds": time.perf_counter() - start, "ok": proc.returncode == 0,
            "error": proc.stderr.strip()[-300:], "path": str(target),
            "bytes": target.stat().st_size if target.exists() else 0}


def run(ctx: Run) -> JobSummary:
    """Simulate to NPZ and CSV at the largest N, and read both back in a child."""
    big = max(ctx.settings.sizes)
    sim = {suffix: simulate(ctx, suffix, big) for suffix in ("npz", "csv")}
    ctx.report["simulate"] = sim
    note = (f"symcal simulate, N={fmt_n(big)}: "
            + ", ".join(f"{k} {v['seconds']:.2f} s" for k, v in sim.items()))
    say("== " + note)
    failures = [f"simulate to {k}: {v['error']}" for k, v in sim.items() if not v["ok"]]
    processes = len(sim)
    if not failures:
        read = run_child({"kind": NAME, "csv": sim["csv"]["path"],
                          "npz": sim["npz"]["path"]}, ctx.settings, timeout=600)
        ctx.report["read"] = read
        processes += 1
        if "error" in read:
            failures.append(f"read: {read['error']}")
        line = (f"read_table, N={fmt_n(big)}: csv {read.get('csv', float('nan')):.2f} s, "
                f"npz {read.get('npz', float('nan')):.3f} s")
        say("== " + line)
        note += f"; {line}"
    for suffix in ("npz", "csv"):
        Path(sim[suffix]["path"]).unlink(missing_ok=True)
    return JobSummary(NAME, processes, failures, note)
