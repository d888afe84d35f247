"""Serial correlation and its standard errors on a log kept as shards, by passes.

What :mod:`symcal.analysis.serial` does on rows in memory, shard by shard: whether the
rows are in time order (each shard's own order, and each shard's first time not before
the last of the one before); the lag-1 autocorrelation of each weighted residual about
its mean over all rows (two passes: the means, then each shard's ``Σ c²`` and
``Σ c_i c_{i-1}`` with its first and last row, joined across the boundaries,
:func:`~symcal.analysis.serial.lag_one_of`); and, where it is found, the Newey-West sum of
the per-row scores (each shard's sum within it and its first and last L rows of scores,
joined across the boundaries, :func:`~symcal.analysis.serial.hac_combine`).  The weights
of a weighted objective are computed in the passes
(:class:`~symcal.solvers.weighed.Weighed`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from symcal.analysis.serial import (
    HacPart,
    LagSums,
    SerialCorrelation,
    bandwidth,
    detected,
    hac_combine,
    hac_part,
    lag_one_of,
    lag_sums,
)
from symcal.base.linalg import information_coordinates, sqrt_psd
from symcal.base.numeric import Mapped, chunks
from symcal.problem.symbolic import Problem
from symcal.solvers.base import SolverOutput
from symcal.solvers.objective import Objective, Source
from symcal.solvers.weighed import (
    Residuals,
    RowWeigher,
    linearised_function,
    map_pieces,
    read_piece,
    residual_rows,
)


@dataclass(frozen=True)
class _Times:
    """A piece's ``(rows, first time, last time, in order within)``."""

    column: str

    def __call__(self, piece: Any) -> tuple[int, float, float, bool]:
        t = read_piece(piece, (self.column,))[0]
        if not t.size:
            return 0, np.nan, np.nan, True
        return t.size, float(t[0]), float(t[-1]), bool(np.all(np.diff(t) >= 0))


def time_column(problem: Problem, columns: Any) -> str | None:
    """The problem's time column (``role: time``) if the data have it."""
    return next((c for c, spec in problem.column_specs.items()
                 if spec.role == "time" and c in columns), None)


def time_ordered_passes(problem: Problem, data: Source, columns: Any) -> bool:
    """Whether the rows of ``data`` (whose columns are ``columns``) are in time order, as
    :func:`symcal.analysis.floors.time_ordered` says of rows in memory (one pass)."""
    time = time_column(problem, columns)
    if time is None or data.n < 3:
        return False
    parts = [p for p in map_pieces(_Times(time), data, "time_order") if p[0]]
    if not all(p[3] for p in parts):
        return False
    if not all(b[1] >= a[2] for a, b in zip(parts, parts[1:], strict=False)):
        return False
    return bool(parts[-1][2] > parts[0][1])


@dataclass(frozen=True)
class WeightedRows:
    """The weighted residual rows of a chunk: ``g`` times its row factors."""

    rows: Residuals
    weigher: RowWeigher | None

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """``m × n_g``."""
        g = self.rows(u)
        if self.weigher is None:
            return g
        w = self.weigher(u)
        return np.einsum("mab,mb->ma", w, g) if w.ndim == 3 else g * w


def weighted_rows(objective: Objective, theta: np.ndarray, observations: int = 0
                  ) -> WeightedRows:
    """The weighted residual rows of ``objective`` (its weigher's factors applied)."""
    if objective.row_weights is not None:
        raise ValueError("row weights held in memory: use the objective's own passes")
    return WeightedRows(residual_rows(objective, theta, observations),
                        getattr(objective, "weigher", None))


@dataclass(frozen=True)
class _Means:
    rows: WeightedRows
    columns: tuple[str, ...]

    def __call__(self, piece: Any) -> tuple[np.ndarray, int]:
        u = read_piece(piece, self.columns)
        total: np.ndarray | None = None
        for part in chunks(u.shape[1]):
            s = self.rows(u[:, part]).sum(axis=0)
            total = s if total is None else total + s
        return (np.zeros(0) if total is None else total), u.shape[1]


@dataclass(frozen=True)
class _Lags:
    rows: WeightedRows
    columns: tuple[str, ...]
    mean: np.ndarray

    def __call__(self, piece: Any) -> LagSums:
        u = read_piece(piece, self.columns)
        return lag_sums((self.rows(u[:, part]) - self.mean[None, :]
                         for part in chunks(u.shape[1])), self.mean.size)


@dataclass(frozen=True)
class _Scores:
    """A piece's :class:`~symcal.analysis.serial.HacPart` of the per-row scores
    ``J_iᵀ g_i`` (weighted) at ``theta``, in the coordinates ``to`` maps them to
    (:func:`~symcal.base.linalg.information_coordinates`)."""

    fn: Mapped
    theta: np.ndarray
    weigher: RowWeigher | None
    shape: tuple[int, int]
    lags: int
    columns: tuple[str, ...]
    to: np.ndarray

    def scores(self, u: np.ndarray) -> Iterator[np.ndarray]:
        ng, n = self.shape
        for part in chunks(u.shape[1]):
            block = u[:, part]
            g, jt = (np.array(x) for x in self.fn.evaluate(self.theta, block))
            m = g.shape[0]
            jac = jt.reshape(m, ng, n)
            w = None if self.weigher is None else self.weigher(block)
            if w is not None and w.ndim == 3:
                g, jac = np.einsum("mab,mb->ma", w, g), np.einsum("mab,mbn->man", w, jac)
            elif w is not None:
                g, jac = g * w, jac * w[:, :, None]
            yield np.einsum("ma,man->mn", g, jac) @ self.to

    def __call__(self, piece: Any) -> HacPart:
        return hac_part(self.scores(read_piece(piece, self.columns)), self.lags,
                        self.to.shape[1])


def serial_passes(objective: Objective, data: Source, out: SolverOutput
                  ) -> tuple[SerialCorrelation, np.ndarray | None]:
    """Serial correlation of the stage's weighted residuals on time-ordered rows, and
    where it is found the HAC meat for its standard errors (as ``symcal.solve``'s on rows
    in memory), by passes over ``data``."""
    columns = tuple(objective.problem.columns)
    rows = weighted_rows(objective, out.theta, data.n)
    means = map_pieces(_Means(rows, columns), data, "serial_means")
    n = sum(m[1] for m in means)
    mean = np.sum([m[0] for m in means if m[1]], axis=0) / n
    rho, z = lag_one_of(map_pieces(_Lags(rows, columns, mean), data, "serial_lags"))
    found = detected(objective.constraints, rho, n, len(objective.constraints), z)
    if not found.detected:
        return found, None
    lags = bandwidth(max(found.rho, key=abs), n)
    n_free = len(objective.index)
    to, back = information_coordinates(out.r_factor, out.rows, objective.scales)
    rank = to.shape[1]                # the identifiable parameters, by the same SVD
    task = _Scores(linearised_function(objective, data.n), rows.rows.theta, rows.weigher,
                   (len(objective.constraints), n_free), lags, columns, to)
    meat = hac_combine(map_pieces(task, data, "hac_scores", "linearised"), lags,
                       to.shape[1])
    meat *= out.rows / max(out.rows - rank, 1)
    return replace(found, lags=lags), sqrt_psd(meat).T @ back
