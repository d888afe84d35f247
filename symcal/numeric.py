"""Evaluate per-observation CasADi functions over a whole dataset, in chunks.

A function of ONE observation, ``f(theta, u)``, is mapped serially over a chunk of
observations (the graph never grows with N) and the chunks are concatenated; θ is
broadcast.  Outputs must be column vectors; each comes back as an ``N × k`` array.
"""

from __future__ import annotations

from collections.abc import Iterator

import casadi as ca
import numpy as np

CHUNK = 65_536


def chunks(n: int, size: int = CHUNK) -> Iterator[slice]:
    """Consecutive slices of ``range(n)`` of at most ``size`` elements."""
    for start in range(0, n, size):
        yield slice(start, min(n, start + size))


class Mapped:
    """A per-observation function ready to evaluate over many observations.

    Parameters
    ----------
    fn
        ``fn(theta, u) -> (out_1, ..., out_m)``, each output a column vector.
    """

    def __init__(self, fn: ca.Function) -> None:
        self.fn = fn
        self._maps: dict[int, ca.Function] = {}

    def _map(self, n: int) -> ca.Function:
        if n not in self._maps:
            self._maps[n] = self.fn.map(n, "serial")
        return self._maps[n]

    def chunk(self, theta: np.ndarray, u: np.ndarray) -> list[np.ndarray]:
        """Evaluate on one chunk: ``u`` is ``n_u × n``; returns ``n × k`` arrays."""
        n = u.shape[1]
        outs = self._map(n)(theta, u)
        if not isinstance(outs, (list, tuple)):
            outs = [outs]
        return [np.asarray(o).reshape(-1, n).T for o in outs]

    def __call__(self, theta: np.ndarray, u: np.ndarray, size: int = CHUNK) -> list[np.ndarray]:
        """Evaluate over all observations (``u`` is ``n_u × N``)."""
        n = u.shape[1]
        parts = [self.chunk(theta, u[:, s]) for s in chunks(n, size)]
        return [np.concatenate([p[i] for p in parts], axis=0) for i in range(self.fn.n_out())]


def mapped(theta: ca.SX, u: ca.SX, outputs: list[ca.SX], name: str = "f") -> Mapped:
    """Build a :class:`Mapped` function of ``(theta, u)`` returning ``outputs`` (columns)."""
    fn = ca.Function(name, [theta, u], [ca.vec(o) for o in outputs])
    return Mapped(fn)
