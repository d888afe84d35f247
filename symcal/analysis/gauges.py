"""Gauges: the symmetries that make a calibration ill-posed, found before the solve.

A *gauge* is a curve in parameter space along which the constraints either stay the same
or change only by a fixed linear map of themselves, on every observation and whatever the
data:

- **offset**: a constant direction leaves every constraint unchanged (parameters that
  enter only through a difference, e.g. two encoders' zeros);
- **scale**: the constraints are homogeneous in a set of parameters,
  ``g(λ^w·θ_S) = λ^k·g(θ_S)``, the powers ``w`` of either sign: whatever fits, a scaled
  copy fits too, and for ``k > 0`` a least-squares solve slides down to the trivial point
  where those with a positive power are zero (and those with a negative one grow without
  bound); ``k = 0`` is an invariance (``(r, b) → (λ r, λ b)`` in ``r/b``).  The powers
  are found jointly at the random points, as the constant ``w`` with
  ``J·(w∘θ) = k·g`` at every one of them;
- **rotation**: the constraints turn together (``g → R(α)·g``), so the cost
  ``Σ‖g‖²`` is unchanged although no single constraint is, e.g. a base frame's angle
  turned together with a point expressed in it;
- **symmetry**: any other such curve (the constraints unchanged along a direction that
  depends on where one is, or changed by another fixed map).

All of them share one infinitesimal test, checked at the start and at a few random
points of the parameter space (within the bounds): a tangent ``t(θ)`` and a constant
matrix ``K`` (``n_g × n_g``, one observation's constraints) with

    ``J(θ, u_i)·t(θ) = K·g(θ, u_i)``   for every observation i,

``K = 0`` for offsets and invariances, ``K = I`` for a homogeneity (then ``t = w∘θ``, the
Euler relation), ``K`` antisymmetric for a rotation.  The Jacobian is the model's own,
noise-free one at random points, so a symmetry found here is exact whatever the noise in
the data; :mod:`symcal.base.linalg` decides what is numerically zero.  The test uses a bounded,
evenly spread sample of the observations (:data:`SAMPLE`).

Gauges that share parameters are one *fix set* when fixing one suggested parameter of
each would not fix them all (two scales that both suggest ``r``): each then says how many
of their parameters to fix, with an example that does.  A solve that ends where the
constraints vanish whatever the data (on the sample with each column scrambled) is a
collapse onto a trivial point, whatever its gauge was called.

Cost: the sample's Jacobian (``SAMPLE·n_g × n``) is reduced once per point to its R factor
(``n × n``, one QR), and every rank decision, null space, range and least-squares tangent
comes from the SVD of R: the same singular values and right singular vectors as the
Jacobian's (``J = Q R``, Q with orthonormal columns), the same
:func:`~symcal.base.linalg.rank_tolerance` (the Jacobian's row count), at a fraction of the
cost of SVDs of the tall Jacobian.  The Jacobian is evaluated by the stage objective's own
mapped function (its compiled twin when one is cached).  An analysis is kept per problem,
keyed by everything it depends on (constraints, free parameters, weights, the sample's
data, the start and the seed): a solve repeated on the same structure, data and start (a
benchmark loop, ``improve``'s re-solves of a kept model) reuses it.
"""

from __future__ import annotations

import hashlib
import itertools
import weakref
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from symcal.analysis.identifiability import Combination, format_combination, null_groups
from symcal.analysis.identifiability import _rref_rows as _rref
from symcal.base.forks import ForkLock
from symcal.base.linalg import (
    EXACT_RTOL,
    common_null,
    null_basis,
    range_basis,
    rank_tolerance,
)
from symcal.base.units import internal_unit
from symcal.data.dataset import Dataset
from symcal.problem.symbolic import Problem
from symcal.solvers.executor import blas_limit
from symcal.solvers.objective import Objective

#: At most this many observations, evenly spread over the dataset, enter the test.
SAMPLE = 256
#: Random points (besides the start) at which the test is made.
POINTS = 3
#: Random points lie this many nominal scales (standard deviation) from the start.
SPREAD = 0.3
#: At random points the data are moved too, by this fraction of each column's spread: a
#: gauge is an identity in the data, while a coincidence of these data (readings that fit a
#: linear model exactly, so that ``J·(θ - θ*) = g``) is not, and must not be named.
JITTER = 1e-3
#: A homogeneous set has collapsed when its size (in nominal scales) fell below this
#: fraction of its size at the start.
COLLAPSE = 1e-6
#: Kinds of gauge, in the order they are reported.
KINDS = ("scale", "rotation", "offset", "symmetry")
#: Analyses kept per problem (the most recent ones).
MEMO_SIZE = 32

#: Per problem (while it lives): analyses by the digest of everything they depend on.
_MEMO: weakref.WeakKeyDictionary[Problem, dict[bytes, Any]] = weakref.WeakKeyDictionary()
_MEMO_LOCK = ForkLock()


def _digest(kind: str, objective: Objective, u: np.ndarray, theta: np.ndarray,
            seed: int) -> bytes:
    """What an analysis depends on: the stage's structure, the sample, the point, the seed."""
    h = hashlib.sha256()
    whiten = b"" if objective.whiten is None else np.asarray(objective.whiten, float).tobytes()
    for part in (kind.encode(), "\0".join(objective.constraints).encode(),
                 objective.free.tobytes(), whiten, str(u.shape).encode(),
                 np.ascontiguousarray(u, dtype=float).tobytes(),
                 np.ascontiguousarray(theta, dtype=float).tobytes(), str(seed).encode()):
        h.update(len(part).to_bytes(8, "little"))
        h.update(part)
    return h.digest()


def _remembered(problem: Problem, key: bytes) -> Any:
    with _MEMO_LOCK:
        return _MEMO.get(problem, {}).get(key)


def _remember(problem: Problem, key: bytes, value: Any) -> None:
    with _MEMO_LOCK:
        memo = _MEMO.setdefault(problem, {})
        memo.pop(key, None)
        memo[key] = value
        while len(memo) > MEMO_SIZE:
            memo.pop(next(iter(memo)))


@dataclass(frozen=True)
class Gauge:
    """One gauge of a stage: what it moves, what it does to the constraints, the fix.

    Attributes
    ----------
    kind
        ``scale``, ``rotation``, ``offset`` or ``symmetry`` (see the module).
    parameters
        The free parameters it moves.
    directions
        Its direction(s) at the start, in parameter names (several for a group of offsets).
    fix
        What to do, in parameter names ("fix one of a1, a2, a3 or give a known length").
    text
        One line a person reads.
    generator
        ``K`` (row-major, ``n_g × n_g``): what the gauge does to one observation's
        constraints (zero: nothing).
    weights
        Scale only: the power of λ each parameter is scaled by (1 for a plain scale).
    degree
        Scale only: ``k`` in ``g(λ^w θ) = λ^k g``.
    """

    kind: str
    parameters: tuple[str, ...]
    directions: tuple[Combination, ...]
    fix: str
    text: str
    generator: tuple[tuple[float, ...], ...] = ()
    weights: dict[str, float] | None = None
    degree: float | None = None
    # its own fix and text where a fix set shared with other gauges replaced them (see
    # _fix_sets): restored when the others do not hold (GaugeAnalysis.confirmed)
    alone: tuple[str, str] | None = field(default=None, compare=False, repr=False)

    @property
    def dimension(self) -> int:
        """Number of independent directions."""
        return len(self.directions)

    @property
    def key(self) -> tuple[str, tuple[str, ...], tuple[Combination, ...]]:
        """What the gauge is, whatever its fix says (a fix set's is rewritten when a gauge
        it shared parameters with does not hold)."""
        return self.kind, self.parameters, self.directions

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form."""
        return {"kind": self.kind, "parameters": list(self.parameters),
                "directions": [c.to_dict() for c in self.directions], "fix": self.fix,
                "text": self.text, "generator": [list(r) for r in self.generator],
                "weights": None if self.weights is None else dict(self.weights),
                "degree": self.degree}

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> Gauge:
        """Inverse of :meth:`to_dict`."""
        return cls(doc["kind"], tuple(doc["parameters"]),
                   tuple(Combination.from_dict(c) for c in doc["directions"]), doc["fix"],
                   doc["text"], tuple(tuple(r) for r in doc["generator"]),
                   None if doc.get("weights") is None else dict(doc["weights"]),
                   doc.get("degree"))


def _names(names: list[str] | tuple[str, ...]) -> str:
    return ", ".join(names)


def _are(names: list[str], what: str) -> str:
    """``a is zero`` or ``a, b are all zero``."""
    return f"{names[0]} is {what}" if len(names) == 1 else f"{_names(names)} are all {what}"


def _one_of(names: list[str]) -> str:
    return names[0] if len(names) == 1 else f"one of {_names(names)}"


def _combination(vector: np.ndarray, names: tuple[str, ...]) -> Combination:
    """A direction in parameter units, largest coefficient 1, as a named combination."""
    v = vector / np.max(np.abs(vector))
    if v[np.flatnonzero(np.abs(v) > 1e-9)[0]] < 0:
        v = -v
    v = np.where(np.abs(v - np.round(v)) < 1e-6, np.round(v), v)
    coeffs = {names[i]: float(f"{v[i]:.6g}") for i in np.flatnonzero(np.abs(v) > 1e-9)}
    return Combination(coeffs, format_combination(coeffs))


class _Sample:
    """The stage's weighted constraints and their Jacobian on a sample of observations."""

    def __init__(self, objective: Objective, data: Dataset) -> None:
        problem = objective.problem
        take = np.unique(np.linspace(0, data.n - 1, min(data.n, SAMPLE)).round().astype(int))
        self.u = np.array([data.columns[c][take] if c in data.columns
                           else np.full(take.size, np.nan) for c in problem.columns],
                          dtype=float).reshape(len(problem.columns), take.size)
        self.objective = objective
        self.n = int(objective.free.sum())
        self.ng = int(objective.g.shape[0])
        self.index = objective.index
        self.scales = objective.scales

    def jittered(self, rng: np.random.Generator) -> np.ndarray:
        """The sample's data, each column moved by :data:`JITTER` of its spread."""
        with np.errstate(invalid="ignore"):
            spread = np.nanstd(self.u, axis=1) if self.u.shape[1] else np.zeros(0)
        spread = np.where(np.isfinite(spread), spread, 0.0)
        with np.errstate(invalid="ignore"):
            size = np.nanmax(np.abs(self.u), axis=1) if self.u.shape[1] else np.zeros(0)
        size = np.where(np.isfinite(size) & (size > 0), size, 1.0)
        spread = np.where(spread > 0, spread, size)   # a constant column moves too
        return self.u + JITTER * spread[:, None] * rng.standard_normal(self.u.shape)

    def at(self, theta: np.ndarray, u: np.ndarray | None = None
           ) -> tuple[np.ndarray, np.ndarray] | None:
        """``(g, J·D)``: stacked residuals (``m·n_g``) and the Jacobian in scaled units
        (``m·n_g × n``) at ``theta`` (on ``u``, default the sample's data); None where
        either is not finite."""
        got = self.objective.linearised(theta, self.u if u is None else u)
        if got is None:
            return None
        g, jac = got
        return g, jac * self.scales[None, :]

    def lift(self, g: np.ndarray) -> np.ndarray:
        """``G`` with ``G·vec(K) = (K g_i)_i`` stacked (vec row-major)."""
        m = g.size // self.ng
        gi = g.reshape(m, self.ng)
        out = np.zeros((m, self.ng, self.ng * self.ng))
        for a in range(self.ng):
            out[:, a, a * self.ng:(a + 1) * self.ng] = gi
        return out.reshape(m * self.ng, self.ng * self.ng)


@dataclass(frozen=True)
class _Point:
    """The sample at one point: residuals, and the Jacobian as ``Q R`` with the SVD of R.

    ``R = U S Vᵀ`` gives the Jacobian's singular values ``s``, right singular vectors
    ``vt`` and (through Q) its range, so nothing is decomposed at the Jacobian's height."""

    theta: np.ndarray   # full θ
    g: np.ndarray
    q: np.ndarray       # M × k, orthonormal columns (k = min(M, n))
    r: np.ndarray       # k × n: J·D = q r (scaled units)
    u: np.ndarray       # k × k
    s: np.ndarray       # k singular values, descending
    vt: np.ndarray      # n × n
    rank: int

    @property
    def null(self) -> np.ndarray:
        """Orthonormal null directions of the Jacobian (rows, scaled units)."""
        return self.vt[self.rank:]

    @property
    def jac(self) -> np.ndarray:
        """The Jacobian itself (scaled units), ``q r``."""
        product: np.ndarray = self.q @ self.r
        return product

    @property
    def range(self) -> np.ndarray:
        """Orthonormal columns spanning the Jacobian's numerical range (``M × rank``)."""
        return self.q @ self.u[:, :self.rank]

    @property
    def norm(self) -> float:
        """Frobenius norm of the Jacobian."""
        return float(np.linalg.norm(self.s))

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """The minimum-norm least-squares ``t`` of ``J t = rhs`` on the numerical range
        (orthogonal to the null directions)."""
        k = self.rank
        return np.asarray(self.vt[:k].T @ ((self.u[:, :k].T @ (self.q.T @ rhs)) / self.s[:k]))


def _point(theta: np.ndarray, g: np.ndarray, jac: np.ndarray) -> _Point:
    """The :class:`_Point` of residuals ``g`` and scaled Jacobian ``jac`` at ``theta``."""
    q, r = np.linalg.qr(jac)
    u, s, vt = np.linalg.svd(r, full_matrices=True)
    rank = int(np.sum(s > rank_tolerance(s, jac.shape[0])))
    return _Point(theta, g, q, r, u, s, vt, rank)


def _points(sample: _Sample, objective: Objective, theta0: np.ndarray, seed: int
            ) -> tuple[_Point | None, list[_Point]]:
    """The start and up to :data:`POINTS` random points (within the bounds)."""
    problem = objective.problem
    lower = np.array([p.lower for p in problem.parameters])
    upper = np.array([p.upper for p in problem.parameters])
    rng = np.random.default_rng(seed)

    def point(theta: np.ndarray, u: np.ndarray | None = None) -> _Point | None:
        got = sample.at(theta, u)
        return None if got is None else _point(theta, *got)

    start = point(theta0)
    points = []
    for _ in range(POINTS):
        z = rng.standard_normal(sample.n)
        for shrink in (1.0, 0.3, 0.1, 0.03):
            theta = theta0.copy()
            theta[sample.index] += SPREAD * shrink * sample.scales * z
            theta = np.clip(theta, lower, upper)
            p = point(theta, sample.jittered(rng))
            if p is not None:
                points.append(p)
                break
    return start, points


def _canonical_generators(basis: np.ndarray, ng: int) -> list[np.ndarray]:
    """A readable basis of a subspace of generators ``K`` (columns of ``basis``, vec
    row-major): the identity first if it belongs, then antisymmetric ones, then the rest."""
    out: list[np.ndarray] = []
    q = np.linalg.qr(basis)[0] if basis.size else basis
    eye = np.eye(ng).reshape(-1) / np.sqrt(ng)
    if q.size and np.linalg.norm(eye - q @ (q.T @ eye)) < 1e-6:
        out.append(np.eye(ng).reshape(-1))
        q = range_basis(q - np.outer(eye, eye @ q))
    if q.size:
        sym = np.zeros((ng * ng, ng * ng))
        for a in range(ng):
            for b in range(ng):
                sym[a * ng + b, a * ng + b] += 0.5
                sym[a * ng + b, b * ng + a] += 0.5
        anti = null_basis(sym @ q, ng * ng)
        for c in anti:
            k = q @ c
            out.append(k / np.max(np.abs(k)))
        if anti.size:
            q = range_basis(q - q @ (anti.T @ anti))
        for c in q.T:
            out.append(c / np.max(np.abs(c)))
    return out


def _tangent(point: _Point, sample: _Sample, k: np.ndarray) -> np.ndarray | None:
    """``t`` (scaled units, orthogonal to the invariances) with ``J t = K g`` at a point;
    None where ``K g`` is at rounding level (an exact fit)."""
    rhs = sample.lift(point.g) @ k
    if np.linalg.norm(rhs) <= EXACT_RTOL * max(point.norm, 1e-300):
        return None
    return point.solve(rhs)


@dataclass(frozen=True)
class GaugeAnalysis:
    """The gauges of one stage, found before the solve.

    Attributes
    ----------
    gauges
        Every gauge, largest kind first (:data:`KINDS`).
    points
        Random points the test was made at (besides the start).
    observations
        Observations in the sample.
    names
        The stage's free parameters.
    """

    gauges: tuple[Gauge, ...]
    points: int
    observations: int
    names: tuple[str, ...]
    sample: Any = field(default=None, compare=False, repr=False)   # _Sample of the search

    @property
    def dimension(self) -> int:
        """Number of independent gauge directions."""
        return sum(g.dimension for g in self.gauges)

    def collapse(self, theta_start: np.ndarray, theta_end: np.ndarray,
                 objective: Objective) -> str | None:
        """Why the solve failed, when it slid onto a trivial point: a scale gauge's
        parameters of positive power all gone to zero (or those of negative power grown
        without bound), or, whatever the gauges were called, constraints that vanish at
        the end whatever the data; None otherwise."""
        scales = dict(zip(objective.names, objective.scales, strict=True))
        index = objective.problem.index
        for gauge in self.gauges:
            if gauge.kind != "scale" or not gauge.degree or gauge.degree <= 0 or \
                    gauge.weights is None:
                continue
            shrink = [n for n in gauge.parameters if gauge.weights.get(n, 0.0) > 0]
            grow = [n for n in gauge.parameters if gauge.weights.get(n, 0.0) < 0]

            def size(names: list[str], theta: np.ndarray) -> float:
                return float(np.linalg.norm([theta[index[n]] / scales[n] for n in names]))

            before, after = size(shrink, theta_start), size(shrink, theta_end)
            if shrink and before > 0 and after < COLLAPSE * before:
                grew = ""
                if grow and size(grow, theta_end) > size(grow, theta_start):
                    grew = f" and {_names(grow)} grew"
                return (f"failed: the solve collapsed onto the trivial point of a gauge: "
                        f"{_names(shrink)} all went to zero{grew} (their size fell to "
                        f"{after / before:.2g} of its start), where the constraints, "
                        f"homogeneous in them, vanish whatever the data; {gauge.fix}")
            if grow and size(grow, theta_end) > size(grow, theta_start) / COLLAPSE:
                return (f"failed: the solve collapsed onto the trivial point of a gauge: "
                        f"{_names(grow)} grew without bound, where the constraints, "
                        f"homogeneous in them, vanish whatever the data; {gauge.fix}")
        return self._trivial(theta_start, theta_end, objective)

    def _trivial(self, theta_start: np.ndarray, theta_end: np.ndarray,
                 objective: Objective) -> str | None:
        """The collapse of a solve that ends where the constraints vanish whatever the
        data: on the sample with each column scrambled (no longer consistent), the
        constraints at the end are below :data:`COLLAPSE` of their size at the start."""
        sample = self.sample
        if sample is None or not self.gauges or sample.u.shape[1] < 2:
            return None
        rng = np.random.default_rng(0)
        scrambled = np.array([rng.permutation(row) for row in sample.u])
        start = sample.at(theta_start, scrambled)
        end = sample.at(theta_end, scrambled)
        real = sample.at(theta_start)
        if start is None or end is None or real is None:
            return None
        size0 = float(np.linalg.norm(start[0]))
        if size0 == 0 or float(np.linalg.norm(start[0] - real[0])) < 1e-3 * size0:
            return None      # the constraints hardly depend on the data
        size1 = float(np.linalg.norm(end[0]))
        if size1 >= COLLAPSE * size0:
            return None
        scales = dict(zip(objective.names, objective.scales, strict=True))
        index = objective.problem.index
        moved = [g for g in self.gauges if g.parameters]
        zero = [n for g in moved for n in g.parameters
                if abs(theta_end[index[n]]) < COLLAPSE * max(abs(theta_start[index[n]]),
                                                             scales[n])]
        zero = list(dict.fromkeys(zero))
        fixes = "; ".join(dict.fromkeys(g.fix for g in moved))
        went = f": {_names(zero)} went to zero" if zero else ""
        return (f"failed: the solve collapsed onto a trivial point, where the constraints "
                f"vanish whatever the data (on scrambled data their size fell to "
                f"{size1 / size0:.2g} of the start's){went}; {fixes}")

    def directions(self, objective: Objective, data: Dataset, theta: np.ndarray
                   ) -> np.ndarray:
        """The gauges' directions at ``theta`` (``k × n_free``, parameter units): what
        the identifiability analysis counts as exactly undeterminable there."""
        return self.confirmed(objective, data, theta)[0]

    def confirmed(self, objective: Objective, data: Dataset, theta: np.ndarray
                  ) -> tuple[np.ndarray, GaugeAnalysis]:
        """The gauges' directions at ``theta`` and the analysis reduced to the gauges that
        hold there.  A symmetry without a known tangent (found only as a null direction
        of the Jacobian at the start and the random points) holds at ``theta`` only where
        the Jacobian is null along it to :data:`symcal.base.linalg.EXACT_RTOL`; one that does
        not was a degeneracy of the region the start lies in (an exponential term that
        vanishes there, say), not a symmetry, and must not hide a direction the data
        determine."""
        n = len(self.names)
        if not self.gauges:
            return np.zeros((0, n)), self
        sample = _Sample(objective, data)
        key = _digest("confirmed " + repr(self.to_dict()), objective, sample.u, theta, 0)
        known = _remembered(objective.problem, key)
        if known is None:
            with blas_limit():
                known = self._confirmed(sample, objective, theta)
            _remember(objective.problem, key, known)
        basis, held = known
        return basis.copy(), held

    def _confirmed(self, sample: _Sample, objective: Objective, theta: np.ndarray
                   ) -> tuple[np.ndarray, GaugeAnalysis]:
        n = len(self.names)
        got = sample.at(theta)
        if got is None:
            return np.zeros((0, n)), self
        here = _point(theta, *got)
        scales = sample.scales
        explicit: list[np.ndarray] = []
        implicit: list[Gauge] = []
        for gauge in self.gauges:
            if gauge.kind == "offset":
                explicit += [np.array([c.coefficients.get(m, 0.0) for m in self.names])
                             / scales for c in gauge.directions]
            elif gauge.kind == "scale" and gauge.weights is not None:
                w = np.array([gauge.weights.get(m, 0.0) for m in self.names])
                explicit.append(w * theta[objective.index] / scales)
            elif gauge.generator and np.any(np.asarray(gauge.generator)):
                t = _tangent(here, sample, np.asarray(gauge.generator).reshape(-1))
                if t is None:
                    implicit.append(gauge)
                else:
                    explicit.append(t)
            else:
                implicit.append(gauge)
        rows = [v / np.linalg.norm(v) for v in explicit if np.linalg.norm(v) > 0]
        basis = range_basis(np.array(rows).T) if rows else np.zeros((n, 0))
        kept = [gauge for gauge in self.gauges if gauge not in implicit]
        if implicit:
            # J (I - B Bᵀ) = Q R (I - B Bᵀ): the same singular values and right vectors
            r = here.r
            projected = r - (r @ basis) @ basis.T
            if projected.shape[0] < n:
                projected = np.vstack([projected, np.zeros((n - projected.shape[0], n))])
            _, sv, vt = np.linalg.svd(projected)
            top = float(here.s[0]) if here.s.size and here.s[0] > 0 else 1.0
            extra: list[np.ndarray] = []
            for gauge in implicit:
                room = [i for i in range(len(sv) - 1, -1, -1)
                        if np.linalg.norm(basis.T @ vt[i]) < 0.5
                        and not any(abs(vt[i] @ e) > 0.5 for e in extra)]
                chosen = room[:gauge.dimension]
                if len(chosen) == gauge.dimension and all(
                        sv[i] <= EXACT_RTOL * top for i in chosen):
                    extra += [vt[i] for i in chosen]
                    kept.append(gauge)
            basis = range_basis(np.column_stack([basis, *extra])) if extra else basis
        held = self if len(kept) == len(self.gauges) else replace(
            self, gauges=_without(self.gauges, kept, self.names))
        return (basis * scales[:, None]).T, held

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form."""
        return {"gauges": [g.to_dict() for g in self.gauges], "points": self.points,
                "observations": self.observations, "names": list(self.names)}

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> GaugeAnalysis:
        """Inverse of :meth:`to_dict`."""
        return cls(tuple(Gauge.from_dict(g) for g in doc["gauges"]), doc["points"],
                   doc["observations"], tuple(doc["names"]))


def _group_offsets(rows: np.ndarray, names: tuple[str, ...]) -> list[Gauge]:
    """Constant null directions (parameter units, RREF rows) as one gauge per group of
    parameters that share them."""
    clean = np.where(np.abs(rows) > 1e-9, rows, 0.0)
    pivots_of = [int(np.flatnonzero(row)[0]) for row in clean]
    out = []
    for group in null_groups(clean):
        members = [r for r, pivot in enumerate(pivots_of) if pivot in group]
        sub = rows[members]
        involved = [names[i] for i in np.flatnonzero(np.any(np.abs(sub) > 1e-9, axis=0))]
        pivots = [names[int(np.flatnonzero(np.abs(r) > 1e-9)[0])] for r in sub]
        d = len(members)
        if d == 1:
            fix = f"fix {_one_of(involved)}"
        else:
            fix = f"fix {d} of {_names(involved)} (e.g. {_names(pivots)})"
        directions = tuple(_combination(r, names) for r in sub)
        along = " or ".join(c.text for c in directions)
        text = (f"offset: {_names(involved)} enter the constraints only in combinations: "
                f"moving them along {along} changes no constraint; {fix}")
        out.append(Gauge("offset", tuple(involved), directions, fix, text))
    return out


def _covariant(points: list[_Point], sample: _Sample) -> list[np.ndarray]:
    """Generators ``K ≠ 0`` with ``J t = K g`` solvable at every random point."""
    ng = sample.ng
    if not points or any(p.g.size < sample.n + ng * ng + 1 for p in points):
        return []
    lifted = [sample.lift(p.g) for p in points]
    residual = []
    for p, big_g in zip(points, lifted, strict=True):
        q = p.range
        residual.append(big_g - q @ (q.T @ big_g))
    _, sg, vgt = np.linalg.svd(np.vstack(lifted), full_matrices=False)
    keep = sg > EXACT_RTOL * max(float(sg[0]) if sg.size else 0.0, 1e-300)
    if not keep.any():
        return []
    whiten = vgt[keep].T / sg[keep][None, :]          # vec(K) = whiten @ c
    _, s, vt = np.linalg.svd(np.vstack(residual) @ whiten, full_matrices=False)
    s_full = np.concatenate([s, np.zeros(vt.shape[1] - s.size)])
    null = vt[s_full <= EXACT_RTOL]
    if not null.size:
        return []
    return _canonical_generators(whiten @ null.T, ng)


def find_gauges(objective: Objective, data: Dataset, theta: np.ndarray, seed: int = 0
                ) -> GaugeAnalysis:
    """The gauges of a stage (its constraints and free parameters) on its data.

    Parameters
    ----------
    objective
        The stage's objective (constraints, free parameters, weights).
    data
        The dataset it is solved on (a bounded sample of it is used).
    theta
        The full parameter vector at the start.
    seed
        Seed of the random points.

    Returns
    -------
    GaugeAnalysis
        Every gauge found, in parameter names, with the fix.
    """
    names = objective.names
    if len(names) == 0 or data.n == 0:
        return GaugeAnalysis((), 0, 0, names)
    sample = _Sample(objective, data)
    key = _digest("find", objective, sample.u, theta, seed)
    known = _remembered(objective.problem, key)
    if known is None:
        with blas_limit():
            known = _find(sample, objective, theta, seed)
        _remember(objective.problem, key, known)
    return known   # frozen: shared by every solve that asks the same


def _find(sample: _Sample, objective: Objective, theta: np.ndarray, seed: int
          ) -> GaugeAnalysis:
    names = objective.names
    n = len(names)
    start, points = _points(sample, objective, theta, seed)
    if not points:
        return GaugeAnalysis((), 0, sample.u.shape[1], names)
    scales = sample.scales
    gauges: list[Gauge] = []
    reference = start if start is not None else points[0]
    units = {p.name: p.unit for p in objective.problem.parameters}
    # homogeneities: constant powers w with J·(w∘θ) = k·g at every point
    const = common_null([p.null for p in points], n)
    powers, zero_degree = _homogeneities(points, sample, const)
    # scale and rotation first: what K ≠ 0 does
    for k in _covariant(points, sample):
        if powers is not None and np.allclose(k.reshape(sample.ng, sample.ng),
                                              np.eye(sample.ng)):
            gauges.append(_scale_gauge(powers, 1.0, reference, sample, names, units))
        else:
            gauges.append(_covariant_gauge(k, points, reference, sample, names, units))
    # invariances (K = 0): constant ones are offsets, homogeneities of degree 0 scales,
    # the rest symmetries
    d_inv = min(p.null.shape[0] for p in points)
    if d_inv:
        if const.size:
            rows = _rref(const * scales[None, :])
            gauges += _group_offsets(rows, names)
        for w in zero_degree:
            gauges.append(_scale_gauge(w, 0.0, reference, sample, names, units))
        varying = d_inv - const.shape[0] - len(zero_degree)
        if varying > 0:
            gauges.append(_varying_gauge(varying, const, reference, points[0], names,
                                         scales))
    gauges.sort(key=lambda g: KINDS.index(g.kind))
    gauges = _fix_sets(gauges, reference, names)
    return GaugeAnalysis(tuple(gauges), len(points), sample.u.shape[1], names, sample)


# --------------------------------------------------------------------------- homogeneities


def _homogeneities(points: list[_Point], sample: _Sample, const: np.ndarray
                   ) -> tuple[np.ndarray | None, list[np.ndarray]]:
    """The constraints' homogeneities: constant powers ``w`` and degree ``k`` with
    ``J·(w∘θ) = k·g`` at every random point (in parameter units).

    Returns
    -------
    (powers, zero_degree)
        ``powers``: the powers of degree 1 (None when there is none), the representative
        with the fewest negative and the fewest non-zero powers; ``zero_degree``: the
        invariances of this form (``k = 0``), readable rows, none of which is a constant
        offset or a parameter the constraints do not depend on.
    """
    n = sample.n
    if not points or any(p.g.size < n + 2 for p in points):
        return None, []
    blocks = []
    for p in points:
        theta = p.theta[sample.index] / sample.scales
        blocks.append(np.column_stack([p.jac * theta[None, :], -p.g]))
    stacked = np.vstack(blocks)
    norms = np.linalg.norm(stacked, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    # more rows than columns (above): the thin SVD has every right singular vector, and
    # does not form the rows x rows U (75 MB and 0.9 s for the dual problem's sample)
    _, sv, vt = np.linalg.svd(stacked / norms[None, :], full_matrices=False)
    sv = np.concatenate([sv, np.zeros(vt.shape[0] - sv.size)])
    null = vt[sv <= EXACT_RTOL * max(float(sv[0]), 1e-300)] / norms[None, :]
    if not null.size:
        return None, []
    dead = np.all(np.array([np.all(np.abs(p.jac) <= EXACT_RTOL * max(
        float(np.abs(p.jac).max(initial=0.0)), 1e-300), axis=0) for p in points]), axis=0)
    null[:, :n][:, dead] = 0.0
    degree = null[:, n]
    powers = None
    if np.max(np.abs(degree)) > EXACT_RTOL * np.max(np.abs(null)):
        lead = degree / float(degree @ degree)          # lead · degree = 1
        powers = lead @ null[:, :n]
        basis = null_basis(degree[None, :], 1) if null.shape[0] > 1 else np.zeros((0, 1))
        flat = basis @ null[:, :n] if basis.size else np.zeros((0, n))
    else:
        flat = null[:, :n]
    zero = _independent(flat, const, points[0], sample)
    if powers is not None:
        powers = _simplest(powers, zero)
    return powers, zero


def _independent(rows: np.ndarray, const: np.ndarray, point: _Point, sample: _Sample
                 ) -> list[np.ndarray]:
    """Readable rows (RREF, largest power 1) of the degree-0 powers that are no constant
    offset: their directions at a point, with the offsets', have full rank."""
    if not rows.size:
        return []
    rows = rows[np.linalg.norm(rows, axis=1) > 1e-12]
    if not rows.size:
        return []
    rows = _rref(range_basis(rows.T).T) if rows.shape[0] > 1 else rows
    theta = point.theta[sample.index] / sample.scales
    kept: list[np.ndarray] = []
    base = [c for c in const] if const.size else []
    for row in rows:
        trial = np.array([*base, *(k * theta for k in kept), row * theta])
        if np.linalg.matrix_rank(trial, tol=1e-9 * max(float(np.abs(trial).max()), 1e-300)) \
                == len(trial):
            kept.append(row)
    out = []
    for row in kept:
        row = np.where(np.abs(row) > 1e-12 * np.max(np.abs(row)), row, 0.0)
        row = row / np.max(np.abs(row))
        if row[np.flatnonzero(row)[0]] < 0:
            row = -row
        out.append(_tidy(row))
    return out


def _tidy(w: np.ndarray) -> np.ndarray:
    """Powers rounded to whole numbers and simple fractions where they are one."""
    out = w.copy()
    for i, x in enumerate(w):
        for den in (1, 2, 3, 4):
            if abs(x * den - round(x * den)) < 1e-6:
                out[i] = round(x * den) / den
                break
    return out


def _simplest(powers: np.ndarray, zero: list[np.ndarray]) -> np.ndarray:
    """Of ``powers`` plus degree-0 rows, the one with the fewest negative and non-zero
    powers (a scale of a positive set, where there is one)."""
    best = powers

    def key(w: np.ndarray) -> tuple[int, int]:
        big = 1e-9 * max(float(np.max(np.abs(w))), 1e-300)
        return int(np.sum(w < -big)), int(np.sum(np.abs(w) > big))

    for row in zero:
        options = [best] + [best - best[j] / row[j] * row for j in np.flatnonzero(row)]
        best = min(options, key=key)
    return _tidy(best)


def _scale_gauge(w: np.ndarray, degree: float, reference: _Point, sample: _Sample,
                 names: tuple[str, ...], units: Mapping[str, str]) -> Gauge:
    """A homogeneity of the constraints (powers ``w``, degree 0 or 1) as a scale gauge."""
    ng = sample.ng
    big = np.max(np.abs(w))
    support = np.abs(w) > 1e-9 * big
    involved = [names[i] for i in np.flatnonzero(support)]
    norm = 1.0 / big
    weights = {names[i]: float(f"{w[i] * norm:.6g}") for i in np.flatnonzero(support)}
    degree = float(f"{degree * norm:.6g}")
    direction = w * reference.theta[sample.index]
    lengths = all(internal_unit(units.get(m, "")) == "mm" for m in involved)
    known = "a known length" if lengths else "one of them a known value"
    fix = f"fix {_one_of(involved)} or give {known}"
    power = "" if all(abs(x - 1) < 1e-9 for x in weights.values()) else (
        " (powers " + ", ".join(f"{m}: {x:g}" for m, x in weights.items()) + ")")
    up = [m for m in involved if weights[m] > 0]
    down = [m for m in involved if weights[m] < 0]
    if degree == 0:
        moved = f"{_names(up)} up together with {_names(down)} down" if down else _names(up)
        text = (f"scale: the constraints are homogeneous of degree 0 in "
                f"{_names(involved)}{power}: scaling {moved} leaves every constraint "
                f"unchanged; {fix}")
    else:
        trivial = ("the trivial point where they are all zero" if not down else
                   f"the trivial point where {_are(up, 'zero')} and {_names(down)} "
                   f"{'grows' if len(down) == 1 else 'grow'} without bound")
        text = (f"scale: the constraints are homogeneous of degree {degree:g} in "
                f"{_names(involved)}{power}: scaling them all fits as well, down to "
                f"{trivial}; {fix}")
    generator = tuple(tuple(float(1.0 if (a == b and degree) else 0.0) for b in range(ng))
                      for a in range(ng))
    return Gauge("scale", tuple(involved), (_combination(direction, names),), fix, text,
                 generator, weights, degree)


# --------------------------------------------------------------------------- fix sets


def _suggested(gauge: Gauge) -> list[tuple[str, ...]]:
    """The choices a gauge's own fix offers: one parameter each (several for a gauge of
    more than one direction: its example)."""
    if gauge.dimension > 1:
        found = gauge.fix.split("(e.g. ", 1)
        if len(found) == 2:
            return [tuple(found[1].rstrip(")").split(", "))]
        return [gauge.parameters[:gauge.dimension]]
    fix = gauge.fix.split(" or give ", 1)[0]
    fix = fix.removeprefix("fix ").removeprefix("one of ")
    return [(name,) for name in fix.split(", ")]


def _fix_sets(gauges: list[Gauge], reference: _Point | None, names: tuple[str, ...]
              ) -> list[Gauge]:
    """Gauges that share parameters, where fixing one suggested parameter of each can
    leave a direction free, as one fix set: each says how many of their parameters to
    fix, with an example that fixes them all."""
    groups: list[list[int]] = []
    for i, gauge in enumerate(gauges):
        joined = [g for g in groups if any(set(gauge.parameters) & set(gauges[j].parameters)
                                           for j in g)]
        merged = [i] + [j for g in joined for j in g]
        groups = [g for g in groups if g not in joined] + [sorted(merged)]
    out = list(gauges)
    for group in groups:
        if len(group) < 2:
            continue
        members = [gauges[i] for i in group]
        rows = np.array([[c.coefficients.get(n, 0.0) for n in names]
                         for g in members for c in g.directions])
        rows = rows / np.max(np.abs(rows), axis=1, keepdims=True)
        total = len(rows)

        def fixes(chosen: tuple[str, ...], rows: np.ndarray = rows, total: int = total
                  ) -> bool:
            cols = [names.index(c) for c in dict.fromkeys(chosen)]
            sub = rows[:, cols]
            return len(cols) >= total and np.linalg.matrix_rank(sub, tol=1e-9) == total

        combos = itertools.islice(itertools.product(*(_suggested(g) for g in members)), 4096)
        if all(fixes(tuple(n for part in combo for n in part)) for combo in combos):
            continue
        union = list(dict.fromkeys(n for g in members for n in g.parameters))
        count = {n: sum(n in g.parameters for g in members) for n in union}
        chosen: list[str] = []
        for name in sorted(union, key=lambda n: (count[n], union.index(n))):
            cols = [names.index(c) for c in [*chosen, name]]
            if np.linalg.matrix_rank(rows[:, cols], tol=1e-9) == len(cols):
                chosen.append(name)
            if len(chosen) == total:
                break
        example = (" and ".join(chosen) if len(chosen) <= 2
                   else ", ".join(chosen[:-1]) + f" and {chosen[-1]}")
        shared = [n for n in union if count[n] > 1]
        fix = (f"fix {total} of {_names(union)}: e.g. {example} (these {len(members)} "
               f"gauges share {_names(shared)}, so one fix of each is not enough)")
        for i in group:
            g = gauges[i]
            text = g.text[: len(g.text) - len(g.fix)] + fix if g.text.endswith(g.fix) \
                else f"{g.text}; {fix}"
            out[i] = replace(g, fix=fix, text=text, alone=g.alone or (g.fix, g.text))
    return out


def _without(gauges: tuple[Gauge, ...], kept: list[Gauge], names: tuple[str, ...]
             ) -> tuple[Gauge, ...]:
    """The gauges that hold (``kept``, in ``gauges``' order), their fix sets made again
    among themselves: a symmetry found at the start and dismissed where it does not hold
    no longer counts in the fix of a gauge it shared parameters with (a flow loop's scale
    said "fix 2" where one fix does)."""
    held = [g for g in gauges if g in kept]
    if len(held) == len(gauges):
        return gauges
    own = [replace(g, fix=g.alone[0], text=g.alone[1], alone=None) if g.alone else g
           for g in held]
    return tuple(_fix_sets(own, None, names))


def _varying_gauge(count: int, const: np.ndarray, reference: _Point, fallback: _Point,
                   names: tuple[str, ...], scales: np.ndarray) -> Gauge:
    """Invariances whose direction depends on the point, named at the start."""
    directions = []
    for point in (reference, fallback):
        null = point.null
        if const.size and null.size:
            null = null - (null @ const.T) @ const
        basis = range_basis(null.T) if null.size else np.zeros((len(names), 0))
        if basis.shape[1] >= count:
            directions = list(_rref((basis[:, :count] * scales[:, None]).T))
            break
    involved = [names[i] for i in np.flatnonzero(
        np.any(np.abs(np.array(directions)) > 1e-9, axis=0))] if directions else list(names)
    pivots = [names[int(np.flatnonzero(np.abs(d) > 1e-9)[0])] for d in directions]
    fix = (f"fix {_one_of(involved)}" if count == 1 else f"fix {count} of {_names(involved)}"
           + (f" (e.g. {_names(pivots)})" if len(pivots) == count else ""))
    combos = tuple(_combination(d, names) for d in directions)
    text = (f"symmetry: moving {_names(involved)} together along a curve that depends on "
            f"where they are leaves every constraint unchanged; {fix}")
    return Gauge("symmetry", tuple(involved), combos, fix, text)


def _covariant_gauge(k: np.ndarray, points: list[_Point], reference: _Point,
                     sample: _Sample, names: tuple[str, ...], units: Mapping[str, str]
                     ) -> Gauge:
    """A generator K ≠ 0 as a scale, a rotation or a symmetry."""
    ng = sample.ng
    k = np.where(np.abs(k) > 1e-9 * np.max(np.abs(k)), k, 0.0)
    lower = k.reshape(ng, ng)[np.tril_indices(ng)]
    lead = lower[np.flatnonzero(lower)[0]] if np.any(lower) else k[np.flatnonzero(k)[0]]
    k = k * np.sign(lead)      # the rotation generator as [[0, -1], [1, 0]]
    kmat = k.reshape(ng, ng)
    generator = tuple(tuple(float(f"{x:.12g}") + 0.0 for x in row) for row in kmat)
    scales = sample.scales
    tangents = [t * scales for t in (_tangent(p, sample, k) for p in points)
                if t is not None]
    here = _tangent(reference, sample, k)
    t0 = here * scales if here is not None else tangents[0]
    support = np.any(np.abs(np.array(tangents)) > 1e-9 * np.max(np.abs(tangents)), axis=0)
    involved = [names[i] for i in np.flatnonzero(support)]
    if np.allclose(kmat, np.eye(ng)):
        ratios = np.array([t / p.theta[sample.index] for t, p in
                           zip(tangents, points, strict=True)])
        ratios = np.where(support[None, :], ratios, 0.0)
        if np.allclose(ratios, ratios[0], rtol=1e-6, atol=1e-9) and np.all(
                np.isfinite(ratios)):
            r = ratios[0]
            degree = 1.0 / float(np.max(np.abs(r)))
            weights = {names[i]: float(f"{r[i] * degree:.6g}")
                       for i in np.flatnonzero(support)}
            degree = float(f"{degree:.6g}")
            lengths = all(internal_unit(units.get(m, "")) == "mm" for m in involved)
            fix = (f"fix {_one_of(involved)} or give "
                   + ("a known length" if lengths else "one of them a known value"))
            power = "" if all(abs(w - 1) < 1e-9 for w in weights.values()) else (
                " (powers " + ", ".join(f"{m}: {w:g}" for m, w in weights.items()) + ")")
            text = (f"scale: the constraints are homogeneous of degree {degree:g} in "
                    f"{_names(involved)}{power}: scaling them all fits as well, down to "
                    f"the trivial point where they are all zero; {fix}")
            return Gauge("scale", tuple(involved), (_combination(t0, names),), fix, text,
                         generator, weights, degree)
    # anchors: parameters moved by the same amount at every point (the frame's angle)
    stacked = np.array(tangents)
    anchors = [names[i] for i in np.flatnonzero(support)
               if np.allclose(stacked[:, i], stacked[0, i], rtol=1e-6, atol=1e-12)]
    if np.allclose(kmat, -kmat.T):
        fix = f"fix {_one_of(anchors or involved)} or give a known direction"
        text = (f"rotation: turning {_names(anchors or involved)} together with "
                f"{_names([m for m in involved if m not in anchors]) or 'nothing else'} "
                f"turns the constraints together and leaves the cost unchanged; {fix}")
        return Gauge("rotation", tuple(involved), (_combination(t0, names),), fix, text,
                     generator)
    fix = f"fix {_one_of(anchors or involved)}"
    text = (f"symmetry: moving {_names(involved)} together changes the constraints only "
            f"by a fixed linear map of themselves; {fix}")
    return Gauge("symmetry", tuple(involved), (_combination(t0, names),), fix, text,
                 generator)
