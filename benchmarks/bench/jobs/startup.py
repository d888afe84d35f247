"""Job ``startup``: the fixed cost a user sees, and the compiled functions made once.

* ``symcal --help`` and ``symcal solve`` of the bundled §3.1 problem (its own simulated
  data, ``--quiet``), whole commands in fresh processes, interpreter start included:
  the median of 5 and of 3 runs.
* The compiled twins of both problems' single-stage functions (``symcal.base.jit``), built
  once into the run's cache folder (``XDG_CACHE_HOME`` points into the run's temporary
  folder, see ``bench.cli``), as the first large solve of a problem on a machine builds
  them; the compile time is reported here, and every later job finds them in the cache.
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import time
from typing import Any

from ..children import run_child
from ..config import PROBLEMS, ROOT, Run
from ..fmt import say
from ..measure import child_env
from .base import JobSummary

NAME = "startup"
SOLVE = "problems/platen_self_calibration.yaml"


def child(job: dict[str, Any]) -> dict[str, Any]:
    """Compile (or load from the cache) both problems' single-stage functions."""
    import numpy as np

    from symcal.base import jit
    from symcal.solvers.objective import Objective

    from ..problems import single_stage_problem

    out: dict[str, Any] = {"compiler": jit.compiler(), "cache": str(jit.cache_dir())}
    for problem in PROBLEMS:
        prob = single_stage_problem(problem)
        stage = prob.stages[0]
        objective = Objective(prob, stage.constraints,
                              np.array([p.name in stage.free for p in prob.parameters]))
        for name, outputs in (("residual", [objective.g]),
                              ("linearised", [objective.g, objective.jac.T])):
            start = time.perf_counter()
            fast = jit.fast(objective._mapped(name, outputs), build=True)
            out[f"{problem}_{name}"] = {"seconds": time.perf_counter() - start,
                                        "compiled": isinstance(fast, jit.CompiledMapped)}
        start = time.perf_counter()
        _public_twins(problem, prob)
        out[f"{problem}_analysis"] = {"seconds": time.perf_counter() - start,
                                      "compiled": jit.compiler() is not None}
    return out


def _public_twins(problem: str, prob: Any) -> None:
    """One public solve on a few simulated rows with every function compiled
    (``SYMCAL_JIT=on``): the twins of the analysis around the solve (noise floors,
    series statistics, serial correlation) join the run's cache, as they do on a
    user's machine once their solves have evaluated enough observations."""
    import os

    import symcal
    from symcal.data.dataset import make_dataset
    from symcal.data.loading import load_datasets, needed_columns
    from symcal.simulation import load_scenario, simulate_run

    cols = simulate_run(load_scenario(ROOT / PROBLEMS[problem]["scenario"]), "calibration",
                        seed=3, n=500)
    data = make_dataset("calibration", "benchmark", cols, needed_columns(prob))
    before = os.environ.get("SYMCAL_JIT")
    os.environ["SYMCAL_JIT"] = "on"
    try:
        symcal.solve(prob, {**load_datasets(prob, {"calibration": data}), "calibration": data})
    finally:
        if before is None:
            del os.environ["SYMCAL_JIT"]
        else:
            os.environ["SYMCAL_JIT"] = before


def _command(args: list[str], ctx: Run, runs: int) -> dict[str, Any]:
    times, code = [], 0
    for _ in range(runs):
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "symcal", *args], capture_output=True,
                              cwd=ROOT, env=child_env(ctx.settings.blas_threads))
        times.append(time.perf_counter() - start)
        code = code or proc.returncode
    return {"seconds": statistics.median(times), "times": times, "exit": code}


#: What a ``symcal solve`` process spends before solving, each in a fresh interpreter.
PARTS = {
    "interpreter": "pass",
    "import symcal.calibrate.solve": "import symcal.calibrate.solve",
    "pint's unit registry": "from symcal.base.units import registry; registry()",
}


def _parts(ctx: Run) -> dict[str, float]:
    """Seconds of each of :data:`PARTS` (median of 3 fresh processes, start included)."""
    out = {}
    for label, code in PARTS.items():
        times = []
        for _ in range(3):
            start = time.perf_counter()
            subprocess.run([sys.executable, "-c", code], capture_output=True, cwd=ROOT,
                           env=child_env(ctx.settings.blas_threads))
            times.append(time.perf_counter() - start)
        out[label] = statistics.median(times)
    return out


def run(ctx: Run) -> JobSummary:
    """Time the two commands; compile the functions."""
    compiled = run_child({"kind": NAME}, ctx.settings, timeout=600)
    result = {"help": _command(["--help"], ctx, 5),
              "solve": _command(["solve", SOLVE, "--quiet"], ctx, 3), "jit": compiled,
              "parts": _parts(ctx)}
    ctx.report["startup"] = result
    failures = [f"{k} exited {v['exit']}" for k, v in result.items()
                if k in ("help", "solve") and v["exit"] != 0]
    if "error" in compiled:
        failures.append(f"compile: {compiled['error']}")
    note = (f"symcal --help {result['help']['seconds']:.2f} s, symcal solve §3.1 "
            f"{result['solve']['seconds']:.2f} s; compiled functions: " +
            ", ".join(f"{k} {v['seconds']:.2f} s" for k, v in compiled.items()
                      if isinstance(v, dict)))
    say("== " + note)
    return JobSummary(NAME, 1 + 8, failures, note)


def table(report: dict[str, Any]) -> list[str]:
    """The RESULTS.md section of the job (empty when it did not run)."""
    r = report.get("startup")
    if not r:
        return []
    lines = ["", "## Start-up and compiled functions", "",
             "| command (fresh process, interpreter start included) | median | runs |",
             "|---|---|---|",
             f"| `symcal --help` | {r['help']['seconds']:.3f} s | "
             f"{', '.join(f'{t:.3f}' for t in r['help']['times'])} |",
             f"| `symcal solve {SOLVE} --quiet` | {r['solve']['seconds']:.3f} s | "
             f"{', '.join(f'{t:.3f}' for t in r['solve']['times'])} |", ""]
    parts = r.get("parts", {})
    if parts:
        lines += ["Start-up parts, each in a fresh interpreter (median of 3, interpreter "
                  "start included): " + ", ".join(f"{k} {v:.3f} s" for k, v in parts.items())
                  + ".", ""]
    jit = r["jit"]
    if "error" in jit:
        return [*lines, f"Compiling the functions failed: {jit['error']}"]
    lines.append(f"Compiled twins of the single-stage functions and of the analysis around "
                 f"a public solve (compiler `{jit['compiler']}`; *analysis*: one public solve "
                 "of 500 simulated rows with `SYMCAL_JIT=on`, the solve included), built "
                 "once into the run's cache and loaded from it by every later process: " +
                 ", ".join(f"{k.replace('_', ' ')} {v['seconds']:.2f} s"
                           + ("" if v["compiled"] else " (not compiled)")
                           for k, v in jit.items() if isinstance(v, dict)) + ".")
    return lines
