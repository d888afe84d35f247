"""Every timed job runs in a fresh interpreter: starting one and reading its result.

The parent runs ``python benchmarks/run.py --child JSON``; the child
(:func:`bench.cli.child_main`) looks up the job's ``kind`` in
:data:`bench.jobs.CHILDREN`, runs it and prints its result as one JSON line after
:data:`bench.config.MARK`.  The jobs import this module; it imports none of them.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from typing import Any

from .config import MARK, ROOT, RUN, Settings
from .measure import child_env

#: ``threads`` value of :func:`run_child` meaning "as the run's settings say".
FROM_SETTINGS = "settings"


def run_child(job: dict[str, Any], settings: Settings, timeout: float,
              threads: str | None = FROM_SETTINGS,
              extra_env: dict[str, str] | None = None) -> dict[str, Any]:
    """Run one job in a fresh interpreter.

    Parameters
    ----------
    job
        JSON-ready description; ``job["kind"]`` names the child function.
    settings
        The run's settings (BLAS threads).
    timeout
        Seconds after which the child is killed.
    threads
        BLAS threads of the child (None: the library's default).
    extra_env
        Variables set in the child besides (e.g. an empty compile cache).

    Returns
    -------
    dict
        The child's result with its ``wall`` time, or ``{"error": ..., "wall": ...}``.
    """
    env = child_env(settings.blas_threads if threads == FROM_SETTINGS else threads)
    env.update(extra_env or {})
    cmd = [sys.executable, str(RUN), "--child", json.dumps(job)]
    start = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env,
                              cwd=ROOT)
    except subprocess.TimeoutExpired:
        return {"error": f"killed after the {timeout:.0f} s time limit",
                "wall": time.perf_counter() - start}
    for line in reversed(proc.stdout.splitlines()):
        if line.startswith(MARK):
            result = json.loads(line[len(MARK):])
            result["wall"] = time.perf_counter() - start
            return result
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
    return {"error": f"exit {proc.returncode}: {' | '.join(tail)}",
            "wall": time.perf_counter() - start}
