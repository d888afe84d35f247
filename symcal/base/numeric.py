"""Evaluate per-observation CasADi functions over a whole dataset, in chunks.

A function of ONE observation, ``f(theta, u)``, is mapped over a chunk of observations
with CasADi's ``map`` (a loop over the one-observation code: the graph never grows with N
and building it costs microseconds; outside symcal's pass threads a chunk's rows are split
over the cores, :data:`SPLIT_WORK`), and the chunks are concatenated.
Evaluation goes through CasADi's buffer interface: inputs are read from and outputs
written to numpy memory directly (column-major ``k × n`` is C-contiguous ``n × k``), with
no conversion to CasADi matrices.  θ is repeated once per row of a per-thread buffer, and
refilled only when it changes.

The buffer call releases the GIL, so chunks evaluated by different threads run on
different cores: every thread has its own buffers (:class:`threading.local`).  Results
are bit-for-bit the same whichever thread evaluates a chunk.

A :class:`Mapped` pickles as its CasADi serialisation, so a Dask worker receives it as
bytes and rebuilds it once per process (:func:`from_serialized` keeps a memo by content).
"""

from __future__ import annotations

import hashlib
import threading
import weakref
from collections.abc import Callable, Iterable, Iterator
from typing import Any, TypeVar

import casadi as ca
import numpy as np

from symcal.base.cores import inner_threads
from symcal.base.forks import ForkLock

#: An executor's ``map``: a task over pieces, the results in the pieces' order.
PieceMap = Callable[[Callable[[slice], list[np.ndarray]], list[slice]],
                    Iterable[list[np.ndarray]]]

#: An interpreted chunk of at least this much work (rows × the function's instructions),
#: evaluated outside symcal's pass threads, is split over
#: :func:`~symcal.base.cores.inner_threads` threads by CasADi's threaded map (each row's
#: code is the same: the results are bit for bit those of the serial map).  A small pass
#: then uses the cores too: on 2 cores 1.3x per chunk at this much work, 1.6-1.9x from
#: ten times more (the improvement loop's trials of an implicit model, 9000 instructions
#: per row); below it, starting the threads costs more than they give.
SPLIT_WORK = 1 << 18
#: Observations per chunk.  Each chunk is padded to a power of two (by repeating its
#: last observation), so a function has at most log2(CHUNK) mapped forms, built once.
CHUNK = 8_192


def chunks(n: int, size: int = CHUNK) -> Iterator[slice]:
    """Consecutive slices of ``range(n)`` of at most ``size`` elements."""
    for start in range(0, n, size):
        yield slice(start, min(n, start + size))


def _view(array: np.ndarray) -> memoryview:
    """A memoryview of a C-contiguous array (numpy arrays are buffers)."""
    return memoryview(array)  # type: ignore[arg-type]  # numpy's stubs lack __buffer__


class _Buffers:
    """One thread's buffers for one mapped size: θ rows, input columns, outputs."""

    def __init__(self, mapped_fn: ca.Function, fn: ca.Function, size: int) -> None:
        self.buf, self.trigger = mapped_fn.buffer()
        self.theta = np.empty((size, fn.nnz_in(0)))
        self.theta_key: bytes | None = None
        self.columns = np.empty((size, fn.nnz_in(1)))
        self.outs = [np.empty((size, fn.nnz_out(i))) for i in range(fn.n_out())]
        # the binding takes the size from the memoryview (its stub wrongly asks for it)
        self.buf.set_arg(0, _view(self.theta))  # type: ignore[call-arg]
        self.buf.set_arg(1, _view(self.columns))  # type: ignore[call-arg]
        for i, out in enumerate(self.outs):
            self.buf.set_res(i, _view(out))  # type: ignore[call-arg]


class Mapped:
    """A per-observation function ready to evaluate over many observations.

    Parameters
    ----------
    fn
        ``fn(theta, u) -> (out_1, ..., out_m)``, each output a dense column vector.
    """

    def __init__(self, fn: ca.Function) -> None:
        self.fn = fn
        self._maps: dict[tuple[int, int], ca.Function] = {}
        self._instructions = int(fn.n_instructions()) if fn.is_a("SXFunction") else 0
        self._lock = ForkLock()
        self._local = threading.local()
        self._serialized: bytes | None = None

    def __reduce__(self) -> tuple[Any, tuple[bytes]]:
        return from_serialized, (self.serialized(),)

    def serialized(self) -> bytes:
        """The CasADi serialisation of the one-observation function."""
        if self._serialized is None:
            self._serialized = self.fn.serialize().encode()
        return self._serialized

    def _buffers(self, size: int) -> _Buffers:
        width = inner_threads() if size * self._instructions >= SPLIT_WORK else 1
        key = (size, width)
        states: dict[tuple[int, int], _Buffers] = self._local.__dict__.setdefault(
            "states", {})
        if key not in states:
            with self._lock:
                if key not in self._maps:   # θ given per row; split over the cores
                    self._maps[key] = (self.fn.map(size, "thread", width) if width > 1
                                       else self.fn.map(size))
            states[key] = _Buffers(self._maps[key], self.fn, size)
        return states[key]

    def evaluate(self, theta: np.ndarray, u: np.ndarray) -> list[np.ndarray]:
        """Evaluate on one chunk (``u`` is ``n_u × n``, n ≤ :data:`CHUNK` preferred).

        Returns ``n × k`` arrays that are views of this thread's buffers: valid until the
        next evaluation of this function by the same thread (copy to keep them).
        """
        n = u.shape[1]
        size = 1 << max(0, (n - 1).bit_length())      # padded to a power of two
        b = self._buffers(size)
        th = np.ascontiguousarray(theta, dtype=float)
        key = th.tobytes()
        if key != b.theta_key:
            b.theta[:] = th[None, :]
            b.theta_key = key
        b.columns[:n] = u.T
        b.columns[n:] = u.T[-1:] if n else 0.0         # repeat a real observation
        b.trigger()
        return [out[:n] for out in b.outs]

    def chunk(self, theta: np.ndarray, u: np.ndarray) -> list[np.ndarray]:
        """Evaluate on one chunk: ``u`` is ``n_u × n``; returns ``n × k`` arrays (copies)."""
        return [out.copy() for out in self.evaluate(theta, u)]

    def __call__(self, theta: np.ndarray, u: np.ndarray, size: int = CHUNK,
                 map_pieces: PieceMap | None = None) -> list[np.ndarray]:
        """Evaluate over all observations (``u`` is ``n_u × N``), chunk by chunk; with
        ``map_pieces`` (an executor's ``map``: the chunks' results in order) on its
        threads, the same bits."""
        n = u.shape[1]
        outs = [np.empty((n, self.fn.nnz_out(i))) for i in range(self.fn.n_out())]
        parts = list(chunks(n, size))
        if map_pieces is None:
            values: Iterable[list[np.ndarray]] = (self.evaluate(theta, u[:, p]) for p in parts)
        else:
            values = map_pieces(lambda part: self.chunk(theta, u[:, part]), parts)
        for part, value in zip(parts, values, strict=True):
            for out, column in zip(outs, value, strict=True):
                out[part] = column
        return outs


_MEMO: dict[bytes, Mapped] = {}
_MEMO_LOCK = ForkLock()


def from_serialized(data: bytes) -> Mapped:
    """The :class:`Mapped` of a serialised one-observation function, built once per
    process (memo by content)."""
    key = hashlib.sha256(data).digest()
    with _MEMO_LOCK:
        if key not in _MEMO:
            out = Mapped(ca.Function.deserialize(data.decode()))
            out._serialized = data
            _MEMO[key] = out
        return _MEMO[key]


def shared_mapped(theta: ca.SX, u: ca.SX, outputs: list[ca.SX], name: str = "f") -> Mapped:
    """Like :func:`mapped`, but one :class:`Mapped` per process for equal functions (memo
    by the function's CasADi serialisation): solves and stages of the same problem share
    the mapped forms and evaluation buffers."""
    fn = ca.Function(name, [theta, u], [ca.densify(ca.vec(o)) for o in outputs])
    return from_serialized(fn.serialize().encode())


def mapped(theta: ca.SX, u: ca.SX, outputs: list[ca.SX], name: str = "f") -> Mapped:
    """Build a :class:`Mapped` function of ``(theta, u)`` returning ``outputs`` (columns)."""
    fn = ca.Function(name, [theta, u], [ca.densify(ca.vec(o)) for o in outputs])
    return Mapped(fn)


_T = TypeVar("_T")
#: Per owner (a problem, while it lives): what was built for it, by key.
_OWNED: weakref.WeakKeyDictionary[Any, dict[Any, Any]] = weakref.WeakKeyDictionary()
_OWNED_LOCK = ForkLock()


def owned(owner: Any, key: Any, build: Callable[[], _T]) -> _T:
    """``build()`` once per ``owner`` (held weakly) and ``key``: what depends only on a
    problem's structure (its mapped functions, the expressions an analysis examines) is
    built for its first solve and reused by the next ones."""
    with _OWNED_LOCK:
        memo = _OWNED.setdefault(owner, {})
        if key in memo:
            return memo[key]
    value = build()
    with _OWNED_LOCK:
        return memo.setdefault(key, value)
