"""How many cores symcal's own work may use, and whether a thread is already one of them.

:func:`thread_count` is the policy every parallel part of symcal follows: the usable
cores, or ``SYMCAL_THREADS``.  A thread of symcal's own pass pool marks itself
(:func:`mark_pool_thread`), so that work it runs is not split again
(:func:`inner_threads` is then 1) and a pass it starts runs in it
(:func:`in_pool_thread`): threads never multiply, and a pool never waits on itself.
"""

from __future__ import annotations

import os
import threading

from symcal.base.errors import SymcalError

_LOCAL = threading.local()


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


def mark_pool_thread() -> None:
    """Mark the calling thread as one of symcal's pass threads (a pool's initializer)."""
    _LOCAL.pool = True


def in_pool_thread() -> bool:
    """Whether the calling thread is one of symcal's pass threads (or a worker's task
    thread): a pass it starts runs in it (waiting on its own pool would deadlock)."""
    return bool(getattr(_LOCAL, "pool", False))


def inner_threads() -> int:
    """Threads the calling thread may split one evaluation over: 1 inside symcal's pass
    pool (the pool already uses the cores), else :func:`thread_count`."""
    return 1 if in_pool_thread() else thread_count()
