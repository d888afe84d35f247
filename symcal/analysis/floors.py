"""The noise floor of every residual and the global test of the model on every dataset.

The testing theory of least-squares adjustment with condition equations, first order:

- **propagation.** At the estimate, each observation's residuals r_i (constraints and
  comparisons) have the covariance ``C_i = L_i L_iᵀ`` that the readings' declared noise
  gives them, ``L_i = (∂r/∂ε) diag(σ)`` the derivative by the readings' errors (exact, from
  the noise symbols of :attr:`~symcal.problem.symbolic.Problem.noisy`).  A residual's
  *floor* is the standard deviation noise alone leaves, ``sqrt(mean_i C_i,kk)``.
- **the estimate's share.** The estimate θ̂ carries the calibration data's noise: with
  the fit's weights W_i, ``A = Σ J_iᵀW_iJ_i``, the covariance of θ̂ from the noise is
  ``Cov = A⁺ (Σ J_iᵀW_iC_iW_iJ_i) A⁺``, and the expected residual covariance is
  ``E_i = C_i + J_i Cov J_iᵀ`` on held-out data and
  ``E_i = C_i − X_i A⁺ J_iᵀ − J_i A⁺ X_iᵀ + J_i Cov J_iᵀ`` on the fitted rows
  (``X_i = C_i,·f W_i J_i,f``, f the fitted constraints), so that a fitted residual is
  expected below its floor by the parameters it fitted (``Σ tr(C⁺E) = N·n_g − rank``
  with the propagated weights).
- **global test.** Per dataset, ``χ² = Σ_i r_iᵀ C_i⁺ r_i`` over the constraints against
  its expectation ``ν = Σ_i tr(C_i⁺ E_i)``: χ²/ν in its 95 % band (the central
  interval of χ²_ν / ν) is *at the floor*, above it the model misses something, below it
  the model fits noise (overfitting) or the noise is over-declared.  Each residual and
  comparison has the same test alone (``Σ r_k²/C_kk`` against ``Σ E_kk/C_kk``; the mean
  removed where a comparison's zero is arbitrary).
- **no declared noise.** A residual reading a column whose noise nobody declared has its
  floor estimated from the data where the rows are time-ordered (a ``role: time`` column
  that never decreases): half the mean square of successive differences, which removes
  what varies slowly (von Neumann; its test is the ratio of the variance to that floor,
  band from the ratio's normal approximation); elsewhere the floor is unknown.

Rows are evaluated chunk by chunk; nothing of size N × (residuals × readings) is kept.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import casadi as ca
import numpy as np

from symcal.analysis.bands import chi2_band, normal_band, ratio_band, ratio_sd, shared_ratio_band
from symcal.analysis.row_noise import (
    EXACT,
    Fit,
    RowPropagation,
    assumed_covariance,
    entries_of,
    fit_weights,
    row_grams,
    row_pinv,
    row_propagation,
)
from symcal.analysis.verdicts import (
    DIFFERENCES,
    PROPAGATED,
    UNKNOWN,
    DatasetTest,
    FloorTest,
)
from symcal.base import jit
from symcal.base.numeric import chunks, owned
from symcal.data.dataset import Dataset
from symcal.problem.symbolic import Problem
from symcal.solvers.executor import default_executor

#: Rows per block of a chunk's products in :meth:`RowsPlan.terms` (they stay in the
#: cache: 20 % faster than whole chunks on the dual problem).
BLOCK = 1024


def difference_variances(problem: Problem, ds: Dataset, theta: np.ndarray,
                         names: tuple[str, ...], exprs: list[ca.SX], declared: list[bool]
                         ) -> np.ndarray:
    """Each entry's floor squared estimated by successive differences on the rows of
    ``ds`` at ``theta`` (half the mean square of its successive differences), NaN where
    its noise is declared or the rows are not time-ordered: the variances the estimate's
    share is taken with where no noise is declared (one pass over the residuals)."""
    if all(declared) or not time_ordered(problem, ds):
        return np.full(len(names), np.nan)
    return differences_plan(problem, theta, names, exprs).reduce(ds).variances(declared)


@dataclass(frozen=True)
class Differences:
    """The successive differences of a piece of rows: its first and last residual rows,
    the sum of the squared differences within it, and its number of rows."""

    first: np.ndarray | None
    last: np.ndarray | None
    diff2: np.ndarray
    n: int

    def join(self, later: Differences) -> Differences:
        """These rows followed by ``later``'s (the difference across the boundary)."""
        diff2 = (later.diff2 if not len(self.diff2) else self.diff2 if not len(later.diff2)
                 else self.diff2 + later.diff2)
        if self.last is not None and later.first is not None:
            diff2 = diff2 + (later.first - self.last) ** 2
        return Differences(self.first if self.first is not None else later.first,
                           later.last if later.last is not None else self.last, diff2,
                           self.n + later.n)

    def variances(self, declared: list[bool]) -> np.ndarray:
        """Each undeclared entry's floor squared (half the mean square of the successive
        differences), NaN where declared."""
        out = np.full(len(declared), np.nan)
        for k, known in enumerate(declared):
            if not known and len(self.diff2) and self.diff2[k] > 0:
                out[k] = self.diff2[k] / (2.0 * (self.n - 1))
        return out


@dataclass(frozen=True)
class DifferencesPlan:
    """How a piece of rows is reduced to its :class:`Differences` (picklable: a task of a
    log kept as shards runs it on its own rows)."""

    prop: RowPropagation
    theta: np.ndarray

    def reduce(self, ds: Dataset) -> Differences:
        """The first and last residual rows of ``ds`` and the sum of its squared
        successive differences (one pass over its rows)."""
        u = ds.matrix(self.prop.columns)
        diff2: np.ndarray = np.zeros(0)
        first: np.ndarray | None = None
        last: np.ndarray | None = None
        for part in chunks(ds.n):
            r = self.prop.residuals(u, self.theta, part)
            if not len(r):
                continue
            if last is not None:
                diff2 = diff2 + (r[0] - last) ** 2
            else:
                first, diff2 = r[0], np.zeros(r.shape[1])
            diff2 = diff2 + np.sum(np.diff(r, axis=0) ** 2, axis=0)
            last = r[-1]
        return Differences(first, last, diff2, ds.n)


def differences_plan(problem: Problem, theta: np.ndarray, names: tuple[str, ...],
                     exprs: list[ca.SX]) -> DifferencesPlan:
    """The plan of the successive differences of the entries ``names`` at ``theta``."""
    return DifferencesPlan(row_propagation(problem, ("entries", *names), exprs,
                                           np.zeros(len(problem.parameters), dtype=bool)),
                           np.asarray(theta, dtype=float))


@dataclass(frozen=True)
class _Estimate:
    """The noise's share in the estimate: ``A⁺`` and ``Cov`` (free parameters)."""

    a_pinv: np.ndarray
    cov: np.ndarray


def _estimate_share(problem: Problem, fit: Fit, ds: Dataset, theta: np.ndarray,
                    assumed: Mapping[str, float] | None = None) -> _Estimate | None:
    """A⁺ and the covariance of the estimate from the calibration data's noise, or None
    where a fitted constraint reads a column of undeclared noise and ``assumed`` has no
    variance for it (its floor estimated on ``ds``: :func:`difference_variances`)."""
    plan = share_plan(problem, fit, assumed, cached=True)
    return None if plan is None else plan.finish(*kept_sums(problem, plan, ds, theta)[:2])


#: The share's sums kept per problem (the last asked): a stage whose standard errors
#: take them (:mod:`symcal.analysis.declared_errors`) and the floors of the same fit at
#: the same estimate make one pass, not two.
KEEP_SUMS = 1


def kept_sums(problem: Problem, plan: SharePlan, ds: Dataset, theta: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, float]:
    """``plan.sums(ds, theta)``, kept for the next ask of the same plan's fit, dataset
    and point (the same bits, without another pass)."""
    fit = plan.fit
    key = (fit.dataset, fit.constraints, np.asarray(fit.free, bool).tobytes(), fit.weighting,
           None if fit.whiten is None else np.asarray(fit.whiten, float).tobytes(),
           None if plan.variances is None else plan.variances.tobytes(),
           np.ascontiguousarray(theta, dtype=float).tobytes())
    kept: list[tuple[Any, Any, tuple[np.ndarray, np.ndarray, float]]] = owned(
        problem, "share sums", list)
    for ref, at, found in list(kept):
        if ref() is ds and at == key:
            return found
    found = plan.sums(ds, theta)
    kept[:] = [*kept[1 - KEEP_SUMS:], (weakref.ref(ds), key, found)]
    return found


@dataclass(frozen=True)
class _Chunk:
    """One chunk's share of a dataset's tests (:meth:`RowsPlan.terms`): what the lead
    folds in order, and what it needs to compute an entry's share again."""

    r: np.ndarray               # m × n_e residuals at the estimate
    d: np.ndarray               # m × n_e: each residual's propagated variance C_kk
    e: np.ndarray               # m × n_e: its expectation E_kk (the estimate's share in)
    vectors: dict[int, tuple[np.ndarray, np.ndarray | None, bool]]   # entry k: its
    #   Jacobian rows, its fitted rows' term X_k and whether its spread Σ w JᵀJ is needed
    r0: np.ndarray | None       # m × n_e residuals at the initial parameters
    chi2: float                 # the joint test's terms
    dof: float
    parts: tuple[_Part, ...] = ()    # each entry's share of its sums (at the estimate)
    parts0: tuple[_Part, ...] = ()   # and at the initial parameters

    def part(self, k: int, mean: float) -> _Part:
        """Entry ``k``'s share after rows of mean variance ``mean``."""
        jk, xk, spread = self.vectors.get(k, (None, None, False))
        return _part(self.r[:, k], self.d[:, k], self.e[:, k], jk, xk, mean, spread)


@dataclass
class _Sums:
    """One entry's accumulators over the rows of a dataset (see :func:`_entry_test`)."""

    n: int = 0
    w: float = 0.0
    wr2: float = 0.0
    wr: float = 0.0
    r: float = 0.0
    d: float = 0.0
    wd: float = 0.0       # Σ w E_kk (the estimate's share and the fitted rows' term in)
    wj: np.ndarray | None = None
    wjj: np.ndarray | None = None     # Σ w Jᵀ J (the share's spread)
    wxv: np.ndarray | None = None
    j: np.ndarray | None = None
    x: np.ndarray | None = None
    exact: int = 0
    # successive differences (time-ordered rows)
    diff2: float = 0.0
    last: float | None = None
    r2: float = 0.0

    def add_vectors(self, name: str, value: np.ndarray) -> None:
        old = getattr(self, name)
        setattr(self, name, value if old is None else old + value)


@dataclass(frozen=True)
class Residuals:
    """The residuals and comparisons of one dataset the floors evaluated (``names``, in
    the order of the series statistics): ``N × n_e`` at the estimate (``after``) and at
    the initial parameters (``before``, None without them)."""

    names: tuple[str, ...]
    after: np.ndarray
    before: np.ndarray | None


@dataclass(frozen=True)
class FloorOutcome:
    """What :func:`floor_outcome` gives: the tests, the datasets' global tests and the
    residuals each dataset's rows had (kept where asked)."""

    tests: dict[tuple[str, str], FloorTest]
    joint: tuple[DatasetTest, ...]
    residuals: dict[str, Residuals]


def floor_outcome(problem: Problem, datasets: Mapping[str, Dataset], theta: np.ndarray,
                  fit: Fit, theta0: np.ndarray | None = None, keep: bool = True
                  ) -> FloorOutcome:
    """The floor and test of every residual and comparison on every dataset, and the
    global test of each dataset (the module's theory).

    Parameters
    ----------
    problem
        The problem solved (its :attr:`~symcal.problem.symbolic.Problem.noisy` view
        carries the declared noise).
    datasets
        The datasets by name.
    theta
        The estimate.
    fit
        How the estimate was fitted (:class:`Fit`).
    theta0
        The initial parameters: each test then also has ``chi2_before`` (same weights).

    keep
        Keep the residuals the rows had (``N × n_e`` at the estimate and at the start,
        per dataset: what :func:`symcal.analysis.fit.series_statistics` reads).

    Returns
    -------
    FloorOutcome
        ``(dataset, name) → FloorTest``, one :class:`DatasetTest` per dataset, and the
        residuals where kept.
    """
    assumed = {}
    for ds in datasets.values():
        entries = entries_of(problem, ds)
        assumed[ds.name] = difference_variances(problem, ds, theta, tuple(entries.names),
                                                entries.exprs, entries.declared)
    share = None
    if fit.dataset in datasets and np.any(fit.free):
        names = entries_of(problem, datasets[fit.dataset]).names
        share = _estimate_share(
            problem, fit, datasets[fit.dataset], theta,
            {n: float(v) for n, v in zip(names, assumed[fit.dataset], strict=True)
             if not np.isnan(v)})
    out: dict[tuple[str, str], FloorTest] = {}
    tests = []
    residuals: dict[str, Residuals] = {}
    for ds in datasets.values():
        found, joint, kept = _dataset_outcome(problem, ds, theta, fit, share, theta0,
                                              assumed[ds.name], keep)
        out.update({(ds.name, k): v for k, v in found.items()})
        tests.append(joint)
        if kept is not None:
            residuals[ds.name] = kept
    return FloorOutcome(out, tuple(tests), residuals)


def fit_chi2(problem: Problem, ds: Dataset, theta: np.ndarray, fit: Fit
             ) -> DatasetTest | None:
    """The fitted dataset ``ds``'s global test as far as one pass tells it: its χ² at the
    estimate, the same bits as :func:`floor_outcome`'s joint test, without its degrees
    of freedom and band (those need the estimate's share: the test says nothing of the
    floor).  What a loop that compares many candidate models reads of the floors (the
    fit's χ², :attr:`~symcal.calibrate.result.Result.rss`), at the cost of one pass.
    None where the tests may not give that χ²: an entry of undeclared noise (the test is
    then combined from the entries'), or rows whose ranks ν do not exceed the free
    parameters p (the test needs positive degrees of freedom, which are at least ν − p
    whatever the fit's weights: ``tr(C⁺ Cov r)`` with ``r`` the noise left by a
    projection of rank at most p)."""
    # without the parameters' Jacobian, which χ² does not read: the same operations
    # give r and L (their expressions are the same), in a function half the size
    plan = rows_plan(problem, ds, theta, replace(fit, free=np.zeros_like(fit.free)), None,
                     cached=True)
    if not plan.joint_ok:
        return None
    chi2, nu = plan.joint_chi2(ds)
    if not nu > np.count_nonzero(fit.free) + 0.5:
        return None
    return DatasetTest(ds.name, tuple(plan.names[k] for k in plan.cons), PROPAGATED, chi2)


def held_out_test(problem: Problem, ds: Dataset, theta: np.ndarray, fit: Fit,
                  share: _Estimate, joint: DatasetTest) -> DatasetTest:
    """A held-out dataset's global test with the band its statistic has.

    On data the estimate was not fitted to, the residual carries the estimate's error,
    ``r_i = e_i + J_i δθ``: one random vector shared by every row, so that χ² is not
    χ²_ν.  Its expectation (``dof``) already counts it, ``ν₀ + tr(G Cov)``, ν₀ the rows'
    ranks and ``G = Σ_i J_iᵀ C_i⁺ J_i``; its variance is
    ``2 (ν₀ + 2 tr(G Cov) + tr((G Cov)²))`` (a quadratic form in normal noise), larger
    than ``2ν`` where the share is concentrated in a few directions.  The band is that of
    χ² with Satterthwaite's degrees of freedom ``2 E²/Var`` (measured on the planar arm's
    held-out swing, 100 seeds: the χ²/dof spread 0.083 against √(2/ν) = 0.069; 9 of 100
    below the χ²_ν band).  The fitted dataset's own test needs none of this: with the
    propagated weights its χ² is χ²_{ν-p} exactly."""
    if joint.method != PROPAGATED or not joint.dof or not joint.constraints:
        return joint
    names = joint.constraints
    prop = row_propagation(problem, ("information", *names),
                           [problem.noisy.constraint(n).sx for n in names], fit.free)
    n_p = prop.n_p
    if n_p == 0 or share.cov.shape != (n_p, n_p):
        return joint
    info = np.zeros((n_p, n_p))
    for _, _, lmat, jac in prop.rows(ds, theta):
        pinv, _ = row_pinv(lmat @ np.swapaxes(lmat, 1, 2))
        info += jac.reshape(-1, n_p).T @ (pinv @ jac).reshape(-1, n_p)
    gc = info @ share.cov
    first, second = float(np.trace(gc)), float(np.trace(gc @ gc))
    base = joint.dof - first
    variance = 2.0 * (base + 2.0 * first + second)
    if not (base > 0 and variance > 0):
        return joint
    nu = 2.0 * joint.dof**2 / variance
    return replace(joint, band=chi2_band(nu), sd=math.sqrt(2.0 / nu))


def time_ordered(problem: Problem, ds: Dataset) -> bool:
    """Whether the rows of ``ds`` are in time order (a time column that never decreases)."""
    time = next((c for c, spec in problem.column_specs.items()
                 if spec.role == "time" and c in ds.columns), None)
    if time is None or ds.n < 3:
        return False
    t = np.asarray(ds.columns[time], dtype=float)
    return bool(np.all(np.diff(t) >= 0) and t[-1] > t[0])


# ------------------------------------------------------------ a log kept as shards
# The sums behind the estimate's share, the floors and the tests, as plans that a task of
# a log kept as shards runs on its own rows (picklable: no Problem), and sums that join in
# row order.  The arithmetic is that of _estimate_share and _dataset_tests, a piece of
# rows at a time; tests/test_hugelog.py holds the two equal (whole result documents, to
# 1e-9).


@dataclass(frozen=True)
class SharePlan:
    """What the estimate's share is summed with over the fitted rows (a task of a log
    kept as shards sums its own rows, :func:`share_finish` ends it)."""

    prop: RowPropagation
    fit: Fit
    sigma: np.ndarray
    scales: np.ndarray                    # the free parameters' scales
    variances: np.ndarray | None = None   # see _estimate_share's assumed

    def finish(self, a: np.ndarray, b: np.ndarray) -> _Estimate:
        """The share from the sums of all rows (:func:`share_finish`)."""
        return share_finish(a, b, self.scales)

    def sums(self, ds: Dataset, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """``(A, B, t)``: ``Σ J_iᵀW_iJ_i``, ``Σ J_iᵀW_iC_iW_iJ_i`` and ``Σ tr(W_iC_i)`` over
        the rows of ``ds``."""
        prop = self.prop
        u = ds.columns_view(prop.columns)
        fn = jit.select(prop.fn, ds.n)

        def piece(part: slice) -> tuple[np.ndarray, np.ndarray, float]:
            _, lmat, jac = prop.at(fn, u, theta, part)
            return self.terms(lmat, jac)

        a, b, t = np.zeros((prop.n_p, prop.n_p)), np.zeros((prop.n_p, prop.n_p)), 0.0
        for da, db, dt in default_executor(ds.n).map(piece, chunks(ds.n)):   # in order
            a += da
            b += db
            t += dt
        return a, b, t

    def terms(self, lmat: np.ndarray, jac: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """``(A, B, t)`` of one chunk of rows from their ``L`` and ``J``
        (:meth:`RowPropagation.at`): products, not einsum loops."""
        n_p = self.prop.n_p
        c = assumed_covariance(row_grams(lmat), self.variances)
        w = fit_weights(self.fit, c, self.sigma)
        wj = w @ jac
        flat = wj.reshape(-1, n_p)
        return (jac.reshape(-1, n_p).T @ flat, flat.T @ (c @ wj).reshape(-1, n_p),
                float(np.einsum("mab,mba->", w, c)))


def share_plan(problem: Problem, fit: Fit, assumed: Mapping[str, float] | None = None,
               cached: bool = False) -> SharePlan | None:
    """The plan of the estimate's share (None where a fitted constraint reads a column of
    undeclared noise and ``assumed`` has no variance for it); ``cached``: the evaluation
    built once per problem (in memory) rather than for this plan alone (a task of a log
    kept as shards carries its own)."""
    quantities = [problem.constraint(n) for n in fit.constraints]
    known, variances = _assumed_variances(problem, fit, assumed)
    if not known:
        return None
    exprs = [problem.noisy.constraint(n).sx for n in fit.constraints]
    prop = row_propagation(problem, ("share", *fit.constraints), exprs, fit.free) if cached \
        else RowPropagation(problem, exprs, fit.free)
    scales = np.array([p.scale for p in problem.parameters])[np.asarray(fit.free, bool)]
    return SharePlan(prop, fit, np.array([q.sigma for q in quantities]), scales, variances)


def _assumed_variances(problem: Problem, fit: Fit, assumed: Mapping[str, float] | None
                       ) -> tuple[bool, np.ndarray | None]:
    """Whether every fitted constraint has a variance (declared, or in ``assumed``: its
    floor estimated on the fitted rows), and those of the undeclared ones (NaN for the
    others; None where every one is declared)."""
    assumed = assumed or {}
    undeclared = [k for k, n in enumerate(fit.constraints)
                  if problem.undeclared(problem.constraint(n).sx)]
    if not undeclared:
        return True, None
    if any(fit.constraints[k] not in assumed for k in undeclared):
        return False, None
    variances = np.full(len(fit.constraints), np.nan)
    for k in undeclared:
        variances[k] = assumed[fit.constraints[k]]
    return True, variances


def share_finish(a: np.ndarray, b: np.ndarray, scales: np.ndarray | None = None
                 ) -> _Estimate:
    """A⁺ and the estimate's covariance ``A⁺ B A⁺`` from the sums of all rows.

    The pseudo-inverse is taken in the parameters' own scales (``D A D``, ``D`` their
    ``scales``): a direction is dropped where the data do not determine it, not where a
    parameter's unit makes its entries small (a cubic coefficient's directions were cut
    from the unscaled ``A``, one degree of freedom too many in the tests)."""
    if a.shape[0] == 0:
        return _Estimate(a, b)
    d = np.ones(a.shape[0]) if scales is None else np.asarray(scales, dtype=float)
    vals, vecs = np.linalg.eigh(a * d[:, None] * d[None, :])
    keep = vals > 1e-10 * max(float(vals.max(initial=0.0)), 1e-300)
    a_pinv = d[:, None] * ((vecs[:, keep] / vals[keep]) @ vecs[:, keep].T) * d[None, :]
    return _Estimate(a_pinv, a_pinv @ b @ a_pinv)


@dataclass
class RowSums:
    """What a piece of a dataset's rows reduces to: each entry's accumulators at the
    estimate and at the start, each entry's first residual there (to join the successive
    differences across a boundary), and the joint χ² and its expectation."""

    sums: list[_Sums]
    before: list[_Sums]
    first: list[float | None]
    first_before: list[float | None]
    chi2: float = 0.0
    dof: float = 0.0

    def join(self, later: RowSums) -> RowSums:
        """The sums of this piece followed by ``later``."""
        return RowSums(
            [_joined(a, b, f) for a, b, f in zip(self.sums, later.sums, later.first,
                                                 strict=True)],
            [_joined(a, b, f) for a, b, f in zip(self.before, later.before,
                                                 later.first_before, strict=True)],
            [a if a is not None else b for a, b in zip(self.first, later.first,
                                                       strict=True)],
            [a if a is not None else b for a, b in zip(self.first_before, later.first_before,
                                                       strict=True)],
            self.chi2 + later.chi2, self.dof + later.dof)


def _joined(a: _Sums, b: _Sums, b_first: float | None) -> _Sums:
    """An entry's accumulators over a piece of rows followed by another, whose first
    residual is ``b_first``."""
    def add(x: np.ndarray | None, y: np.ndarray | None) -> np.ndarray | None:
        return y if x is None else x if y is None else x + y

    diff2 = a.diff2 + b.diff2
    if a.last is not None and b_first is not None:
        diff2 += (b_first - a.last) ** 2
    return _Sums(n=a.n + b.n, w=a.w + b.w, wr2=a.wr2 + b.wr2, wr=a.wr + b.wr, r=a.r + b.r,
                 d=a.d + b.d, wd=a.wd + b.wd, wj=add(a.wj, b.wj), wjj=add(a.wjj, b.wjj),
                 wxv=add(a.wxv, b.wxv),
                 j=add(a.j, b.j), x=add(a.x, b.x), exact=a.exact + b.exact, diff2=diff2,
                 last=b.last if b.last is not None else a.last, r2=a.r2 + b.r2)


@dataclass(frozen=True)
class RowsPlan:
    """How the rows of one dataset are reduced for its floors and tests, in memory and on
    a log kept as shards alike: :meth:`reduce` on each piece, the pieces' sums joined in
    order (:meth:`RowSums.join`), then :meth:`finish`."""

    dataset: str
    names: tuple[str, ...]
    declared: tuple[bool, ...]
    centred: tuple[bool, ...]
    prop: RowPropagation
    fitted: tuple[int, ...]
    cons: tuple[int, ...]
    joint_ok: bool
    sigma_f: np.ndarray
    fit: Fit
    share: _Estimate | None
    theta: np.ndarray
    theta0: np.ndarray | None
    assumed: np.ndarray | None = None    # each entry's floor squared where estimated

    def estimated(self, k: int) -> bool:
        """Whether entry ``k``'s floor was estimated from the data (and is its variance)."""
        return self.assumed is not None and not np.isnan(self.assumed[k])

    def reduce(self, ds: Dataset) -> RowSums:
        """The sums of the rows of ``ds``: each chunk's terms on the in-memory passes'
        executor (threads for a large dataset), folded here in order."""
        return self.reduce_with(ds, False)[0]

    def reduce_with(self, ds: Dataset, keep: bool) -> tuple[RowSums, Residuals | None]:
        """:meth:`reduce`, and where ``keep`` asks, the residuals it evaluated (at the
        estimate and at the start, ``N × n_e`` each: the series statistics read them
        rather than evaluating the same expressions again, the same bits)."""
        n = len(self.names)
        out = RowSums([_Sums() for _ in range(n)], [_Sums() for _ in range(n)], [None] * n,
                      [None] * n)
        prop, theta0 = self.prop, self.theta0
        u = ds.columns_view(prop.columns)
        fn = jit.select(prop.fn if theta0 is None else prop.with_start, ds.n)

        def piece(part: slice) -> _Chunk:
            if theta0 is None:
                return self.terms(*prop.at(fn, u, self.theta, part), None)
            r, lmat, jac, r0 = prop.at_and_start(fn, u, self.theta, theta0, part)
            return self.terms(r, lmat, jac, r0)

        parts = list(chunks(ds.n))
        kept = None
        if keep:
            kept = Residuals(self.names, np.empty((ds.n, n)),
                             None if theta0 is None else np.empty((ds.n, n)))
        for part, chunk in zip(parts, default_executor(ds.n).map(piece, parts), strict=True):
            if part.start == 0 and len(chunk.r):     # the piece's first row is here
                out.first = [float(v) for v in chunk.r[0]]
                if chunk.r0 is not None:
                    out.first_before = [float(v) for v in chunk.r0[0]]
            if kept is not None:
                kept.after[part] = chunk.r
                if kept.before is not None and chunk.r0 is not None:
                    kept.before[part] = chunk.r0
            _fold_chunk(out, chunk)
        return out, kept

    def terms(self, r: np.ndarray, lmat: np.ndarray, jac: np.ndarray,
              r0: np.ndarray | None) -> _Chunk:
        """One chunk's terms from its residuals, ``L`` and ``J`` (:meth:`RowPropagation.at`)
        and its residuals at the start: independent of every other chunk.

        ``E_kk`` and the joint test's expectation need only the products of the rows' own
        Jacobians with ``Z = J Cov − 2 X A⁺`` (the fitted rows' two cross terms are equal
        under the trace with a symmetric ``C⁺``), and ``X A⁺ Jᵀ = α (J_f A⁺) Jᵀ`` with
        ``α = C_·f W``: ``X`` itself is formed only for an entry whose mean is removed."""
        c = assumed_covariance(row_grams(lmat), self.assumed)
        d = np.diagonal(c, axis1=1, axis2=2).copy()             # C_kk
        m, n_e = r.shape
        e = d.copy()                                            # E_kk
        chi2 = dof = 0.0
        xs: dict[int, np.ndarray] = {}
        for start in range(0, m, BLOCK):     # blocks whose products stay in the cache
            rows = slice(start, start + BLOCK)
            share_kk, chi2_b, dof_b, x_b = self._block(r[rows], c[rows], jac[rows])
            if share_kk is not None:
                e[rows] += share_kk
            chi2 += chi2_b
            dof += dof_b
            for k, xk in x_b.items():
                if k not in xs:
                    xs[k] = np.empty((m, xk.shape[1]))
                xs[k][rows] = xk
        vectors: dict[int, tuple[np.ndarray, np.ndarray | None, bool]] = {
            k: (jac[:, k, :].copy(), xs.get(k), self.estimated(k))   # not all of J
            for k in range(n_e) if self.share is not None
            and (self.centred[k] or self.estimated(k))}   # the others' sums need no J
        chunk = _Chunk(r, d, e, vectors, r0, chi2, dof)
        parts = tuple(chunk.part(k, 0.0) for k in range(n_e))
        parts0 = () if r0 is None else tuple(
            _part(r0[:, k], d[:, k], d[:, k], None, None, 0.0) for k in range(n_e))
        return replace(chunk, parts=parts, parts0=parts0)

    def _block(self, r: np.ndarray, c: np.ndarray, jac: np.ndarray
               ) -> tuple[np.ndarray | None, float, float, dict[int, np.ndarray]]:
        """A block of a chunk's rows (:meth:`terms`): ``(Z Jᵀ)_kk`` (None without the
        estimate's share), the joint test's χ² and expectation, and ``X_k`` of every
        mean-removed entry."""
        m, n_e = r.shape
        q = None                                                 # m × n_e × n_e: Z Jᵀ
        alpha = None
        share, fitted = self.share, list(self.fitted)
        if share is not None:
            n_p = jac.shape[2]
            jac_t = np.swapaxes(jac, 1, 2)
            q = (jac.reshape(-1, n_p) @ share.cov).reshape(m, n_e, n_p) @ jac_t
            if fitted:
                w = fit_weights(self.fit, c[:, fitted][:, :, fitted], self.sigma_f)
                alpha = c[:, :, fitted] @ w                       # m × n_e × n_f
                # np.take, not jac[:, fitted, :]: that gather is laid out entry-major
                # and its reshape to rows a strided copy 30 times slower than the gather
                ja = (np.take(jac, fitted, axis=1).reshape(-1, n_p) @ share.a_pinv
                      ).reshape(m, len(fitted), n_p)
                q -= 2.0 * (alpha @ (ja @ jac_t))
        chi2 = dof = 0.0
        if self.joint_ok:
            chi2, dof = self._joint(r, c, q)
        xs = {}
        if alpha is not None:
            for k in range(n_e):
                if self.centred[k]:
                    xk = alpha[:, k, 0, None] * jac[:, fitted[0], :]
                    for i in range(1, len(fitted)):
                        xk += alpha[:, k, i, None] * jac[:, fitted[i], :]
                    xs[k] = xk
        return (None if q is None else np.diagonal(q, axis1=1, axis2=2)), chi2, dof, xs

    def _joint(self, r: np.ndarray, c: np.ndarray, q: np.ndarray | None
               ) -> tuple[float, float]:
        """A block's terms of the joint test: χ² and its expectation (without the
        estimate's share ``q``: the rows' ranks ν)."""
        cons = _span(self.cons)
        c_cons = np.ascontiguousarray(_block_of(c, cons))
        pinv, _ = row_pinv(c_cons)
        # column-major, the layout a gather of columns (r[:, list]) gives: einsum sums in
        # the order of its operands' layout, so χ² has the same bits however cons is taken
        rc = np.asfortranarray(r[:, cons])
        chi2 = float(np.einsum("ma,mab,mb->", rc, pinv, rc))
        expect = c_cons if q is None else c_cons + _block_of(q, cons)
        return chi2, float(np.einsum("mab,mab->", pinv, expect))

    def joint_chi2(self, ds: Dataset) -> tuple[float, float]:
        """The joint test's χ² over the rows of ``ds`` (the same bits as :meth:`reduce`
        sums) and the rows' ranks ν (its degrees of freedom before the estimate's
        share): one pass, nothing else of the tests."""
        chi2 = nu = 0.0
        for _, r, lmat, _ in self.prop.rows(ds, self.theta):
            c = assumed_covariance(row_grams(lmat), self.assumed)
            chi2_c = nu_c = 0.0
            for start in range(0, r.shape[0], BLOCK):      # as terms() blocks them
                rows = slice(start, start + BLOCK)
                chi2_b, nu_b = self._joint(r[rows], c[rows], None)
                chi2_c += chi2_b
                nu_c += nu_b
            chi2 += chi2_c
            nu += nu_c
        return chi2, nu

    def finish(self, sums: RowSums, ordered: bool) -> tuple[dict[str, FloorTest], DatasetTest]:
        """Each entry's floor and test and the dataset's global test from the sums of all
        its rows (``ordered``: whether the rows are in time order)."""
        names, cons = self.names, self.cons
        found = {}
        for k, name in enumerate(names):
            found[name] = _entry_test(sums.sums[k], self.declared[k], self.centred[k],
                                      ordered, self.share, self.estimated(k),
                                      self.dataset == self.fit.dataset and k in self.fitted)
            if self.theta0 is not None and found[name].method == PROPAGATED and \
                    found[name].chi2 is not None:
                found[name] = replace(found[name],
                                      chi2_before=_chi2(sums.before[k], self.centred[k]))
        if self.joint_ok and sums.dof > 0:
            joint = DatasetTest(self.dataset, tuple(names[k] for k in cons), PROPAGATED,
                                sums.chi2, sums.dof, chi2_band(sums.dof))
        else:
            joint = _combined(self.dataset, [names[k] for k in cons],
                              [found[names[k]] for k in cons])
        return found, joint


def _span(index: tuple[int, ...]) -> slice | list[int]:
    """``index`` as a slice where it is a run of consecutive entries (a view, not a
    gather: the same values), else as a list."""
    if index and list(index) == list(range(index[0], index[-1] + 1)):
        return slice(index[0], index[-1] + 1)
    return list(index)


def _block_of(a: np.ndarray, index: slice | list[int]) -> np.ndarray:
    """Per row, the block ``a[:, index, index]`` of ``m × n × n`` matrices."""
    if isinstance(index, slice):
        return a[:, index, index]
    return a[:, index][:, :, index]


def rows_plan(problem: Problem, ds: Dataset, theta: np.ndarray, fit: Fit,
              share: _Estimate | None, theta0: np.ndarray | None = None,
              assumed: np.ndarray | None = None, cached: bool = False) -> RowsPlan:
    """The plan of the floors and tests of the dataset ``ds`` (its name and columns: a
    sample of a log kept as shards will do), at the estimate ``theta`` (``theta0``: the
    start too), with the estimate's share ``share`` from the fitted rows; ``assumed``:
    each entry's floor squared where estimated from the data on a held-out dataset (NaN
    elsewhere; :func:`difference_variances`), its variance in the tests.  ``cached``:
    the evaluation built once per problem (in memory) rather than for this plan alone
    (a task of a log kept as shards carries its own)."""
    entries = entries_of(problem, ds)
    if ds.name == fit.dataset:
        # the fitted rows keep the ratio's test: what the fit takes from their spread
        # depends on how their constraints' noise correlates, which nobody declared (on
        # the courier with several fitted constraints, taking them independent put 13 of
        # 100 clean calibration runs above their floor)
        assumed = None
    prop = row_propagation(problem, ("entries", *entries.names), entries.exprs, fit.free) \
        if cached else RowPropagation(problem, entries.exprs, fit.free)
    fitted = [entries.names.index(n) for n in fit.constraints] \
        if ds.name == fit.dataset else []
    cons = [k for k, kind in enumerate(entries.kinds) if kind == "constraint"]
    joint_ok = all(entries.declared[k] for k in cons) and bool(cons)
    sigma_f = np.array([problem.constraint(entries.names[k]).sigma for k in fitted])
    use_share = share is not None and prop.n_p > 0
    return RowsPlan(ds.name, tuple(entries.names), tuple(entries.declared),
                    tuple(entries.centred), prop, tuple(fitted), tuple(cons), joint_ok,
                    sigma_f, fit, share if use_share else None,
                    np.array(theta, dtype=float),
                    None if theta0 is None else np.array(theta0, dtype=float),
                    None if assumed is None else np.array(assumed, dtype=float))


def _dataset_tests(problem: Problem, ds: Dataset, theta: np.ndarray, fit: Fit,
                   share: _Estimate | None, theta0: np.ndarray | None = None,
                   assumed: np.ndarray | None = None
                   ) -> tuple[dict[str, FloorTest], DatasetTest]:
    found, joint, _ = _dataset_outcome(problem, ds, theta, fit, share, theta0, assumed,
                                       False)
    return found, joint


def _dataset_outcome(problem: Problem, ds: Dataset, theta: np.ndarray, fit: Fit,
                     share: _Estimate | None, theta0: np.ndarray | None,
                     assumed: np.ndarray | None, keep: bool
                     ) -> tuple[dict[str, FloorTest], DatasetTest, Residuals | None]:
    plan = rows_plan(problem, ds, theta, fit, share, theta0, assumed, cached=True)
    sums, kept = plan.reduce_with(ds, keep)
    found, joint = plan.finish(sums, time_ordered(problem, ds))
    if plan.share is not None and ds.name != fit.dataset and plan.joint_ok and sums.dof > 0:
        joint = held_out_test(problem, ds, theta, fit, plan.share, joint)
    return found, joint, kept


def _fold_chunk(out: RowSums, chunk: _Chunk) -> None:
    """Add one chunk's shares to a piece's sums, in the chunks' order.  Each entry's share
    was computed on the pass's threads without the rows before it; where those rows change
    which of its rows count as exact (rare), it is computed again here as the rows before
    it say: the sums are the same either way."""
    if chunk.r0 is not None:
        for k, s in enumerate(out.before):
            if _fits(chunk.parts0[k], s, chunk.d[:, k]):
                _fold(s, chunk.parts0[k])
            else:
                dk = chunk.d[:, k]
                _accumulate(s, chunk.r0[:, k], dk, dk, None, None)
    out.chi2 += chunk.chi2
    out.dof += chunk.dof
    for k, s in enumerate(out.sums):
        if _fits(chunk.parts[k], s, chunk.d[:, k]):
            _fold(s, chunk.parts[k])
        else:
            _fold(s, chunk.part(k, s.d / max(s.n, 1)))


def _accumulate(s: _Sums, rk: np.ndarray, d: np.ndarray, e: np.ndarray,
                jk: np.ndarray | None, xk: np.ndarray | None, spread: bool = False) -> None:
    """Add one chunk of one entry: its residuals ``rk``, variances ``d`` (C_kk),
    expectations ``e`` (E_kk), Jacobian rows ``jk`` and fitted-rows term ``xk`` (with the
    estimate's share only; ``spread``: :func:`_part`)."""
    _fold(s, _part(rk, d, e, jk, xk, s.d / max(s.n, 1), spread))


@dataclass
class _Part:
    """One chunk's share of one entry's sums (:func:`_part`), to be added in order
    (:func:`_fold`); ``bound`` is the variance at or below which a row counted as exact."""

    bound: float
    exact: int
    n: int
    w: float
    wr2: float
    wr: float
    r: float
    r2: float
    d: float
    wd: float
    vectors: tuple[tuple[str, np.ndarray], ...]
    first: float | None
    last: float | None
    diff2: float


def _bound(d: np.ndarray, mean: float) -> float:
    """The variance at or below which a row is exact: :data:`EXACT` of the chunk's
    largest, of the mean of the rows before it, or of the smallest positive number."""
    return EXACT * max(float(d.max(initial=0.0)), mean, 1e-300)


def _part(rk: np.ndarray, d: np.ndarray, e: np.ndarray, jk: np.ndarray | None,
          xk: np.ndarray | None, mean: float, spread: bool = False) -> _Part:
    """One chunk's share of an entry's sums (as :func:`_accumulate` describes), the rows
    before it having a mean variance ``mean``: heavy work that needs nothing of the other
    chunks, so a pass's threads do it.  ``Σ w JᵀJ`` only where ``spread`` asks for it
    (an estimated floor's band, :func:`_estimated_test`)."""
    bound = _bound(d, mean)
    live = d > bound
    w = np.where(live, 1.0 / np.where(live, d, 1.0), 0.0)
    vectors: list[tuple[str, np.ndarray]] = []
    if jk is not None:     # sums over the rows as products (a strided sum is slow)
        both = np.vstack([w, np.ones(len(rk))])
        wj, j = both @ jk
        vectors += [("wj", wj), ("j", j)]
        if spread:
            vectors.append(("wjj", (jk * w[:, None]).T @ jk))
        if xk is not None:
            wxv, x = both @ xk
            vectors += [("wxv", wxv), ("x", x)]
    return _Part(bound, int(np.sum(~live)), len(rk), float(w.sum()),
                 float(np.sum(w * rk * rk)), float(np.sum(w * rk)), float(rk.sum()),
                 float(np.sum(rk * rk)), float(d.sum()), float(np.sum(w * e)),
                 tuple(vectors), float(rk[0]) if len(rk) else None,
                 float(rk[-1]) if len(rk) else None,
                 float(np.sum(np.diff(rk) ** 2)) if len(rk) else 0.0)


def _fits(part: _Part, s: _Sums, d: np.ndarray) -> bool:
    """Whether ``part`` (computed without the rows before it) is what :func:`_accumulate`
    adds after ``s``: every row is exact or not alike under both bounds."""
    bound = _bound(d, s.d / max(s.n, 1))
    return bound == part.bound or bool(np.array_equal(d > bound, d > part.bound))


def _fold(s: _Sums, part: _Part) -> None:
    """Add one chunk's share to an entry's sums (in the chunks' order)."""
    s.exact += part.exact
    s.n += part.n
    s.w += part.w
    s.wr2 += part.wr2
    s.wr += part.wr
    s.r += part.r
    s.r2 += part.r2
    s.d += part.d
    s.wd += part.wd
    for name, value in part.vectors:
        s.add_vectors(name, value)
    if part.first is not None:
        if s.last is not None:
            s.diff2 += (part.first - s.last) ** 2
        s.diff2 += part.diff2
        s.last = part.last


def _expected(s: _Sums, centred: bool, share: _Estimate | None) -> float:
    """``Σ w E_kk`` of an entry (C, the estimate's share and the fitted rows' term), about
    its mean when ``centred``: the expectation of its ``χ²``."""
    n = s.n
    expected = s.wd
    if centred and n > 1:
        expected -= (2.0 / n) * _wd_plain(s) - s.w * s.d / n**2
        if share is not None and s.wj is not None and s.j is not None:
            jbar = s.j / n
            expected -= 2.0 * float(jbar @ share.cov @ s.wj) - s.w * float(
                jbar @ share.cov @ jbar)
            if s.wxv is not None and s.x is not None:
                xbar = s.x / n
                expected += 2.0 * (float(xbar @ share.a_pinv @ s.wj)
                                   + float(s.wxv @ share.a_pinv @ jbar)
                                   - s.w * float(xbar @ share.a_pinv @ jbar))
    return expected


def _estimated_test(s: _Sums, centred: bool, share: _Estimate, fitted: bool, floor: float,
                    chi2: float) -> FloorTest:
    """The test of an entry whose floor was estimated by successive differences and
    taken as its variance in the estimate's share (:func:`assumed_covariance`), so that the share is
    counted: the estimate's error ``J_i δθ`` moves with the design, often in steps (one
    per orientation, pose or run) that successive differences cannot see, and adds
    ``Σ w J_i Cov J_iᵀ`` to the spread on held-out rows; on the fitted rows the fit takes
    about one variance per parameter away.  Its spread: ``2 tr((G Cov)²) + 4 tr(G Cov)``
    held out (the share's quadratic form and its cross term with the rows' own noise,
    ``G = Σ w J_iᵀJ_i`` about the mean when ``centred``), ``2 tr((G Cov)²)`` on the
    fitted rows (the fit's projection of their noise); the band
    :func:`shared_ratio_band`."""
    n = s.n
    k = float(n - 1 if centred else n)
    expected = max(_expected(s, centred, share), 1.0)
    var_y = 0.0
    if s.wjj is not None and s.wj is not None and share.cov.size:
        g = s.wjj - (np.outer(s.wj, s.wj) / s.w if centred else 0.0)
        gc = g @ share.cov
        first, second = float(np.trace(gc)), float(np.trace(gc @ gc))
        var_y = 2.0 * second + (0.0 if fitted else 4.0 * first)
    sd = math.sqrt((k * ratio_sd(n, centred)) ** 2 + var_y) / expected
    return FloorTest(floor, DIFFERENCES, chi2, expected,
                     shared_ratio_band(n, centred, expected, sd), sd, rows=n)


def _entry_test(s: _Sums, declared: bool, centred: bool, time_ordered: bool,
                share: _Estimate | None, estimated: bool = False, fitted: bool = False
                ) -> FloorTest:
    """One entry's floor and test from its accumulators (``estimated``: its floor,
    estimated from the data, was its variance in the estimate's share and its
    accumulators' weights; ``fitted``: it is a fitted constraint on the fitted rows)."""
    n = s.n
    if declared and n and s.d > 0 and s.w > 0:
        floor = math.sqrt(s.d / n)
        chi2 = s.wr2
        if centred and n > 1:
            mean = s.r / n
            chi2 = s.wr2 - 2.0 * mean * s.wr + mean * mean * s.w
        expected = max(_expected(s, centred, share), 1.0)
        return FloorTest(floor, PROPAGATED, chi2, expected, chi2_band(expected),
                         math.sqrt(2.0 / expected))
    if declared and n and s.d == 0:
        return FloorTest(0.0, PROPAGATED)      # every reading it uses is declared exact
    if time_ordered and n > 2 and s.diff2 > 0:
        floor = math.sqrt(s.diff2 / (2.0 * (n - 1)))
        mean = s.r / n if centred else 0.0
        spread = (s.r2 - 2.0 * mean * s.r + n * mean * mean)
        expected = float(n - 1 if centred else n)
        chi2 = spread / floor**2
        if estimated and share is not None and s.w > 0:
            return _estimated_test(s, centred, share, fitted, floor, chi2)
        return FloorTest(floor, DIFFERENCES, chi2, expected, ratio_band(n, centred),
                         ratio_sd(n, centred))
    return FloorTest(None, UNKNOWN)


def _chi2(s: _Sums, centred: bool) -> float:
    """Σ w r² of an entry's accumulators, about its mean when ``centred``."""
    if not centred or not s.n:
        return s.wr2
    mean = s.r / s.n
    return s.wr2 - 2.0 * mean * s.wr + mean * mean * s.w


def _wd_plain(s: _Sums) -> float:
    """Σ w_i d_i: the number of rows whose variance is not exact."""
    return float(s.n - s.exact)


def _combined(dataset: str, names: list[str], found: list[FloorTest]) -> DatasetTest:
    """The dataset's test from its constraints' own tests (some floors estimated)."""
    parts = [(f.chi2, f.dof, f.sd) for f in found]
    known = [(c, d, s) for c, d, s in parts if c is not None and d and s is not None]
    if not found or len(known) < len(parts):
        return DatasetTest(dataset, tuple(names), UNKNOWN)
    chi2 = sum(c for c, _, _ in known)
    dof = sum(d for _, d, _ in known)
    sd = math.sqrt(sum((d * s) ** 2 for _, d, s in known)) / dof
    if all(f.method == PROPAGATED for f in found):
        return DatasetTest(dataset, tuple(names), "combined", chi2, dof, chi2_band(dof),
                           "chi2", sd)
    if len(found) == 1:         # one constraint, its floor estimated: its own band
        return DatasetTest(dataset, tuple(names), "combined", chi2, dof, found[0].band,
                           "ratio", sd, found[0].rows)
    return DatasetTest(dataset, tuple(names), "combined", chi2, dof, normal_band(sd),
                       "normal", sd)
