"""Who runs the chunk passes: the seam between a pass over the data and the cores.

A pass over the data is a *map* of one task over pieces (chunks of an in-memory dataset,
or shards of a partitioned one) followed by an *ordered reduce* in the lead: an executor
only maps, and gives the results back in the order of the pieces, so the reduction, and
therefore the result, is the same whoever ran the tasks.

* :class:`SerialExecutor`: one after the other, in the calling thread.
* :class:`ThreadExecutor`: a pool of threads in this process.  CasADi's buffer call and
  numpy's BLAS release the GIL, so the evaluation and the reduction of different chunks
  run on different cores; BLAS itself keeps its one thread (:func:`blas_limit`), so
  threads never multiply.
* ``DaskExecutor`` (:mod:`symcal.solvers.dask_executor`, which alone imports Dask): tasks
  on a Dask cluster, each reading its own shard and returning a small reduction.

:func:`default_executor` is the policy of an in-memory pass: threads, one per usable core,
from :data:`THREAD_MIN` observations on, else serial.  The environment variable
``SYMCAL_THREADS`` overrides the number of threads (``1``: always serial).  Inside
``with using(executor):`` every pass over a partitioned dataset runs on ``executor`` (and
every in-memory pass too, unless the executor is remote: in-memory chunks are not shipped
to other processes).

BLAS threads: symcal reduces tall, thin blocks (``JᵀJ``, QR of ``[J | g]``), where
OpenBLAS's own threads cost more than they give (on 2 cores: 1.6× to 60× slower, more
the busier the machine, benchmarks/RESULTS.md), and a pass already runs one thread per
core.  :func:`blas_limit` holds every BLAS library loaded in the process (numpy's and
SciPy's OpenBLAS, MKL, ...) to :func:`blas_threads` threads around symcal's passes and
solver steps, through ``threadpoolctl``: it works whatever was imported first, and
restores the libraries' own setting afterwards, so a user's own numpy code keeps its
threads.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import sys
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any, ParamSpec, Protocol, TypeVar

from symcal.base.cores import in_pool_thread, mark_pool_thread, thread_count
from symcal.base.errors import SymcalError
from symcal.base.forks import ForkLock

T = TypeVar("T")
P = ParamSpec("P")
R = TypeVar("R")

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
        threads' evaluation buffers are reused from pass to pass; a forked child (which
        has none of its threads) creates its own.
    """

    remote = False

    def __init__(self, workers: int) -> None:
        if workers < 1:
            raise SymcalError(f"a thread executor needs at least one worker, not {workers}")
        self.workers = workers
        self._pool: ThreadPoolExecutor | None = None
        self._pid = 0
        self._lock = ForkLock()

    def _get_pool(self) -> ThreadPoolExecutor:
        with self._lock:
            if self._pool is None or self._pid != os.getpid():
                self._pool = ThreadPoolExecutor(self.workers, "symcal-pass",
                                                initializer=mark_pool_thread)
                self._pid = os.getpid()
            return self._pool

    def map(self, task: Callable[[Any], T], pieces: Iterable[Any]) -> Iterator[T]:
        """``task(piece)`` for every piece, in order (at most ``2 × workers`` pieces in
        flight, so results waiting to be reduced stay few)."""
        if in_pool_thread():    # a task of a pass: its own pass runs here, never
            yield from (task(piece) for piece in pieces)   # waiting on a busy pool
            return
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


_SERIAL = SerialExecutor()
_THREADS: dict[int, ThreadExecutor] = {}
_THREADS_LOCK = ForkLock()


def threads(workers: int) -> ThreadExecutor:
    """The process's shared thread executor with ``workers`` threads."""
    with _THREADS_LOCK:
        if workers not in _THREADS:
            _THREADS[workers] = ThreadExecutor(workers)
        return _THREADS[workers]


def default_executor(observations: int) -> Executor:
    """The executor of an in-memory pass over ``observations`` observations: threads (one
    per usable core, or ``SYMCAL_THREADS``) from :data:`THREAD_MIN` on, else serial; and
    serial inside a pass thread (a shard's pass inside a pass over the shards)."""
    workers = thread_count()
    if workers <= 1 or observations < THREAD_MIN or in_pool_thread():
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


#: Environment variables a user sets to choose BLAS's threads (the first one set wins).
BLAS_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS")


def blas_threads() -> int:
    """BLAS threads inside symcal's passes: the user's ``OPENBLAS_NUM_THREADS`` (or
    ``MKL_NUM_THREADS``, ``OMP_NUM_THREADS``) when set to a whole number, else 1."""
    for var in BLAS_VARIABLES:
        text = os.environ.get(var, "").strip()
        if text.isdigit() and int(text) >= 1:
            return int(text)
    return 1


class _BlasLimit:
    """Process-wide BLAS thread limit held while any thread is inside :func:`blas_limit`
    (BLAS's thread count is global to each library, so nested and concurrent users share
    one limit: the first in sets it, the last out restores it)."""

    def __init__(self) -> None:
        self.lock = ForkLock()
        self.depth = 0
        self.controller: Any = None
        self.scanned_scipy = False
        self.active: Any = None

    def _get_controller(self) -> Any:
        # scan the loaded libraries again once SciPy's LAPACK (its own OpenBLAS) is loaded
        scipy_loaded = "scipy.linalg" in sys.modules
        if self.controller is None or (scipy_loaded and not self.scanned_scipy):
            from threadpoolctl import ThreadpoolController

            self.controller = ThreadpoolController()
            self.scanned_scipy = scipy_loaded
        return self.controller

    def enter(self) -> None:
        with self.lock:
            self.depth += 1
            if self.depth == 1:
                self.active = self._get_controller().limit(limits=blas_threads(),
                                                           user_api="blas")

    def refresh(self) -> None:
        """Rescan the loaded libraries (SciPy's LAPACK was just loaded), and hold the new
        ones too when a limit is in force."""
        with self.lock:
            if "scipy.linalg" not in sys.modules or self.scanned_scipy:
                return
            if self.active is not None:
                self.active.restore_original_limits()
            self.controller = None
            controller = self._get_controller()
            if self.depth > 0:
                self.active = controller.limit(limits=blas_threads(), user_api="blas")

    def exit(self) -> None:
        with self.lock:
            self.depth -= 1
            if self.depth == 0 and self.active is not None:
                self.active.restore_original_limits()
                self.active = None


_BLAS = _BlasLimit()


@contextlib.contextmanager
def blas_limit() -> Iterator[None]:
    """Hold BLAS to :func:`blas_threads` threads inside the block (see the module)."""
    _BLAS.enter()
    try:
        yield
    finally:
        _BLAS.exit()


def blas_loaded() -> None:
    """Call after loading a library with its own BLAS (SciPy's LAPACK): a limit in force
    then holds it too."""
    _BLAS.refresh()


def blas_limited(fn: Callable[P, R]) -> Callable[P, R]:
    """``fn`` run inside :func:`blas_limit` (a decorator for symcal's entry points)."""
    import functools

    @functools.wraps(fn)
    def wrapped(*args: P.args, **kwargs: P.kwargs) -> R:
        with blas_limit():
            return fn(*args, **kwargs)

    return wrapped
