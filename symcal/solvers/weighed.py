"""Per-row weights computed where the rows are read: no N weights held by anyone.

An in-memory solve may hold its per-row weights (``Objective.row_weights``: ``N × n_g``
factors or ``N × n_g × n_g`` matrices).  A log kept as shards must not: its weights are a
function of each row (the robust loss's ``ρ'`` of the row's residual at the point the
round froze, the propagated covariance of the row's readings), so each pass computes
them from the rows it reads.  A :class:`RowWeigher` maps one chunk of observations
(``n_u × m``, the problem's columns in order) to the chunk's factors, shaped as
``row_weights`` are; :class:`Weighed` is an objective with one: every pass over it (cost,
per-constraint terms, normal equations, TSQR, Gram matrix, residuals) first weighs each
chunk, then reduces it as the unweighted pass would reduce weighted rows
(:class:`symcal.solvers.passes.Pass`), so the closed form, ``lm`` and IPOPT run on it
unchanged, over shards on any executor (the weigher is pickled with the task).

The weighers of the solver layer: :class:`LossWeights` (a robust loss's IRLS weights,
``ρ'(z)^power`` at a frozen point) and :class:`Aside` (0 on the residuals a fit flagged
as outliers, 1 elsewhere: the fit solved again without them).  The propagated
weighting's weigher is built where the noisy view is (:mod:`symcal.analysis.propagated`).

:func:`map_pieces` runs any per-piece task (a callable of one piece, returning something
small) over a dataset in memory or kept as shards, results in the order of the pieces:
the analyses that reduce a log shard by shard use it.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from symcal.base import jit
from symcal.base.numeric import Mapped, chunks
from symcal.data.dataset import Dataset
from symcal.data.shards import ShardedDataset
from symcal.solvers import instrument
from symcal.solvers.executor import (
    Executor,
    SerialExecutor,
    blas_limit,
    current,
    default_executor,
)
from symcal.solvers.objective import Objective, Source
from symcal.solvers.passes import Kind, Pass, reduce_two, run_pass
from symcal.solvers.robust import RowLosses


class RowWeigher(Protocol):
    """The factors of a chunk's rows, computed from the chunk itself (picklable)."""

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """Factors of the observations ``u`` (``n_u × m``): ``m × n_g`` or
        ``m × n_g × n_g`` (see ``Objective.row_weights``)."""
        ...


def read_piece(piece: Any, columns: tuple[str, ...]) -> np.ndarray:
    """The observations of a piece, ``len(columns) × rows``: a block in memory as it is,
    a shard (or :class:`Whole`) read and checked."""
    if isinstance(piece, np.ndarray):
        return piece
    return np.asarray(piece.read(columns))


def read_both(piece: Any, columns: tuple[str, ...], more: tuple[str, ...]
              ) -> tuple[np.ndarray, np.ndarray]:
    """Two sets of columns of a shard (or :class:`Whole`), read once; ``more`` NaN where
    the piece lacks them."""
    ds = piece.dataset("shard")
    return ds.matrix(columns), ds.matrix(more)


@dataclass(frozen=True)
class Whole:
    """A dataset in memory as the one piece of a per-piece task (run in this process)."""

    data: Dataset

    def read(self, columns: tuple[str, ...]) -> np.ndarray:
        """``columns`` of the dataset, ``len(columns) × N``."""
        return self.data.matrix(columns)

    def dataset(self, name: str) -> Dataset:
        """The dataset itself."""
        return self.data


def pieces_of(source: Source) -> list[Any]:
    """The pieces of a per-piece task: the shards of a partitioned log, or the whole of a
    dataset in memory."""
    if isinstance(source, ShardedDataset):
        return list(source.shards)
    return [Whole(source)]


def map_pieces(task: Any, source: Source, method: str,
               kind: instrument.PassKind = "residual",
               executor: Executor | None = None) -> list[Any]:
    """``task`` on every piece of ``source`` (:func:`pieces_of`), results in their order:
    a partitioned log's shards on ``executor`` (default: the executor of an enclosing
    ``using`` block, else this process), a dataset in memory in this process.  One pass
    of ``kind`` over the data (:mod:`symcal.solvers.instrument`), by ``method``."""
    instrument.record_pass(kind, method, source.n)
    if isinstance(source, ShardedDataset):
        runner = executor or current() or SerialExecutor()
    else:
        runner = SerialExecutor()
    with blas_limit():
        return list(runner.map(task, pieces_of(source)))


@dataclass(frozen=True)
class Residuals:
    """The weighted residual rows ``g/σ`` (whitened as the objective is) of a chunk at a
    point: the residual function of an objective, evaluated once per chunk (a copy)."""

    fn: Mapped
    theta: np.ndarray

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """``m × n_g``."""
        with np.errstate(over="ignore", invalid="ignore"):
            return self.fn.chunk(self.theta, u)[0]


def residual_rows(objective: Objective, theta: np.ndarray, observations: int = 0
                  ) -> Residuals:
    """The residual rows of ``objective``'s function (before its row weights) at ``theta``
    (its compiled twin when it pays for a pass over ``observations``)."""
    fn = objective._mapped("residual", [objective.g])
    return Residuals(jit.select(fn, observations), np.ascontiguousarray(theta, dtype=float))


def linearised_function(objective: Objective, observations: int = 0) -> Mapped:
    """``(g, vec(Jᵀ))`` per observation of ``objective`` (before its row weights)."""
    return jit.select(objective._mapped("linearised", [objective.g, objective.jac.T]),
                      observations)


@dataclass(frozen=True)
class LossWeights:
    """A robust loss's IRLS weights ``ρ'((g/c)²)`` of each residual at the frozen point
    ``rows.theta``, raised to ``power`` (½: the factors of the reweighted objective; 1: the
    weights ψ = w g of the sandwich)."""

    rows: Residuals
    losses: RowLosses
    power: float = 0.5

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """``m × n_g`` factors."""
        w = self.losses.weights(self.rows(u))
        return w if self.power == 1.0 else w ** self.power


@dataclass(frozen=True)
class Flags:
    """The residuals a fit treats as outliers (:mod:`symcal.analysis.outliers`): the rows'
    ``|g - centre| / spread`` (0 where the spread is 0) at ``rows.theta`` beyond
    ``threshold``."""

    rows: Residuals
    centre: np.ndarray
    spread: np.ndarray
    threshold: float

    def z(self, u: np.ndarray) -> np.ndarray:
        """The whitened residuals of a chunk, ``m × n_g``."""
        g = self.rows(u)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.spread[None, :] > 0,
                            np.abs(g - self.centre[None, :]) / self.spread[None, :], 0.0)

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """``m × n_g``: True where flagged."""
        return self.z(u) > self.threshold


@dataclass(frozen=True)
class Aside:
    """Factors that set the flagged residuals aside: 0 where :class:`Flags` flags, else 1."""

    flags: Flags

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """``m × n_g`` factors."""
        return (~self.flags(u)).astype(float)


@dataclass(frozen=True, eq=False)
class WeighedPass:
    """A pass's task on weighted rows: each chunk weighed by ``weigher``, then reduced by
    ``task`` as a chunk of rows with those factors (picklable for Dask)."""

    task: Pass
    weigher: RowWeigher

    @property
    def kind(self) -> Kind:
        """The pass's kind."""
        return self.task.kind

    @property
    def shape(self) -> tuple[int, int]:
        """``(n_g, n_free)``."""
        return self.task.shape

    def __call__(self, piece: Any) -> Any:
        """The piece's reduction (a block in memory, or a shard to read)."""
        u = read_piece(piece, self.task.columns)
        out: Any = None
        with np.errstate(over="ignore", invalid="ignore"):
            for part in chunks(u.shape[1]):
                block = u[:, part]
                value = self.task._chunk(block, self.weigher(block))
                out = value if out is None else reduce_two(self.kind, out, value)
        return out


@dataclass(frozen=True, eq=False)
class Weighed(Objective):
    """An objective whose rows are weighted by a :class:`RowWeigher`, computed in every
    pass from the rows it reads (see the module).  ``weigher`` None: as
    :class:`~symcal.solvers.objective.Objective`."""

    weigher: RowWeigher | None = None

    @classmethod
    def of(cls, objective: Objective, weigher: RowWeigher | None) -> Weighed:
        """``objective`` (constraints, free parameters, whitening, executor) weighed by
        ``weigher``."""
        if objective.row_weights is not None:
            raise ValueError("an objective with per-row weights held in memory")
        return cls(objective.problem, objective.constraints, objective.free,
                   objective.whiten, None, objective.executor, weigher)

    def accumulate_r(
        self, dataset: Source, theta: np.ndarray, transform: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, float, int]:
        """As :meth:`Objective.accumulate_r`, on the weighted rows (never from the cache
        of the unweighted objective)."""
        if self.weigher is None:
            return super().accumulate_r(dataset, theta, transform)
        n = int(self.free.sum())
        instrument.record_pass("r", "accumulate_r", dataset.n)
        out = self._pass("r", "linearised", dataset, theta, transform)
        r_aug, rows = out if out is not None else (np.zeros((0, n + 1)), 0)
        return self._split_r(r_aug, rows, n)

    def cost(self, dataset: Source, theta: np.ndarray, keep: bool = False) -> float:
        """As :meth:`Objective.cost`; weighed rows keep no residuals, so ``keep`` asks for
        nothing more than the cost (one pass of it)."""
        return super().cost(dataset, theta, keep and self.weigher is None)

    def residuals(self, dataset: Dataset, theta: np.ndarray) -> np.ndarray:
        """Weighted residuals at ``theta``, ``N × n_g`` (in-memory data only; never from,
        nor into, what the unweighted objective keeps)."""
        if self.weigher is None:
            return super().residuals(dataset, theta)
        instrument.record_pass("residual", "residuals", dataset.n)
        return np.asarray(self._pass("residuals", "residual", dataset, theta))

    def _kept_g(self, dataset: Source, theta: np.ndarray) -> np.ndarray | None:
        """What the unweighted objective keeps of its residuals is not this one's."""
        if self.weigher is not None:
            return None
        parent = getattr(super(), "_kept_g", None)
        return None if parent is None else parent(dataset, theta)

    def _pass(self, kind: Kind, fn_name: str, dataset: Source, theta: np.ndarray,
              transform: np.ndarray | None = None) -> Any:
        if self.weigher is None:
            return super()._pass(kind, fn_name, dataset, theta, transform)
        fn = (linearised_function(self, dataset.n) if fn_name == "linearised"
              else jit.select(self._mapped("residual", [self.g]), dataset.n))
        task = WeighedPass(Pass(kind, fn, np.ascontiguousarray(theta, dtype=float),
                                (self.g.shape[0], int(self.free.sum())),
                                tuple(self.problem.columns), transform), self.weigher)
        if isinstance(dataset, ShardedDataset):
            return run_pass(task, dataset.shards,   # type: ignore[arg-type]
                            self.executor or current() or SerialExecutor())
        u = dataset.columns_view(self.problem.columns)
        pieces: Iterable[Any] = (u[:, part] for part in chunks(dataset.n))
        ambient = current()
        executor = self.executor or (ambient if ambient is not None and not ambient.remote
                                     else default_executor(dataset.n))
        return run_pass(task, pieces, executor)   # type: ignore[arg-type]


def loss_weights(objective: Objective, theta: np.ndarray, losses: RowLosses,
                 power: float = 0.5, observations: int = 0) -> LossWeights:
    """The IRLS weigher of ``objective``'s losses frozen at ``theta``."""
    return LossWeights(residual_rows(objective, theta, observations), losses, power)


@dataclass(frozen=True)
class LossCost:
    """A piece's robust cost ``Σ c² ρ((g/c)²)`` at ``rows.theta`` and whether every IRLS
    weight there is finite (``(cost, finite)``)."""

    rows: Residuals
    losses: RowLosses
    columns: tuple[str, ...]

    def __call__(self, piece: Any) -> tuple[float, bool]:
        """The piece's ``(cost, finite)``."""
        u = read_piece(piece, self.columns)
        cost, finite = 0.0, True
        with np.errstate(over="ignore", invalid="ignore"):
            for part in chunks(u.shape[1]):
                g = self.rows(u[:, part])
                finite = finite and bool(np.all(np.isfinite(self.losses.weights(g))))
                cost += self.losses.cost(g)
        return cost, finite

