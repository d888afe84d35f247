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


def test_ctrl_c_in_a_forked_child_is_pythons_own(monkeypatch) -> None:
    """The command's SIGINT handler records the stop in the command's process only; a
    forked child gets Python's KeyboardInterrupt, records nothing and inherits no
    record."""
    from symcal.base import stops

    real_getsignal = signal.getsignal

    def check() -> int:
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
        except KeyboardInterrupt:
            return 0 if not stops._REQUESTED and \
                real_getsignal(signal.SIGINT) is signal.default_int_handler else 2
        return 1

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


@pytest.mark.parametrize("value, expected", [("", "fork"), ("spawn", "spawn"),
                                             (" Fork ", "fork"),
                                             ("forkserver", "forkserver")])
def test_worker_start_on_linux(monkeypatch, value, expected) -> None:
    monkeypatch.setattr("sys.platform", "linux")
    monkeypatch.setenv("SYMCAL_WORKER_START", value)
    assert worker_start() == expected


def test_worker_start_elsewhere_and_refusals(monkeypatch) -> None:
    monkeypatch.delenv("SYMCAL_WORKER_START", raising=False)
    monkeypatch.setattr("sys.platform", "darwin")
    assert worker_start() == "spawn"
    monkeypatch.setenv("SYMCAL_WORKER_START", "threads")
    with pytest.raises(SymcalError) as err:
        worker_start()
    assert str(err.value) == ("SYMCAL_WORKER_START must be fork, spawn or forkserver, "
                              "not 'threads'")
    monkeypatch.setenv("SYMCAL_WORKER_START", "fork")
    monkeypatch.setattr(multiprocessing, "get_all_start_methods", lambda: ["spawn"])
    with pytest.raises(SymcalError) as err:
        worker_start()
    assert str(err.value) == ("SYMCAL_WORKER_START=fork: this platform cannot start "
                              "processes that way (it can: spawn)")
