"""What a run ran on, and which symcal it measured."""

from __future__ import annotations

import hashlib
import os
import platform
import subprocess

import numpy as np

from .config import ROOT


def machine() -> dict[str, str]:
    """CPU, usable cores, memory, OS, library versions and BLAS of this machine."""
    info: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next(line.split(":", 1)[1].strip() for line in fh
                       if line.startswith("model name"))
    except (OSError, StopIteration):
        cpu = platform.processor() or "unknown"
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        usable = os.cpu_count() or 0
    info["CPU"] = f"{cpu}; {usable} usable core(s) (os.cpu_count() = {os.cpu_count()})"
    try:
        with open("/proc/meminfo") as fh:
            kib = next(int(line.split()[1]) for line in fh if line.startswith("MemTotal"))
        info["memory"] = f"{kib / 2**20:.1f} GiB"
    except (OSError, StopIteration):
        pass
    info["OS"] = platform.platform()
    import casadi
    import scipy

    info["software"] = (f"Python {platform.python_version()}, numpy {np.__version__}, "
                        f"scipy {scipy.__version__}, casadi {casadi.__version__}")  # type: ignore[attr-defined]
    try:
        blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
        info["BLAS"] = f"{blas.get('name')} {blas.get('version', '')}".strip()
    except Exception:  # noqa: BLE001 - informative only
        pass
    return info


def code_state() -> dict[str, str]:
    """Which symcal was measured: a hash of symcal/**/*.py, and the git commit (read only)."""
    digest = hashlib.sha256()
    for path in sorted((ROOT / "symcal").rglob("*.py")):
        digest.update(path.relative_to(ROOT).as_posix().encode())
        digest.update(path.read_bytes())
    state = {"hash": digest.hexdigest()[:12]}
    try:
        state["commit"] = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                                         capture_output=True, text=True,
                                         timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "symcal"], cwd=ROOT,
                               capture_output=True, text=True, timeout=10).stdout.strip()
        state["dirty"] = ", ".join(line[3:] for line in dirty.splitlines())
    except (OSError, subprocess.SubprocessError):
        pass
    return state


def load_average() -> str:
    """The 1, 5 and 15 min load averages."""
    try:
        return "{:.2f} {:.2f} {:.2f}".format(*os.getloadavg())
    except OSError:  # pragma: no cover
        return "n/a"
