"""A process forked from symcal's (the embedded Dask cluster's workers on Linux) starts
clean: no lock held by a thread it lacks, its own pass threads, no output folder's lock,
its own compile tallies, and SIGTERM ending it as by default; and how the workers start
(``SYMCAL_WORKER_START``).

Each fork test runs its check in a child made by ``os.fork`` and reads the child's exit
status; an alarm ends a child that would hang."""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from symcal.base import jit
from symcal.base.errors import SymcalError
from symcal.base.files import _HELD, writing_to
from symcal.base.forks import ForkLock
from symcal.cli.common import Terminated, signals_handled
from symcal.solvers.dask_executor import worker_start
from symcal.solvers.executor import ThreadExecutor

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this platform")

#: Seconds a forked child may take before its alarm ends it (status: killed by SIGALRM).
ALARM = 20


def in_child(check: Callable[[], int]) -> int:
    """Fork; the child exits with ``check()``'s code (99 on an exception); the parent
    returns the child's wait status."""
    pid = os.fork()
    if pid == 0:                                   # pragma: no cover - the child
        code = 99
        try:
            signal.alarm(ALARM)
            code = check()
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    return status


def exit_code(status: int) -> int | None:
    return os.waitstatus_to_exitcode(status) if os.WIFEXITED(status) else None


def test_a_fork_lock_held_by_another_thread_is_free_in_the_child() -> None:
    lock, plain = ForkLock(), threading.Lock()
    held, done = threading.Event(), threading.Event()

    def holder() -> None:
        with lock, plain:
            held.set()
            done.wait(30)

    thread = threading.Thread(target=holder)
    thread.start()
    held.wait(10)
    try:
        # 0: the ForkLock is free in the child, where a threading.Lock stays held
        status = in_child(lambda: 0 if lock.acquire(blocking=False)
                          and not plain.acquire(blocking=False) else 1)
    finally:
        done.set()
        thread.join()
    assert exit_code(status) == 0
    assert not lock.locked()


def test_a_thread_executor_works_in_a_forked_child() -> None:
    executor = ThreadExecutor(2)
    assert list(executor.map(lambda x: x * x, range(6))) == [0, 1, 4, 9, 16, 25]

    def check() -> int:
        return 0 if list(executor.map(lambda x: x + 1, range(6))) == [1, 2, 3, 4, 5, 6] \
            else 1

    assert exit_code(in_child(check)) == 0          # not hung on the parent's threads


def test_a_forked_child_does_not_keep_the_output_folders_lock(tmp_path: Path) -> None:
    out = tmp_path / "out"
    go_r, go_w = os.pipe()
    with writing_to(out, "--out out"):
        pid = os.fork()
        if pid == 0:                                # pragma: no cover - the child
            os.close(go_w)
            signal.alarm(ALARM)
            os.read(go_r, 1)                        # alive until the parent is done
            os._exit(0 if not _HELD else 1)
        os.close(go_r)
    try:
        with writing_to(out, "--out out"):          # the lock is free again at once
            pass
    finally:
        os.write(go_w, b"x")
        os.close(go_w)
        _, status = os.waitpid(pid, 0)
    assert exit_code(status) == 0


def test_sigterm_ends_a_forked_child_as_by_default() -> None:
    def check() -> int:
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
        except Terminated:
            return 7                                # the parent's handling: wrong here
        return 0

    with signals_handled():
        status = in_child(check)
        with pytest.raises(Terminated):             # the command itself still raises
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
    assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGTERM


def test_ctrl_c_is_ignored_in_a_forked_child(monkeypatch) -> None:
    """The command's SIGINT handler records the stop in the command's process only; a
    forked child (a worker of the embedded cluster, reached by a terminal's Ctrl-C as
    every process of the command is) ignores it, records nothing and inherits no
    record."""
    from symcal.base import stops

    real_getsignal = signal.getsignal

    def check() -> int:
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.5)
        except KeyboardInterrupt:
            return 1
        return 0 if not stops._REQUESTED and \
            real_getsignal(signal.SIGINT) is signal.SIG_IGN else 2

    monkeypatch.setattr(signal, "getsignal", lambda s: (     # as from a terminal
        signal.default_int_handler if s == signal.SIGINT else real_getsignal(s)))
    with signals_handled():
        stops.request(Terminated)           # the parent's record is not the child's
        status = in_child(check)
        assert stops._REQUESTED == [Terminated]
    monkeypatch.undo()
    assert exit_code(status) == 0 and stops._REQUESTED == []   # cleared with the command


def test_a_forked_child_starts_its_own_compile_tallies(monkeypatch) -> None:
    class Key:                                       # weakly referenced, as a Mapped
        pass

    key = Key()
    monkeypatch.setitem(jit._TALLY, key, 5)
    jit._PENDING.add(key)
    try:
        assert exit_code(in_child(lambda: 0 if not jit._TALLY and not jit._PENDING
                                  else 1)) == 0
    finally:
        jit._PENDING.discard(key)
    assert jit._TALLY[key] == 5                      # the parent's own are kept


@pytest.mark.parametrize("value, alone, expected", [
    ("", True, "fork"), ("auto", True, "fork"), ("", False, "forkserver"),
    ("spawn", True, "spawn"), (" Fork ", False, "fork"), ("forkserver", True, "forkserver")])
def test_worker_start_on_linux(monkeypatch, value, alone, expected) -> None:
    """By default the workers are forked only from a process that runs nothing else."""
    import symcal.solvers.dask_executor as dask_executor

    monkeypatch.setattr("sys.platform", "linux")
    monkeypatch.setattr(dask_executor, "running_alone", lambda: alone)
    monkeypatch.setenv("SYMCAL_WORKER_START", value)
    assert worker_start() == expected


def test_worker_start_elsewhere_and_refusals(monkeypatch) -> None:
    import symcal.solvers.dask_executor as dask_executor

    monkeypatch.delenv("SYMCAL_WORKER_START", raising=False)
    monkeypatch.setattr(dask_executor, "running_alone", lambda: True)
    monkeypatch.setattr("sys.platform", "darwin")
    assert worker_start() == "forkserver"                  # never fork by default there
    monkeypatch.setattr(multiprocessing, "get_all_start_methods", lambda: ["spawn"])
    assert worker_start() == "spawn"
    monkeypatch.setenv("SYMCAL_WORKER_START", "threads")
    with pytest.raises(SymcalError) as err:
        worker_start()
    assert str(err.value) == ("SYMCAL_WORKER_START must be auto, fork, spawn or "
                              "forkserver, not 'threads'")
    monkeypatch.setenv("SYMCAL_WORKER_START", "fork")
    with pytest.raises(SymcalError) as err:
        worker_start()
    assert str(err.value) == ("SYMCAL_WORKER_START=fork: this platform cannot start "
                              "processes that way (it can: spawn)")


def test_running_alone_means_no_other_thread_but_symcals_own(monkeypatch) -> None:
    from symcal.solvers.dask_executor import running_alone

    main = threading.main_thread()
    pool = threading.Thread(name="symcal-pass_0")
    user = threading.Thread(name="Thread-7")
    monkeypatch.setattr(threading, "enumerate", lambda: [main, pool])
    assert running_alone()
    monkeypatch.setattr(threading, "enumerate", lambda: [main, pool, user])
    assert not running_alone()
    monkeypatch.undo()
    seen: list[bool] = []
    thread = threading.Thread(target=lambda: seen.append(running_alone()))
    thread.start()
    thread.join()
    assert seen == [False]                                  # not from another thread


def test_a_forked_child_does_not_keep_a_commits_folder_lock(tmp_path: Path) -> None:
    """A fork while an output set commits (a Dask worker restarted then): the child's
    copy of the folder's descriptor is closed, the lock ends with the commit."""
    import fcntl

    from symcal.base.files import _locked

    go_r, go_w = os.pipe()
    up_r, up_w = os.pipe()
    with _locked(tmp_path):
        pid = os.fork()
        if pid == 0:                                # pragma: no cover - the child
            os.close(go_w)
            signal.alarm(ALARM)
            os.write(up_w, b"x")                    # running: its fork hooks have run
            os.read(go_r, 1)
            os._exit(0)
        os.close(go_r)
        os.read(up_r, 1)
    fd = os.open(tmp_path, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)    # free at once
    finally:
        os.close(fd)
        os.write(go_w, b"x")
        os.close(go_w)
        os.waitpid(pid, 0)


def test_symcal_imports_where_the_platform_does_not_fork(monkeypatch) -> None:
    from symcal.base import forks

    monkeypatch.delattr(os, "register_at_fork")
    forks.in_forked_child(lambda: None)                     # nothing to register


FLEET_BESIDE_A_THREAD = """
import sys, threading
from pathlib import Path
import numpy as np
import symcal
from symcal.data.dataset import write_table
from symcal.simulation import load_scenario, simulate_run
from symcal.solvers.passes import _qr_r

stop = threading.Event()

def busy():                      # a thread of the user's inside BLAS (LAPACK's QR, GIL free)
    a = np.random.default_rng(0).normal(size=(20000, 36))
    while not stop.is_set():
        _qr_r(a)

if __name__ == "__main__":       # workers not forked from here import this file again
    root = Path(sys.argv[1])
    problem = symcal.load_problem(sys.argv[2])
    scenario = load_scenario(sys.argv[3])
    for k in range(4):
        (root / f"unit-{k}").mkdir()
        write_table(root / f"unit-{k}" / "calibration.npz",
                    simulate_run(scenario, "calibration", seed=k, n=400))
    thread = threading.Thread(target=busy)
    thread.start()
    try:
        fleet = symcal.solve_fleet(problem, root, workers=2)
    finally:
        stop.set()
        thread.join()
    worst = 0.0
    for unit in sorted(fleet.results):
        files = {p.stem: str(p) for p in (root / unit).iterdir()}
        local = symcal.solve(problem, files)
        worst = max(worst, max(abs(fleet.results[unit].params[n].value - p.value)
                               for n, p in local.params.items()))
    print("ok", len(fleet.results), worst)
"""


@pytest.mark.slow
def test_a_fleet_starts_beside_a_thread_inside_blas(tmp_path: Path) -> None:
    """A user's thread inside BLAS while the embedded cluster starts: forking the
    workers from this process hung it (OpenBLAS's fork handler) in 4 runs of 5; the
    default starts them from a forkserver then, and the fleet equals local solves."""
    import subprocess
    import sys

    from conftest import ROOT

    (tmp_path / "script.py").write_text(FLEET_BESIDE_A_THREAD)
    (tmp_path / "fleet").mkdir()
    env = {k: v for k, v in os.environ.items() if k != "SYMCAL_WORKER_START"}
    proc = subprocess.run(
        [sys.executable, "script.py", str(tmp_path / "fleet"),
         str(ROOT / "problems" / "platen_self_calibration.yaml"),
         str(ROOT / "problems" / "scenarios" / "courier_platen.yaml")],
        cwd=tmp_path, capture_output=True, text=True, timeout=240, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    word, units, worst = proc.stdout.split()
    assert (word, units) == ("ok", "4") and float(worst) <= 1e-12
