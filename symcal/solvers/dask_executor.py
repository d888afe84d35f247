"""Chunk passes as Dask tasks: the executor of a partitioned dataset on a Dask cluster.

Each task is one shard: the worker reads it (:meth:`symcal.data.shards.Shard.read`), evaluates
the pass chunk by chunk and returns a small reduction (a number, ``Jᵀg`` and ``JᵀJ``, or
an R factor), so a worker holds one shard at a time and the lead never holds the log.
The lead reduces the shards' results in shard order (:func:`symcal.solvers.passes.run_pass`).

This module alone imports Dask (``distributed``), when an executor is made.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import functools
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING, Any, TypeVar

from symcal.base.cores import mark_pool_thread, usable_cores
from symcal.base.errors import SymcalError, excerpt

if TYPE_CHECKING:
    from distributed import Client

T = TypeVar("T")

#: Environment of the embedded cluster's workers: one BLAS thread and one symcal thread
#: each (a worker process is one core's worth: its passes and evaluations stay serial).
#: A worker forked from this process (:func:`worker_start`) gets it after its BLAS was
#: set up: symcal's passes still hold BLAS to one thread (``blas_limit`` reads it), BLAS
#: elsewhere in it keeps this process's thread count.
WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "SYMCAL_THREADS": "1"}
#: How the embedded cluster's worker processes may start (``SYMCAL_WORKER_START``).
START_METHODS = ("auto", "fork", "spawn", "forkserver")
#: Dask settings of the embedded cluster beside the start method: its workers' preload
#: (:func:`dask_setup`), and its diagnostics run less often.  These feed a dashboard and
#: logs the embedded cluster does not show (the workers' statistical profiler sampled
#: every thread's stack every 10 ms, the event loops' tick ran every 20 ms in each of its
#: servers) and took about 0.4 s of the client's and the workers' CPU from a 10 s fleet
#: of the benchmark (2 workers, 2 cores).  The nannies' memory watchdog keeps its own
#: interval.
CLUSTER_CONFIG = {"distributed.worker.preload": ["symcal.solvers.dask_executor"],
                  "distributed.worker.profile.enabled": False,
                  "distributed.admin.tick.interval": "1s",
                  "distributed.admin.system-monitor.interval": "2s",
                  "distributed.client.scheduler-info-interval": "10s"}
#: Seconds a scheduler address has to connect and answer Dask's handshake and an
#: ``identity`` request; an address that listens but does not speak Dask (an HTTP server, a
#: silent port) is refused after this.
HANDSHAKE_SECONDS = 20.0
#: Dask's own log level in the client and the embedded cluster's processes: nothing of
#: its logging (heartbeats failing at shutdown, restarts, tracebacks) reaches a terminal;
#: what matters to a user reaches them as a unit's error or a message.
DASK_LOG_LEVEL = logging.CRITICAL + 1


class DaskExecutor:
    """Tasks on a Dask cluster through ``client``; results in the order of the pieces.

    Parameters
    ----------
    client
        A ``distributed.Client``.
    """

    remote = True

    def __init__(self, client: Client) -> None:
        self.client = client

    def map(self, task: Callable[[Any], T], pieces: Iterable[Any]) -> Iterator[T]:
        """``task(piece)`` for every piece on the cluster, gathered in order."""
        items = list(pieces)
        if not items:
            return iter(())
        futures = self.client.map(functools.partial(_pool_task, task), items, pure=False)
        return self._gather(futures)

    @staticmethod
    def _gather(futures: list[Any]) -> Iterator[T]:
        try:
            for future in futures:
                yield future.result()
        finally:
            for future in futures:
                future.cancel()

    def __repr__(self) -> str:
        return f"DaskExecutor({self.client!r})"


def _pool_task(task: Callable[[Any], T], piece: Any) -> T:
    """``task(piece)`` on a worker's thread, marked as a pass thread: the worker's
    threads are its parallelism, an evaluation is not split again."""
    mark_pool_thread()
    return task(piece)


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None,
                option: str | None = None) -> Iterator[Client]:
    """A ``distributed.Client`` to the scheduler at ``scheduler``, or to an embedded local
    cluster of ``workers`` processes (default: one per usable core, one thread each and
    symcal's passes on one BLAS thread; started as :func:`worker_start` says), closed
    when the block ends.

    Parameters
    ----------
    scheduler
        Address of a running Dask scheduler (``tcp://host:8786``), or None.
    workers
        Worker processes of the local cluster.
    option
        The command-line option that named the scheduler, for the error message.

    Raises
    ------
    SymcalError
        When the scheduler cannot be reached (exit code 2).
    """
    from distributed import Client, LocalCluster

    with _quiet_dask():
        if scheduler is not None:
            named = f"{option} {excerpt(scheduler, 80)}: " if option else ""
            _check_scheduler(scheduler, named)
            try:
                client = Client(scheduler, timeout=f"{HANDSHAKE_SECONDS}s")
            except (OSError, TimeoutError, ValueError) as exc:
                raise SymcalError(f"{named}cannot reach the Dask scheduler "
                                  f"{excerpt(scheduler, 80)} ({excerpt(exc, 120)})") from None
            try:
                yield client
            finally:
                client.close()
            return
        # no dashboard; the scheduler's own HTTP server on a free port of this host only
        # (its default, 8787 on every interface, warns when another cluster has it)
        # the settings hold while the cluster and its client start: a worker restarted
        # later starts Dask's own way
        with _malloc_as_usual(), _started_as_configured():
            cluster = LocalCluster(
                n_workers=workers or usable_cores(), threads_per_worker=1, processes=True,
                dashboard_address="127.0.0.1:0", silence_logs=DASK_LOG_LEVEL,
                env=dict(WORKER_ENV))
            try:
                client = Client(cluster)
            except BaseException:
                cluster.close()
                raise
        with cluster, client:
            yield client


def dask_setup(worker: Any) -> None:
    """Run by each worker of the embedded cluster as it starts (Dask's preload): ignore
    Ctrl-C.  A terminal sends it to every process of the command, and a worker's
    ``KeyboardInterrupt`` only printed a traceback there; the process that started the
    cluster stops it."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def worker_start() -> str:
    """How the embedded cluster starts its worker processes: ``SYMCAL_WORKER_START``
    (``auto``, ``fork``, ``spawn`` or ``forkserver``; default ``auto``).

    ``auto`` forks the workers from this process on Linux when it runs nothing else
    (:func:`running_alone`), else starts them from a forkserver where the platform has
    one (Linux, macOS), else spawns them.  Forked workers start with symcal and Dask
    imported: the quickest start (the benchmark's fleet of 200 units on 2 workers: 1.67-1.76
    times a plain loop against 1.64-1.67 from a forkserver and 1.55-1.62 spawned).  But a
    fork is safe only when no other thread of this process is inside BLAS at that moment:
    OpenBLAS's own fork handler then waits for ever (a thread solving beside a fleet
    forced to ``fork`` hung it in 4 runs of 5).  A forkserver is one fresh process that
    imports Dask and symcal's worker side (:data:`WORKER_PRELOAD`) once and forks the
    workers itself, with no other thread.  A forked worker holds none of this process's
    symcal locks (:mod:`symcal.base.forks`), pass threads or output-folder locks, and
    ends on SIGTERM as a process does by default; outside symcal's passes it keeps this
    process's BLAS thread count.

    Raises
    ------
    SymcalError
        For another value, or a method this platform lacks.
    """
    import multiprocessing

    methods = multiprocessing.get_all_start_methods()
    value = os.environ.get("SYMCAL_WORKER_START", "").strip().lower() or "auto"
    if value not in START_METHODS:
        raise SymcalError(f"SYMCAL_WORKER_START must be auto, fork, spawn or forkserver, "
                          f"not '{excerpt(value, 40)}'")
    if value == "auto":
        if sys.platform.startswith("linux") and "fork" in methods and running_alone():
            return "fork"
        return "forkserver" if "forkserver" in methods else "spawn"
    if value not in methods:
        raise SymcalError(f"SYMCAL_WORKER_START={value}: this platform cannot start "
                          f"processes that way (it can: {', '.join(methods)})")
    return value


def running_alone() -> bool:
    """Whether this is the main thread and every other thread of the process is one of
    symcal's own pass threads (waiting: the passes are driven from here), one of its
    background compiles, or tqdm's monitor: nothing else can be inside BLAS while a
    worker is forked from this process."""
    here = threading.current_thread()
    if here is not threading.main_thread():
        return False
    return all(t is here or t.name.startswith(("symcal-pass", "symcal-jit"))
               or type(t).__name__ == "TMonitor" for t in threading.enumerate())


#: What a ``forkserver`` imports before it forks the workers: Dask and symcal's side of
#: a fleet's or a sharded log's tasks (the problem's build, the solve, the passes).
WORKER_PRELOAD = ("distributed", "numpy", "casadi", "symcal.problem.build",
                  "symcal.calibrate.fleet", "symcal.solvers.dask_executor")


def _preload_forkserver() -> None:
    """Have this process's forkserver, when it starts, import :data:`WORKER_PRELOAD`.

    Dask sets the forkserver's preload list once per process, the first time it asks for
    the context; it is asked first here, then the list replaced.  A forkserver already
    running keeps what it imported."""
    import multiprocessing

    from distributed.utils import get_mp_context

    get_mp_context()
    multiprocessing.get_context("forkserver").set_forkserver_preload(list(WORKER_PRELOAD))


@contextlib.contextmanager
def _started_as_configured() -> Iterator[None]:
    """Dask's settings for the embedded cluster: the workers' start method
    (:func:`worker_start`; a forkserver preloaded) and :data:`CLUSTER_CONFIG`."""
    import dask

    method = worker_start()
    with dask.config.set({"distributed.worker.multiprocessing-method": method,
                          **CLUSTER_CONFIG}):
        if method == "forkserver":
            _preload_forkserver()
        yield


@contextlib.contextmanager
def _malloc_as_usual() -> Iterator[None]:
    """The embedded cluster's workers start with glibc's own malloc settings.

    Dask starts its workers with ``MALLOC_TRIM_THRESHOLD_`` set, which also fixes glibc's
    mmap threshold at 128 KiB: every array above it (a chunk's Jacobian, the noise
    floors' products) is then mapped and unmapped at each allocation, its pages faulted
    in and zeroed again.  A worker solved the same units with 1.4 to 1.8 times the CPU
    time of a plain loop.  symcal's workers hold bounded memory (chunks, one shard), so
    they start as any process does."""
    import dask

    key = "distributed.nanny.pre-spawn-environ"
    environ = {k: v for k, v in dict(dask.config.get(key, default={})).items()
               if k != "MALLOC_TRIM_THRESHOLD_"}
    with dask.config.set({key: environ}):
        yield


@contextlib.contextmanager
def _quiet_dask() -> Iterator[None]:
    """Dask's loggers (``distributed``, ``tornado``, ``asyncio``) silent in this process
    while a client runs, restored after."""
    import warnings

    names = ("distributed", "dask", "tornado", "asyncio")
    saved = [(logging.getLogger(n), logging.getLogger(n).level) for n in names]
    for logger, _ in saved:
        logger.setLevel(DASK_LOG_LEVEL)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", module=r"(distributed|dask|tornado)(\.|$)")
            yield
    finally:
        for logger, level in saved:
            logger.setLevel(level)


def _check_scheduler(address: str, named: str) -> None:
    """Refuse an address that is not a Dask scheduler within :data:`HANDSHAKE_SECONDS`:
    nothing listens, something listens but never answers Dask's handshake (a silent
    port, an HTTP server), or a Dask server that is not a scheduler.  The whole exchange
    has one deadline (Dask's own connect timeout does not cover the handshake)."""
    import asyncio

    from distributed.comm import connect
    from distributed.comm.addressing import parse_address

    shown = excerpt(address, 80)
    try:
        parse_address(address)
    except ValueError as exc:
        raise SymcalError(f"{named}not a Dask scheduler address ({excerpt(exc, 120)}); "
                          "write tcp://HOST:PORT") from None

    async def exchange() -> Any:
        comm = await connect(address, timeout=HANDSHAKE_SECONDS)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    def run() -> Any:   # its own event loop, in a thread: a caller's loop may be running
        return asyncio.run(asyncio.wait_for(exchange(), HANDSHAKE_SECONDS))

    try:
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            reply = pool.submit(run).result()
    except TimeoutError:
        raise SymcalError(f"{named}something listens at {shown} but does not answer as a "
                          f"Dask scheduler within {HANDSHAKE_SECONDS:g} s (is it another "
                          "service, such as a web server?)") from None
    except (OSError, ValueError, TypeError, EOFError) as exc:
        reason = excerpt(exc, 120) or exc.__class__.__name__
        raise SymcalError(f"{named}cannot reach the Dask scheduler {shown} ({reason})"
                          ) from None
    kind = reply.get("type") if isinstance(reply, dict) else None
    if kind != "Scheduler":
        raise SymcalError(f"{named}{shown} answers, but not as a Dask scheduler (it says it "
                          f"is {excerpt(kind or 'something else', 40)})")


@contextlib.contextmanager
def dask_executor(scheduler: str | None = None,
                  workers: int | None = None) -> Iterator[DaskExecutor]:
    """A :class:`DaskExecutor` on :func:`dask_client` (the same arguments).

    Raises
    ------
    SymcalError
        When the scheduler cannot be reached (exit code 2).
    """
    with dask_client(scheduler, workers) as client:
        yield DaskExecutor(client)
