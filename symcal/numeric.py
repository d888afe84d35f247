"""Evaluate per-observation CasADi functions over a whole dataset, in chunks.

A function of ONE observation, ``f(theta, u)``, is mapped serially over a chunk of
observations (the graph never grows with N), with θ shared by all of them, and the chunks
are concatenated.  Evaluation goes through CasADi's buffer interface: inputs are read from
and outputs written to numpy memory directly (column-major ``k × n`` is C-contiguous
``n × k``), with no conversion to CasADi matrices.  Outputs are made dense column
vectors; each comes back as an ``N × k`` array.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import casadi as ca
import numpy as np

#: Observations per chunk.  Building a mapped function costs time in proportion to its
#: size (about 13 µs per observation here), so chunks stay modest and each chunk is padded
#: to a power of two: at most log2(CHUNK) mapped functions per function, built once.
CHUNK = 8_192


def chunks(n: int, size: int = CHUNK) -> Iterator[slice]:
    """Consecutive slices of ``range(n)`` of at most ``size`` elements."""
    for start in range(0, n, size):
        yield slice(start, min(n, start + size))


class Mapped:
    """A per-observation function ready to evaluate over many observations.

    Parameters
    ----------
    fn
        ``fn(theta, u) -> (out_1, ..., out_m)``, each output a dense column vector.
    """

    def __init__(self, fn: ca.Function) -> None:
        self.fn = fn
        self._maps: dict[int, tuple[ca.Function, Any, Any]] = {}

    def _map(self, n: int) -> tuple[ca.Function, Any, Any]:
        if n not in self._maps:
            mapped_fn = self.fn.map("chunk", "serial", n, [0], [])  # θ shared, not repeated
            buf, trigger = mapped_fn.buffer()
            self._maps[n] = (mapped_fn, buf, trigger)
        return self._maps[n]

    def chunk(self, theta: np.ndarray, u: np.ndarray) -> list[np.ndarray]:
        """Evaluate on one chunk: ``u`` is ``n_u × n``; returns ``n × k`` arrays."""
        n = u.shape[1]
        size = 1 << max(0, (n - 1).bit_length())      # padded to a power of two
        _, buf, trigger = self._map(size)
        th = np.ascontiguousarray(theta, dtype=float)
        columns = np.empty((size, u.shape[0]))
        columns[:n] = u.T
        columns[n:] = u.T[-1:] if n else 0.0           # repeat a real observation
        outs = [np.empty((size, self.fn.nnz_out(i))) for i in range(self.fn.n_out())]
        buf.set_arg(0, memoryview(th))  # type: ignore[arg-type]  # ndarray is a buffer
        buf.set_arg(1, memoryview(columns))  # type: ignore[arg-type]
        for i, out in enumerate(outs):
            buf.set_res(i, memoryview(out))  # type: ignore[arg-type]
        trigger()
        return [out[:n] for out in outs]

    def __call__(self, theta: np.ndarray, u: np.ndarray, size: int = CHUNK) -> list[np.ndarray]:
        """Evaluate over all observations (``u`` is ``n_u × N``)."""
        n = u.shape[1]
        parts = [self.chunk(theta, u[:, s]) for s in chunks(n, size)]
        if not parts:
            return [np.empty((0, self.fn.nnz_out(i))) for i in range(self.fn.n_out())]
        return [np.concatenate([p[i] for p in parts], axis=0) for i in range(self.fn.n_out())]


def mapped(theta: ca.SX, u: ca.SX, outputs: list[ca.SX], name: str = "f") -> Mapped:
    """Build a :class:`Mapped` function of ``(theta, u)`` returning ``outputs`` (columns)."""
    fn = ca.Function(name, [theta, u], [ca.densify(ca.vec(o)) for o in outputs])
    return Mapped(fn)
