"""The least-squares objective of one solve: chosen constraints, chosen free parameters.

J(θ) = Σ_obs Σ_k (g_k(θ, u)/σ_k)².  Everything is built symbolically for ONE observation
(once per process for a problem's stage) and evaluated over all of them with CasADi
``map`` (serial), in chunks, so the graph never grows with N and memory is bounded.  Every
method is one pass over the data (:mod:`symcal.solvers.passes`) on an executor
(:mod:`symcal.solvers.executor`): the chunks of an in-memory dataset on threads for large
N, or the shards of a partitioned one (:mod:`symcal.data.shards`) on Dask workers.
"""

from __future__ import annotations

import copy
import weakref
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from symcal.base import jit
from symcal.base.errors import SolveError
from symcal.base.numeric import Mapped, chunks, shared_mapped
from symcal.data.dataset import Dataset
from symcal.data.shards import ShardedDataset
from symcal.problem.symbolic import Problem
from symcal.solvers import instrument
from symcal.solvers.executor import Executor, SerialExecutor, current, default_executor
from symcal.solvers.passes import Kind, Pass, run_pass

#: What a pass reads: a dataset in memory, or one kept as shards on disk.
Source = Dataset | ShardedDataset


@dataclass(frozen=True)
class _Built:
    """What an objective builds: its residual, Jacobian and mapped functions, and the
    last R factor it reduced (:meth:`Objective.accumulate_r`)."""

    g: ca.SX
    jac: ca.SX
    mapped: dict[str, Mapped]
    last_r: list[Any] = field(default_factory=list)
    last_g: list[Any] = field(default_factory=list)


#: Per problem (while it lives), what its objectives built, by (constraints, free
#: parameters, whitening): a problem's stages and repeated solves build each once.
_BUILT: weakref.WeakKeyDictionary[Problem, dict[Any, Any]] = weakref.WeakKeyDictionary()


@dataclass(frozen=True, eq=False)
class Objective:
    """Σ (g/σ)² over ``constraints``, as a function of the parameters in ``free``.

    Parameters
    ----------
    problem
        The symbolic problem.
    constraints
        Names of the constraints in the cost.
    free
        Boolean mask over ``problem.parameters``.
    whiten
        Optional ``n_g × n_g`` matrix T: the cost becomes Σ ‖T g‖², e.g. T = S^-½ for an
        estimated covariance S between the constraints of one observation.
    row_weights
        Optional ``N × n_g`` factors multiplying each residual row and its Jacobian row
        (the cost becomes Σ (w g)²): the square roots of the weights of an iteratively
        reweighted solve (:mod:`symcal.solvers.robust`); or ``N × n_g × n_g`` matrices
        T_i applied to each observation's g and J (the cost becomes Σ ‖T_i g_i‖²): the
        propagated weighting's ``C_i^-½``; see :meth:`with_row_weights`.
    executor
        Who runs the passes (:mod:`symcal.solvers.executor`).  None: the executor of
        an enclosing ``executor.using`` block; else in-memory data by
        :func:`~symcal.solvers.executor.default_executor` (threads for large N), and a
        partitioned dataset shard after shard in this process.
    """

    problem: Problem
    constraints: tuple[str, ...]
    free: np.ndarray
    whiten: np.ndarray | None = None
    row_weights: np.ndarray | None = None
    executor: Executor | None = None
    g: ca.SX = field(init=False, repr=False)
    jac: ca.SX = field(init=False, repr=False)
    _cache: dict[str, Mapped] = field(default_factory=dict, init=False, repr=False)
    _last_r: list[Any] = field(default_factory=list, init=False, repr=False)
    _last_g: list[Any] = field(default_factory=list, init=False, repr=False)

    def __post_init__(self) -> None:
        free = np.asarray(self.free, dtype=bool)
        object.__setattr__(self, "free", free)
        key = (tuple(self.constraints), free.tobytes(),
               None if self.whiten is None else np.asarray(self.whiten, float).tobytes())
        built = _BUILT.setdefault(self.problem, {})
        if key not in built:            # once per process for a problem's stage
            quantities = [self.problem.constraint(n) for n in self.constraints]
            g = ca.vertcat(*(q.sx / q.sigma for q in quantities))
            if self.whiten is not None:
                g = ca.mtimes(ca.DM(self.whiten), g)
            built[key] = _Built(g, ca.jacobian(g, self.theta_free), {})
        shared = built[key]
        object.__setattr__(self, "g", shared.g)
        object.__setattr__(self, "jac", shared.jac)
        object.__setattr__(self, "_cache", shared.mapped)
        object.__setattr__(self, "_last_r", shared.last_r)
        object.__setattr__(self, "_last_g", shared.last_g)

    def with_row_weights(self, row_weights: np.ndarray | None) -> Objective:
        """This objective with other per-row factors (None: none), sharing its built
        functions (no CasADi function is built again)."""
        twin = copy.copy(self)
        object.__setattr__(twin, "row_weights",
                           None if row_weights is None else np.asarray(row_weights, float))
        return twin

    def _factor(self, part: slice) -> np.ndarray | float:
        """Per-row factors of the observations ``part`` (``m × n_g``), or 1."""
        return 1.0 if self.row_weights is None else self.row_weights[part]

    @property
    def theta_free(self) -> ca.SX:
        """SX symbols of the free parameters."""
        return self.problem.theta[np.flatnonzero(self.free).tolist()]

    @property
    def index(self) -> np.ndarray:
        """Positions of the free parameters in θ."""
        return np.flatnonzero(self.free)

    @property
    def scales(self) -> np.ndarray:
        """Nominal magnitudes of the free parameters."""
        return np.array([self.problem.parameters[i].scale for i in self.index])

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the free parameters."""
        return tuple(self.problem.parameters[i].name for i in self.index)

    def nonlinear(self) -> list[str]:
        """Constraints of the cost that are not linear in the free parameters."""
        key = ("nonlinear", self.free.tobytes(), tuple(self.constraints))
        memo = _BUILT.setdefault(self.problem, {})
        if key not in memo:
            theta_free = self.theta_free
            memo[key] = [n for n in self.constraints
                         if not ca.is_linear(self.problem.constraint(n).sx, theta_free)]
        return list(memo[key])

    def accumulate_r(
        self, dataset: Source, theta: np.ndarray, transform: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, float, int]:
        """R factor of the weighted Jacobian and the reduced residual at ``theta``.

        Parameters
        ----------
        transform
            Optional ``k × n_g`` matrix T applied to each observation's block of
            residuals and Jacobian rows (T g_i, T J_i) before reduction; ``k`` may be
            less than ``n_g`` (a square root of a singular covariance).

        Returns
        -------
        (R, c, tail, rows)
            ``‖J δ + g‖² = ‖R δ + c‖² + tail`` for every step δ of the free parameters,
            J and g the weighted Jacobian and residual at ``theta``; ``rows`` counts the
            residual rows.  Accumulated chunk by chunk (TSQR: one QR per chunk, the
            chunks' R factors combined in order).  The last reduction of an in-memory
            dataset is kept: asked again for the same data, point and transform (a stage's
            analysis at its start, then the solver's first linearisation there), it is
            returned without a pass, the same bits.
        """
        n = int(self.free.sum())
        key = None
        if isinstance(dataset, Dataset) and self.row_weights is None:
            key = (np.ascontiguousarray(theta, dtype=float).tobytes(),
                   None if transform is None else np.asarray(transform, float).tobytes())
            last = self._last_r[0] if self._last_r else None
            if last is not None and last[0]() is dataset and last[1] == key:
                r_aug, rows, _ = last[2]
                return self._split_r(r_aug.copy(), rows, n)
        instrument.record_pass("r", "accumulate_r", dataset.n)
        # untransformed in memory: each constraint's Σ g² of the same evaluation too, kept
        # for cost_terms (a stage's cost per constraint at its start)
        kind: Kind = "rt" if key is not None and transform is None else "r"
        out = self._pass(kind, "linearised", dataset, theta, transform)
        if out is None:
            out = (np.zeros((0, n + 1)), 0, np.zeros(len(self.constraints)))
        r_aug, rows, terms = out[0], out[1], out[2] if kind == "rt" else None
        if key is not None:
            self._last_r[:] = [(weakref.ref(dataset), key, (r_aug.copy(), rows, terms))]
        return self._split_r(r_aug, rows, n)

    @staticmethod
    def _split_r(r_aug: np.ndarray, rows: int, n: int
                 ) -> tuple[np.ndarray, np.ndarray, float, int]:
        if r_aug.shape[0] < n + 1:
            r_aug = np.vstack([r_aug, np.zeros((n + 1 - r_aug.shape[0], n + 1))])
        return r_aug[:n, :n], r_aug[:n, n], float(r_aug[n, n] ** 2), rows

    def residual_covariance(self, dataset: Source, theta: np.ndarray, rank: int) -> np.ndarray:
        """Covariance between the weighted constraints of one observation (``n_g × n_g``),
        estimated from the residuals at ``theta`` with ``rank`` degrees of freedom used.

        On a dataset in memory without per-row weights, from :meth:`residuals` (kept:
        the stage's outliers and serial correlation read the same residuals), reduced
        chunk by chunk as the pass would, the same bits."""
        kept = self._kept_g(dataset, theta)
        if kept is None and isinstance(dataset, Dataset) and self.row_weights is None:
            kept = self.residuals(dataset, theta)
        if kept is not None:
            gram: Any = None
            for part in chunks(dataset.n):
                block = kept[part]
                value = block.T @ block
                gram = value if gram is None else gram + value
            count = dataset.n
        else:
            instrument.record_pass("residual", "residual_covariance", dataset.n)
            gram, count = self._pass("gram", "residual", dataset, theta)
        rows = count * self.g.shape[0]
        return gram / count * rows / max(rows - rank, 1)

    def score_chunks(self, dataset: Dataset, theta: np.ndarray) -> Iterator[np.ndarray]:
        """Per-row scores ``J_iᵀ g_i`` of the weighted residual at ``theta``, chunk by
        chunk in row order (``m × n_free`` each; in-memory data only), for standard
        errors that allow for correlated rows (:mod:`symcal.analysis.serial`)."""
        instrument.record_pass("linearised", "score_chunks", dataset.n)
        fn = jit.select(self._mapped("linearised", [self.g, self.jac.T]), dataset.n)
        ng, n = self.g.shape[0], int(self.free.sum())
        u = dataset.columns_view(self.problem.columns)

        def scores(part: slice) -> np.ndarray:
            g, jt = (np.array(x) for x in fn.evaluate(theta, u[:, part]))
            m = g.shape[0]
            jac = jt.reshape(m, ng, n)
            w = self.row_weights[part] if self.row_weights is not None else None
            if w is not None and w.ndim == 3:
                g, jac = np.einsum("mab,mb->ma", w, g), np.einsum("mab,mbn->man", w, jac)
            elif w is not None:
                g, jac = g * w, jac * w[:, :, None]
            return np.einsum("ma,man->mn", g, jac)

        # on the passes' executor (threads for a large dataset), the chunks in order
        yield from default_executor(dataset.n).map(scores, list(chunks(dataset.n)))

    def _kept_g(self, dataset: Source, theta: np.ndarray) -> np.ndarray | None:
        """The residuals kept from an earlier :meth:`residuals` of this dataset at this
        point (no per-row weights), or None."""
        if not isinstance(dataset, Dataset) or self.row_weights is not None:
            return None
        key = np.ascontiguousarray(theta, dtype=float).tobytes()
        for ref, at, g in self._last_g:
            if ref() is dataset and at == key:
                return g
        return None

    def _kept_terms(self, dataset: Source, theta: np.ndarray) -> np.ndarray | None:
        """Each constraint's Σ g² from the kept reduction at this point (an untransformed
        :meth:`accumulate_r` of this dataset), or None."""
        last = self._last_r[0] if self._last_r else None
        if last is None or last[0]() is not dataset or self.row_weights is not None:
            return None
        key = (np.ascontiguousarray(theta, dtype=float).tobytes(), None)
        return last[2][2] if last[1] == key else None

    def residuals(self, dataset: Dataset, theta: np.ndarray) -> np.ndarray:
        """Weighted residuals at ``theta``, ``N × n_g`` (in-memory data only; read-only).

        Without per-row weights, the residuals of the last two points asked are kept:
        a stage's analysis asks for them at its start and at its estimate several times
        (finite values, cost per constraint, outliers, serial correlation), and gets
        them, the same bits, without another pass."""
        kept = self._kept_g(dataset, theta)
        if kept is not None:
            return kept
        instrument.record_pass("residual", "residuals", dataset.n)
        g = np.asarray(self._pass("residuals", "residual", dataset, theta))
        if self.row_weights is None:
            g.setflags(write=False)
            key = np.ascontiguousarray(theta, dtype=float).tobytes()
            self._last_g[:] = [*self._last_g[-1:], (weakref.ref(dataset), key, g)]
        return g

    def cost_terms(self, dataset: Source, theta: np.ndarray) -> dict[str, float]:
        """Σ (g_k/σ_k)² of each constraint of the cost at ``theta`` (from the kept
        residuals when :meth:`residuals` was asked at this point: reduced chunk by chunk
        in the same order as the pass, the same bits)."""
        kept = self._kept_g(dataset, theta)
        reduced = self._kept_terms(dataset, theta)
        terms: Any = None
        if kept is not None:
            for part in chunks(dataset.n):
                block = kept[part]
                value = np.sum(block * block, axis=0)
                terms = value if terms is None else terms + value
        elif reduced is not None:
            terms = reduced
        else:
            instrument.record_pass("residual", "cost_terms", dataset.n)
            terms = self._pass("terms", "residual", dataset, theta)
        if terms is None:
            terms = np.zeros(len(self.constraints))
        return {name: float(terms[k]) for k, name in enumerate(self.constraints)}

    def normal_equations(
        self, dataset: Source, theta: np.ndarray
    ) -> tuple[float, np.ndarray, np.ndarray]:
        """``(Σ g², Jᵀg, JᵀJ)`` of the weighted residual at ``theta``, by chunks.

        J is evaluated by CasADi (exact AD) for one chunk of observations at a time and
        reduced with BLAS, so memory stays bounded whatever N is.
        """
        instrument.record_pass("linearised", "normal_equations", dataset.n)
        out = self._pass("normal", "linearised", dataset, theta)
        if out is None:
            n = int(self.free.sum())
            return 0.0, np.zeros(n), np.zeros((n, n))
        return float(out[0]), out[1], out[2]

    def linearised(self, theta: np.ndarray, u: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray] | None:
        """``(g, J)`` on a few observations ``u`` (``n_u × m``, columns in the problem's
        order): the stacked weighted residuals (``m·n_g``) and their Jacobian in the free
        parameters (``m·n_g × n``), by the passes' own function (its compiled twin when
        one is cached); None where either is not finite.  Not a pass over the data: for
        analyses on a sample (:mod:`symcal.analysis.gauges`)."""
        if self.row_weights is not None:
            raise SolveError("linearised: an objective with per-row weights has no sample "
                             "Jacobian")
        fn = self._mapped("linearised", [self.g, self.jac.T])
        if jit.mode() != "off":
            fn = jit.fast(fn, build=False)
        ng, n = self.g.shape[0], int(self.free.sum())
        with np.errstate(over="ignore", invalid="ignore"):
            g, jt = fn(np.ascontiguousarray(theta, dtype=float), u)
        m = g.shape[0]
        jac = jt.reshape(m * ng, n)
        g = g.reshape(m * ng)
        if not (np.all(np.isfinite(g)) and np.all(np.isfinite(jac))):
            return None
        return g, jac

    def cost(self, dataset: Source, theta: np.ndarray, keep: bool = False) -> float:
        """Σ (g/σ)² at ``theta`` (residuals only, no derivatives).

        ``keep``: where this point is the estimate the analysis reads next (the lm's
        polished point), an in-memory dataset's residuals are kept as :meth:`residuals`
        keeps them, and the cost summed from them chunk by chunk as the pass sums it, so
        that the analysis's residuals there are not a pass of their own."""
        if keep and isinstance(dataset, Dataset) and self.row_weights is None:
            g = self.residuals(dataset, theta)
            total = 0.0
            with np.errstate(over="ignore", invalid="ignore"):
                for part in chunks(dataset.n):
                    block = g[part]
                    total += float(np.sum(block * block))
            return total
        instrument.record_pass("residual", "cost", dataset.n)
        with np.errstate(over="ignore", invalid="ignore"):  # an inf cost is an answer
            return float(self._pass("cost", "residual", dataset, theta) or 0.0)

    def _pass(self, kind: Kind, fn_name: str, dataset: Source, theta: np.ndarray,
              transform: np.ndarray | None = None) -> Any:
        """One pass of ``kind`` over ``dataset`` (see :mod:`symcal.solvers.passes`): its
        chunks on :func:`~symcal.solvers.executor.default_executor`, or its shards on
        :attr:`executor` (serial when None)."""
        fn = (self._mapped("linearised", [self.g, self.jac.T]) if fn_name == "linearised"
              else self._mapped("residual", [self.g]))
        fn = jit.select(fn, dataset.n)   # its compiled twin when it pays (base/jit.py)
        task = Pass(kind, fn, np.ascontiguousarray(theta, dtype=float),
                    (self.g.shape[0], int(self.free.sum())), tuple(self.problem.columns),
                    transform)
        if isinstance(dataset, ShardedDataset):
            if self.row_weights is not None:
                raise SolveError("per-row weights are not available on a partitioned "
                                 "dataset")
            return run_pass(task, dataset.shards,
                            self.executor or current() or SerialExecutor())
        u = dataset.columns_view(self.problem.columns)
        weights = self.row_weights
        pieces: Iterable[Any] = (u[:, part] if weights is None else (u[:, part], weights[part])
                                 for part in chunks(dataset.n))
        ambient = current()
        executor = self.executor or (ambient if ambient is not None and not ambient.remote
                                     else default_executor(dataset.n))
        return run_pass(task, pieces, executor)

    def _mapped(self, name: str, outputs: list[ca.SX]) -> Mapped:
        if name not in self._cache:
            self._cache[name] = shared_mapped(self.problem.theta, self.problem.u, outputs,
                                              name)
        return self._cache[name]
