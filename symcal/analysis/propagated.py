"""The propagated weighting of each observation, computed where the observation is read.

``weighting: propagated`` whitens each observation's constraints by ``C_i^-½``, ``C_i``
the covariance the readings' declared noise gives them at a point (first order, the
noise symbols of :attr:`~symcal.problem.symbolic.Problem.noisy`;
:func:`symcal.analysis.row_noise.row_covariances`).
A solve in memory holds these ``N × n_g × n_g`` matrices; a log kept as shards computes
them in every pass from the rows it reads (:class:`PropagatedWeights`, a
:class:`~symcal.solvers.weighed.RowWeigher`), and reduces what the weighting decides on
(singular rows, how much the weights change between two points, the mean variance) with
one pass (:class:`WeightStats`).  The same function, row by row, as in memory.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from symcal.analysis.row_noise import RowPropagation, inverse_sqrt_rows, row_grams
from symcal.base import jit
from symcal.base.numeric import Mapped, chunks
from symcal.problem.symbolic import Problem
from symcal.solvers.objective import Source
from symcal.solvers.weighed import map_pieces, read_piece


@dataclass(frozen=True)
class Covariances:
    """Each observation's propagated covariance of the constraints ``g/σ`` at ``theta``
    (``m × n_g × n_g`` for a chunk ``u``, the problem's columns in order)."""

    fn: Mapped
    theta: np.ndarray
    n_g: int
    n_eps: int
    sigma: np.ndarray

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """The chunk's covariances."""
        m = u.shape[1]
        lt = jit.select(self.fn, m).chunk(self.theta, u)[1]   # compiled when it pays
        lmat = lt.reshape(m, self.n_g, self.n_eps) / self.sigma[None, :, None]
        return row_grams(lmat)

    def at(self, theta: np.ndarray) -> Covariances:
        """The same covariances at another point."""
        return Covariances(self.fn, np.array(theta, dtype=float), self.n_g, self.n_eps,
                           self.sigma)


def covariances(problem: Problem, constraints: tuple[str, ...], theta: np.ndarray
                ) -> Covariances:
    """The propagated covariances of ``constraints`` at ``theta``, row by row (the rows of
    :func:`symcal.analysis.row_noise.row_covariances`)."""
    noisy = problem.noisy
    if noisy.columns != problem.columns:   # pragma: no cover - one build, one order
        raise ValueError("the noisy view reads the columns in another order")
    quantities = [noisy.constraint(n) for n in constraints]
    prop = RowPropagation(problem, [q.sx for q in quantities],
                          np.zeros(len(problem.parameters), dtype=bool))
    return Covariances(prop.fn, np.array(theta, dtype=float), len(constraints), prop.n_eps,
                       np.array([q.sigma for q in quantities]))


@dataclass(frozen=True)
class PropagatedWeights:
    """The weigher of ``weighting: propagated``: each observation's ``C_i^-½`` (the
    symmetric inverse square root; 0 on the directions a singular ``C_i`` lacks)."""

    covariances: Covariances

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """``m × n_g × n_g`` factors."""
        return inverse_sqrt_rows(self.covariances(u))[0]


@dataclass(frozen=True)
class WeightStats:
    """A piece's ``(observations, singular rows, Σ diag C_i, largest change)`` of the
    propagated weights at ``covariances.theta`` (the change: ``‖W_i - V_i‖ / ‖V_i‖`` against
    the weights ``V_i`` at ``before``'s point, 0 without one)."""

    covariances: Covariances
    before: Covariances | None
    columns: tuple[str, ...]

    def __call__(self, piece: Any) -> tuple[int, int, np.ndarray, float]:
        """The piece's statistics."""
        u = read_piece(piece, self.columns)
        singular, change = 0, 0.0
        diag = np.zeros(self.covariances.n_g)
        for part in chunks(u.shape[1]):
            block = u[:, part]
            c = self.covariances(block)
            w, bad = inverse_sqrt_rows(c)
            singular += bad
            diag += np.diagonal(c, axis1=1, axis2=2).sum(axis=0)
            if self.before is not None and len(c):
                v = inverse_sqrt_rows(self.before(block))[0]
                change = max(change, float(np.max(
                    np.linalg.norm(w - v, axis=(1, 2))
                    / np.maximum(np.linalg.norm(v, axis=(1, 2)), 1e-300))))
        return u.shape[1], singular, diag, change


def weight_stats(cov: Covariances, data: Source, columns: tuple[str, ...],
                 before: Covariances | None = None) -> tuple[int, np.ndarray, float]:
    """Over all rows of ``data``: the singular rows of the weights at ``cov``'s point,
    the mean propagated variance of each constraint there, and the largest change of
    the weights from ``before``'s point (one pass)."""
    parts = map_pieces(WeightStats(cov, before, columns), data, "propagated_weights")
    n = sum(p[0] for p in parts)
    diag = np.sum([p[2] for p in parts], axis=0) if parts else np.zeros(cov.n_g)
    return (sum(p[1] for p in parts), diag / max(n, 1),
            max((p[3] for p in parts), default=0.0))
