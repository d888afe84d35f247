"""What a process forked from this one starts with: no lock held by a thread it lacks.

On Linux the embedded Dask cluster forks its workers from the client process
(:mod:`symcal.solvers.dask_executor`), so that they start with symcal imported.  A forked
child has only the thread that forked; a lock another thread held at that moment would
stay held in the child for ever.  symcal's locks are therefore :class:`ForkLock`\\ s,
renewed (unlocked) in every forked child, and :func:`in_forked_child` runs a module's
own clean-up there (a pass pool whose threads the child lacks, an output folder's lock
the child must not keep, a compile in progress it will never finish).
"""

from __future__ import annotations

import os
import threading
import weakref
from collections.abc import Callable
from types import TracebackType


class ForkLock:
    """A mutual-exclusion lock that a forked child gets unlocked (as ``threading.Lock``
    otherwise: ``with lock: ...``, :meth:`acquire`, :meth:`release`, :meth:`locked`)."""

    __slots__ = ("_lock", "__weakref__")

    def __init__(self) -> None:
        self._lock = threading.Lock()
        _LOCKS.add(self)

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        """Acquire the lock (as ``threading.Lock.acquire``)."""
        return self._lock.acquire(blocking, timeout)

    def release(self) -> None:
        """Release the lock."""
        self._lock.release()

    def locked(self) -> bool:
        """Whether the lock is held."""
        return self._lock.locked()

    def __enter__(self) -> bool:
        return self._lock.acquire()

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._lock.release()

    def _renew(self) -> None:
        self._lock = threading.Lock()


_LOCKS: weakref.WeakSet[ForkLock] = weakref.WeakSet()


def in_forked_child(action: Callable[[], None]) -> None:
    """Run ``action`` in every child this process forks (after its locks are renewed);
    nothing where the platform does not fork."""
    if hasattr(os, "register_at_fork"):
        os.register_at_fork(after_in_child=action)


def _renew_locks() -> None:
    for lock in list(_LOCKS):
        lock._renew()


if hasattr(os, "register_at_fork"):  # pragma: no branch - POSIX
    os.register_at_fork(after_in_child=_renew_locks)
