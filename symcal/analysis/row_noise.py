"""The noise each observation's residuals carry, propagated from the readings' declared
noise (first order, the noise symbols of :attr:`~symcal.problem.symbolic.Problem.noisy`):
per row the residuals, ``L = ∂r/∂ε·diag(σ)`` and ``J = ∂r/∂θ``, each row's covariance
``C = L Lᵀ``, its pseudo-inverse and inverse square root, and the fit's weights
(:class:`Fit`).  What :mod:`symcal.analysis.floors` sums, and the weights of
``weighting: propagated``."""

from __future__ import annotations

import weakref
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from symcal.base import jit
from symcal.base.forks import ForkLock
from symcal.base.numeric import Mapped, chunks, mapped, owned
from symcal.data.dataset import ColumnView, Dataset
from symcal.problem.symbolic import Problem
from symcal.solvers.executor import default_executor

#: A row's propagated variance below this share of the largest is an exact reading.
EXACT = 1e-12
#: How far above :data:`EXACT` a row's smallest eigenvalue must clearly be for its
#: covariance to be inverted directly (:func:`row_pinv`).
CLEAR = 1e3


@dataclass(frozen=True)
class Fit:
    """How the estimate was fitted: on ``dataset``, the constraints ``constraints``, the
    parameters ``free``, weighted by ``weighting`` (``equal``: by each constraint's σ;
    ``estimated``: by ``whiten`` applied to g/σ; ``propagated``: by the propagated
    covariance at the estimate)."""

    dataset: str
    constraints: tuple[str, ...]
    free: np.ndarray
    weighting: str
    whiten: np.ndarray | None = None


@dataclass
class Entries:
    """The residuals and comparisons examined on one dataset, as in
    :func:`symcal.analysis.fit.series_statistics`."""

    names: list[str] = field(default_factory=list)
    kinds: list[str] = field(default_factory=list)
    exprs: list[ca.SX] = field(default_factory=list)     # in the noisy view
    centred: list[bool] = field(default_factory=list)
    declared: list[bool] = field(default_factory=list)


def entries_of(problem: Problem, ds: Dataset) -> Entries:
    """The entries of ``ds`` (built once per problem, dataset name and columns)."""
    key = ("floor entries", ds.name, frozenset(ds.columns))
    return owned(problem, key, lambda: _build_entries(problem, ds))


def _build_entries(problem: Problem, ds: Dataset) -> Entries:
    noisy = problem.noisy
    out = Entries()
    comparisons = {c.name: c for c in noisy.comparisons}
    for c, plain in zip(noisy.constraints, problem.constraints, strict=True):
        out.names.append(c.name)
        out.kinds.append("constraint")
        out.exprs.append(c.sx)
        out.centred.append(False)
        out.declared.append(not problem.undeclared(plain.sx))
    for comp in problem.comparisons:
        if comp.datasets is not None and ds.name not in comp.datasets:
            continue
        if any(c not in ds.columns for c in problem.columns_of(comp.reference)):
            continue
        twin = comparisons[comp.name]
        out.names.append(comp.name)
        out.kinds.append("comparison")
        out.exprs.append(twin.estimate - twin.reference)
        out.centred.append(comp.remove_mean)
        out.declared.append(not problem.undeclared(comp.estimate - comp.reference))
    return out


def row_propagation(problem: Problem, names: tuple[str, ...], exprs: list[ca.SX],
                    free: np.ndarray) -> RowPropagation:
    """The :class:`RowPropagation` of ``exprs`` (named ``names``: the same names of one
    problem are the same expressions), built once per problem."""
    key = ("floors", names, np.asarray(free, dtype=bool).tobytes())
    return owned(problem, key, lambda: RowPropagation(problem, exprs, free))


class RowPropagation:
    """Per observation: the residuals, ``L = ∂r/∂ε·diag(σ)`` and ``J = ∂r/∂θ_free``; the
    residuals alone by a function of their own, and with the residuals at a second point
    (the start) by a third.  Each is a function of ``(θ, u)`` with the readings' errors
    ``ε`` set to 0 in its expressions (no input of zeros per row).  Each pass evaluates
    the compiled twin when it pays (:func:`symcal.base.jit.select`: the same bits)."""

    def __init__(self, problem: Problem, exprs: list[ca.SX], free: np.ndarray) -> None:
        noisy = problem.noisy
        readings = [r for r in noisy.readings if r.sigma > 0]
        eps = ca.vertcat(*(r.symbol for r in readings)) if readings else ca.SX(0, 1)
        sigma = np.array([r.sigma for r in readings])
        e = ca.vertcat(*exprs)
        self.n_e, self.n_eps = len(exprs), len(readings)
        self.n_p = int(np.sum(free))
        theta_free = noisy.theta[np.flatnonzero(free).tolist()]
        jac_eps = ca.mtimes(ca.jacobian(e, eps), ca.diag(ca.DM(sigma))) if readings \
            else ca.SX(self.n_e, 0)
        outs = [e, jac_eps.T, ca.jacobian(e, theta_free).T]
        if readings:     # evaluated where the errors are 0: the readings as recorded
            outs = ca.substitute(outs, [eps], [ca.SX.zeros(eps.shape)])
        self._theta, self._u, self._outs = noisy.theta, noisy.u, outs
        self.fn = mapped(noisy.theta, noisy.u, outs, "noise")
        self.plain: Mapped = mapped(noisy.theta, noisy.u, [outs[0]], "noise_residuals")
        self._with_start: list[Mapped] = []
        self._lock = ForkLock()
        self.columns = noisy.columns

    @property
    def with_start(self) -> Mapped:
        """``([θ; θ₀], u) → (r, Lᵀ, Jᵀ, r(θ₀))``: :attr:`fn` and the residuals at a second
        point in one evaluation, whose terms of the readings alone are shared (built on
        first use)."""
        with self._lock:
            if not self._with_start:
                start = ca.SX.sym("theta_start", self._theta.shape[0])
                r0 = ca.substitute(self._outs[0], self._theta, start)
                self._with_start.append(mapped(ca.vertcat(self._theta, start), self._u,
                                               [*self._outs, r0], "noise_with_start"))
            return self._with_start[0]

    def __getstate__(self) -> dict[str, Any]:
        """Picklable (a task of a log kept as shards carries it): the functions, built,
        without their expressions (CasADi pickles no SX) and the lock."""
        self.with_start  # noqa: B018 - built before its expressions are dropped
        state = dict(self.__dict__)
        for name in ("_theta", "_u", "_outs", "_lock"):
            state.pop(name, None)     # absent once unpickled
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._lock = ForkLock()

    def at(self, fn: Mapped, u: np.ndarray | ColumnView, theta: np.ndarray, part: slice
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(r, L, J)`` of the observations ``part`` of ``u`` (the dataset's columns) by
        ``fn`` (:attr:`fn` or its twin): ``r`` m × n_e, ``L`` m × n_e × n_ε, ``J``
        m × n_e × n_p."""
        r, lt, jt = fn.chunk(theta, u[:, part])
        m = r.shape[0]
        return r, lt.reshape(m, self.n_e, self.n_eps), jt.reshape(m, self.n_e, self.n_p)

    def at_and_start(self, fn: Mapped, u: np.ndarray | ColumnView, theta: np.ndarray,
                     theta0: np.ndarray, part: slice
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`at` and the residuals at ``theta0`` (m × n_e), by ``fn``
        (:attr:`with_start` or its twin): one evaluation."""
        r, lt, jt, r0 = fn.chunk(np.concatenate([theta, theta0]), u[:, part])
        m = r.shape[0]
        return (r, lt.reshape(m, self.n_e, self.n_eps), jt.reshape(m, self.n_e, self.n_p),
                r0)

    def rows(self, ds: Dataset, theta: np.ndarray
             ) -> Iterator[tuple[slice, np.ndarray, np.ndarray, np.ndarray]]:
        """``(rows, r, L, J)`` chunk by chunk, in order (evaluated on the in-memory
        passes' executor: threads for a large dataset, the same bits)."""
        u = ds.columns_view(self.columns)
        fn = jit.select(self.fn, ds.n)
        parts = list(chunks(ds.n))
        for part, (r, lmat, jac) in zip(parts, default_executor(ds.n).map(
                lambda part: self.at(fn, u, theta, part), parts), strict=True):
            yield part, r, lmat, jac

    def residuals(self, u: np.ndarray, theta: np.ndarray, part: slice) -> np.ndarray:
        """The residuals of the observations ``part`` of ``u`` (the dataset's columns) at
        ``theta`` (m × n_e)."""
        block = u[:, part]
        return jit.select(self.plain, block.shape[1]).chunk(theta, block)[0]


def row_pinv(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row, the pseudo-inverse of a covariance (m × n × n) and its rank.

    A row whose every eigenvalue is clearly above :data:`EXACT` of the largest
    (``det > CLEAR·EXACT·trⁿ``: ``λ_min ≥ det / trⁿ⁻¹`` and ``λ_max ≤ tr``) has the inverse
    for pseudo-inverse, in closed form up to 3 × 3 (the eigen-decomposition of many small
    matrices is slow); the others (an exact reading, a nearly singular row) the
    eigen-decomposition's, its eigenvalues below that share dropped."""
    m, n = c.shape[0], c.shape[-1]
    if n == 0:
        return np.zeros_like(c), np.zeros(m, dtype=int)
    inv, det = _inverse(c)
    tr = np.trace(c, axis1=1, axis2=2)
    with np.errstate(over="ignore", invalid="ignore"):
        clear = (tr > 0) & (det > CLEAR * EXACT * tr**n) & np.all(np.isfinite(inv),
                                                                   axis=(1, 2))
    rank = np.full(m, n)
    if not np.all(clear):
        rest = ~clear
        w, v = np.linalg.eigh(c[rest])
        top = np.max(w, axis=1, keepdims=True)
        keep = w > EXACT * np.maximum(top, 1e-300)
        scaled = np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0)
        inv[rest] = np.einsum("mab,mb,mcb->mac", v, scaled, v)
        rank[rest] = keep.sum(axis=1)
    return inv, rank


def _inverse(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row, the inverse of a square matrix (m × n × n) and its determinant: by
    cofactors up to 3 × 3, by LAPACK beyond (a singular row gives non-finite values)."""
    n = c.shape[-1]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if n == 1:
            det = c[:, 0, 0].copy()
            return (1.0 / det)[:, None, None], det
        if n == 2:
            a, b, d, e = c[:, 0, 0], c[:, 0, 1], c[:, 1, 0], c[:, 1, 1]
            det = a * e - b * d
            adj = np.stack([np.stack([e, -b], axis=1), np.stack([-d, a], axis=1)], axis=1)
            return adj / det[:, None, None], det
        if n == 3:
            a, b, f = c[:, 0, 0], c[:, 0, 1], c[:, 0, 2]
            d, e, g = c[:, 1, 0], c[:, 1, 1], c[:, 1, 2]
            h, k, i = c[:, 2, 0], c[:, 2, 1], c[:, 2, 2]
            c00, c01, c02 = e * i - g * k, g * h - d * i, d * k - e * h
            det = a * c00 + b * c01 + f * c02
            adj = np.stack([np.stack([c00, f * k - b * i, b * g - f * e], axis=1),
                            np.stack([c01, a * i - f * h, f * d - a * g], axis=1),
                            np.stack([c02, b * h - a * k, a * e - b * d], axis=1)], axis=1)
            return adj / det[:, None, None], det
        sign, logdet = np.linalg.slogdet(c)
        det = sign * np.exp(logdet)
        out = np.full_like(c, np.nan)
        ok = det != 0
        out[ok] = np.linalg.inv(c[ok])
        return out, det


def inverse_sqrt_rows(c: np.ndarray) -> tuple[np.ndarray, int]:
    """Per row, the symmetric ``C^-½`` of a covariance (m × n × n), and how many rows are
    singular (a reading the residuals use is exact)."""
    w, v = np.linalg.eigh(c)
    top = np.max(w, axis=1, keepdims=True)
    keep = w > EXACT * np.maximum(top, 1e-300)
    inv = np.where(keep, 1.0 / np.sqrt(np.where(keep, w, 1.0)), 0.0)
    singular = int(np.sum(~np.all(keep, axis=1)))
    return np.einsum("mab,mb,mcb->mac", v, inv, v), singular


#: Row covariances kept per problem and constraints (the last points asked, at most
#: this many values in each): a propagated solve asks for them at the start and the
#: estimate of each of its solves, its floor, the next stage's start and the outliers,
#: at about half as many distinct points.
KEEP_COVARIANCES = 2
KEEP_VALUES = 1 << 23


def row_covariances(problem: Problem, constraints: tuple[str, ...], ds: Dataset,
                    theta: np.ndarray) -> np.ndarray:
    """The propagated covariance of each observation's weighted constraints g/σ
    (N × n_g × n_g, read-only), at ``theta``: the weights of ``weighting: propagated``.
    The last :data:`KEEP_COVARIANCES` asked of a dataset in memory are kept (the same
    bits, without another pass)."""
    noisy = problem.noisy
    quantities = [noisy.constraint(n) for n in constraints]
    sigma = np.array([q.sigma for q in quantities])
    prop = row_propagation(problem, ("covariances", *constraints),
                           [q.sx for q in quantities],
                           np.zeros(len(problem.parameters), dtype=bool))
    kept: list[tuple[Any, bytes, np.ndarray]] = owned(
        problem, ("row covariances", tuple(constraints)), list)
    key = np.ascontiguousarray(theta, dtype=float).tobytes()
    for ref, at, found in list(kept):
        if ref() is ds and at == key:
            return found
    out = np.empty((ds.n, len(constraints), len(constraints)))
    for part, _, lmat, _ in prop.rows(ds, theta):
        lmat = lmat / sigma[None, :, None]
        out[part] = row_grams(lmat)
    out.setflags(write=False)
    if out.size <= KEEP_VALUES:
        kept[:] = [*kept[1 - KEEP_COVARIANCES:], (weakref.ref(ds), key, out)]
    return out


def row_grams(lmat: np.ndarray) -> np.ndarray:
    """Per row, ``L Lᵀ`` (m × n × k → m × n × n; a stacked product, twice as fast as the
    sum of products an einsum loops over here)."""
    return lmat @ np.swapaxes(lmat, 1, 2)


def fit_weights(fit: Fit, c: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """The fit's weights W_i of the fitted constraints, internal units (m × n_f × n_f)."""
    m, n = c.shape[0], c.shape[1]
    if fit.weighting == "propagated":
        return row_pinv(c)[0]
    scale = np.diag(1.0 / sigma)
    if fit.weighting == "estimated" and fit.whiten is not None:
        t = fit.whiten @ scale
        return np.broadcast_to(t.T @ t, (m, n, n))
    return np.broadcast_to(scale @ scale, (m, n, n))


def assumed_covariance(c: np.ndarray, variances: np.ndarray | None) -> np.ndarray:
    """Per row, the covariance ``c`` (m × n × n) with each entry k whose variance
    ``variances[k]`` is given (not NaN) taken as independent of the others, of that
    variance: its floor estimated from the data, where no noise is declared."""
    if variances is None or not np.any(given := ~np.isnan(variances)):
        return c
    c = c.copy()
    for k in np.flatnonzero(given):
        c[:, k, :] = 0.0
        c[:, :, k] = 0.0
        c[:, k, k] = variances[k]
    return c
