"""Who runs the chunk passes: the seam between a pass over the data and the cores.

A pass over the data is a *map* of one task over pieces (chunks of an in-memory dataset,
or shards of a partitioned one) followed by an *ordered reduce* in the lead: an executor
only maps, and gives the results back in the order of the pieces, so the reduction, and
therefore the result, is the same whoever ran the tasks.

* :class:`SerialExecutor`: one after the other, in the calling thread.
* :class:`ThreadExecutor`: a pool of threads in this process.  CasADi's buffer call and
  numpy's BLAS release the GIL, so the evaluation and the reduction of different chunks
  run on different cores; BLAS itself keeps its one thread (symcal's policy, see
  ``symcal/__init__.py``), so threads never multiply.
* ``DaskExecutor`` (:mod:`symcal.solvers.dask_executor`, which alone imports Dask): tasks
  on a Dask cluster, each reading its own shard and returning a small reduction.

:func:`default_executor` is the policy of an in-memory pass: threads, one per usable core,
from :data:`THREAD_MIN` observations on, else serial.  The environment variable
``SYMCAL_THREADS`` overrides the number of threads (``1``: always serial).  Inside
``with using(executor):`` every pass over a partitioned dataset runs on ``executor`` (and
every in-memory pass too, unless the executor is remote: in-memory chunks are not shipped
to other processes).
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Protocol, TypeVar

from symcal.base.errors import SymcalError

T = TypeVar("T")

#: In-memory passes over at least this many observations use threads by default.
THREAD_MIN = 32_768


class Executor(Protocol):
    """Maps a task over pieces; results come back in the order of the pieces."""

    #: Whether the tasks run in another process (pieces and tasks are then pickled).
    remote: bool

    def map(self, task: Callable[[Any], T], pieces: Iterable[Any]) -> Iterator[T]:
        """``task(piece)`` for every piece, in order."""
        ...


class SerialExecutor:
    """Every task in the calling thread, one after the other (lazily: one piece's result
    at a time)."""

    remote = False

    def map(self, task: Callable[[Any], T], pieces: Iterable[Any]) -> Iterator[T]:
        """``task(piece)`` for every piece, in order."""
        return (task(piece) for piece in pieces)

    def __repr__(self) -> str:
        return "SerialExecutor()"


class ThreadExecutor:
    """Tasks on a pool of ``workers`` threads of this process, results in order.

    Parameters
    ----------
    workers
        Threads (at least 1).  The pool is created on first use and kept, so that the
        threads' evaluation buffers are reused from pass to pass.
    """

    remote = False

    def __init__(self, workers: int) -> None:
        if workers < 1:
            raise SymcalError(f"a thread executor needs at least one worker, not {workers}")
        self.workers = workers
        self._pool: ThreadPoolExecutor | None = None
        self._lock = threading.Lock()

    def _get_pool(self) -> ThreadPoolExecutor:
        with self._lock:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(self.workers, "symcal-pass")
            return self._pool

    def map(self, task: Callable[[Any], T], pieces: Iterable[Any]) -> Iterator[T]:
        """``task(piece)`` for every piece, in order (at most ``2 × workers`` pieces in
        flight, so results waiting to be reduced stay few)."""
        pool = self._get_pool()
        window = 2 * self.workers
        pending: list[Any] = []
        try:
            for piece in pieces:
                pending.append(pool.submit(task, piece))
                if len(pending) >= window:
                    yield pending.pop(0).result()
            while pending:
                yield pending.pop(0).result()
        finally:
            for future in pending:
                future.cancel()

    def __repr__(self) -> str:
        return f"ThreadExecutor({self.workers})"


def usable_cores() -> int:
    """Cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def thread_count() -> int:
    """Threads of an in-memory pass: ``SYMCAL_THREADS`` if set, else the usable cores."""
    text = os.environ.get("SYMCAL_THREADS", "").strip()
    if not text:
        return usable_cores()
    try:
        value = int(text)
    except ValueError:
        raise SymcalError(f"SYMCAL_THREADS must be a whole number of threads, not "
                          f"'{text}'") from None
    if value < 1:
        raise SymcalError(f"SYMCAL_THREADS must be at least 1, not {value}")
    return value


_SERIAL = SerialExecutor()
_THREADS: dict[int, ThreadExecutor] = {}
_THREADS_LOCK = threading.Lock()


def threads(workers: int) -> ThreadExecutor:
    """The process's shared thread executor with ``workers`` threads."""
    with _THREADS_LOCK:
        if workers not in _THREADS:
            _THREADS[workers] = ThreadExecutor(workers)
        return _THREADS[workers]


def default_executor(observations: int) -> Executor:
    """The executor of an in-memory pass over ``observations`` observations: threads (one
    per usable core, or ``SYMCAL_THREADS``) from :data:`THREAD_MIN` on, else serial."""
    workers = thread_count()
    if workers <= 1 or observations < THREAD_MIN:
        return _SERIAL
    return threads(workers)


_AMBIENT: contextvars.ContextVar[Executor | None] = contextvars.ContextVar(
    "symcal_executor", default=None)


@contextlib.contextmanager
def using(executor: Executor) -> Iterator[Executor]:
    """Run the passes of the code inside the block on ``executor`` (see the module)."""
    token = _AMBIENT.set(executor)
    try:
        yield executor
    finally:
        _AMBIENT.reset(token)


def current() -> Executor | None:
    """The executor of the innermost :func:`using` block, if any."""
    return _AMBIENT.get()
