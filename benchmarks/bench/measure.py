"""Clocks and memory: what every measurement of the harness is made with."""

from __future__ import annotations

import os
import resource
import time
from collections.abc import Callable
from typing import Any

BLAS_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def rss_now_mib() -> float:
    """Current resident set size of this process (MiB), from /proc (Linux)."""
    try:
        with open("/proc/self/statm") as fh:
            pages = int(fh.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:  # pragma: no cover - not Linux
        return float("nan")


def peak_rss_mib() -> float:
    """Peak resident set size of this process so far (MiB).

    VmHWM of /proc/self/status: the high-water mark of this address space.  (On Linux
    ``ru_maxrss`` survives ``execve``, so a child would inherit the parent's peak.)
    """
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:  # pragma: no cover - not Linux
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def timed(fn: Callable[[], Any]) -> float:
    """Wall time of one call of ``fn`` (s)."""
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def best(fn: Callable[[], Any], repeats: int = 2) -> float:
    """Shortest wall time of ``repeats`` calls of ``fn`` (s)."""
    return min(timed(fn) for _ in range(repeats))


def child_env(threads: str | None) -> dict[str, str]:
    """This process's environment with the BLAS thread variables set to ``threads``
    (None: unset, leaving the choice to the library)."""
    env = dict(os.environ)
    for var in BLAS_VARIABLES:
        if threads is None:
            env.pop(var, None)
        else:
            env[var] = threads
    return env


class Clock:
    """The run's wall-clock budget: capped rows are skipped or stopped to stay within it.

    Parameters
    ----------
    budget
        Seconds the whole run may take.
    """

    def __init__(self, budget: float) -> None:
        self.start = time.perf_counter()
        self.budget = budget

    def elapsed(self) -> float:
        """Seconds since the run started."""
        return time.perf_counter() - self.start

    def left(self) -> float:
        """Seconds of the budget left (negative once it is spent)."""
        return self.budget - self.elapsed()
