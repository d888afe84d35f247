"""Which physical effect is missing: ranking candidate terms against the residuals.

A candidate says "sensor output y lacks a term c·φ(v)".  Its regressor is (∂ρ/∂y)·φ(v)
for every residual ρ (constraints, and comparisons with a reference), with ∂ρ/∂y taken
symbolically.  Residuals and regressors are whitened per observation (constraints and
comparisons of one observation are correlated and have different noise), then the
nuisance — what the current parameters and the comparisons' arbitrary offsets can
already absorb — is projected out.  A candidate is ranked by the residual sum of squares
it removes, tested with an F-test at a Bonferroni-corrected level, ranked by its
significance (the F-test's log p-value, computed in log space so that it stays finite where
p underflows: a one-column term that removes a little less than
a two-column one can still be the stronger evidence), and grouped with the candidates
whose projected regressors it cannot be told apart from; a group is led by its simplest
member (a term in the sensor's own input first, lower order before higher).

Each tested candidate also gets its *minimal detectable effect*: the smallest term (its
RMS over the calibration data, in the output's internal unit) that the same F-test would
find at its Bonferroni level with power :data:`POWER`, in the direction of its columns
the data see worst: ``sqrt(λ*) σ / sqrt(min eig(X̃ᵀX̃))``, λ* the non-centrality of
χ²_m that gives that power, σ² the residual variance per whitened row, X̃ the projected
regressor with each column scaled to a term of RMS one unit (:attr:`Basis.scales`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from symcal.analysis.bands import f_log_sf
from symcal.base.linalg import rank_tolerance

ABSORBED = 1e-3         # projected norm below this share of the raw norm: absorbed
POWER = 0.8             # the power at which a minimal detectable effect is stated
TERM = 1e-3             # the RMS of a term whose scaled coefficients are 1 (Basis.scales)
INDISTINGUISHABLE = 0.98  # canonical correlation above which candidates are one group
EQUAL = 0.95              # a simpler member leads a group if it explains this much as well
EXACT_FIT = 1e-6          # a residual sum of squares left below this share: an exact fit
#: Kinds of candidate that are not a term added to one output: their label is their
#: description alone ("the constant rho (platen tooth pitch) is off").
STANDALONE = ("approximation", "constant", "fixed", "latency", "zero")


@dataclass(frozen=True)
class Basis:
    """φ(v): the shape of a candidate term, with what it takes to write it in YAML."""

    kind: str                  # harmonic | linear | quadratic | cubic | angle_harmonic |
                               # drift | product | gain | latency | constant | fixed |
                               # zero | approximation
    variable: str              # the variable's name in the problem (column, signal, expr)
    description: str           # e.g. "harmonic 3 of s2.p (period 1.016 mm)"
    columns: tuple[str, ...]   # coefficient names, e.g. ("h3_sin", "h3_cos")
    terms: tuple[str, ...]     # YAML expressions of each column in the model's symbols,
                               # with {v} (and {a} for an angle) placeholders, and
                               # {period}, {centre} for the constants below
    angle: str | None = None   # the angle variable of an angle product
    order: int = 1             # the harmonic number (1 for other kinds)
    unit: str = ""             # display unit of the variable
    angle_unit: str = ""       # display unit of the angle of an angle product
    scales: tuple[float, ...] = ()  # coefficients giving terms of about 1 µm (internal)
    period: float = 0.0        # the period of a harmonic, in internal units
    centre: float = 0.0        # the centre of a linear or quadratic term, internal units
    # a product of two variables, ``({v} - {centre})*({w} - {other_centre})``:
    other: str | None = None   # the second variable's name in the problem
    other_unit: str = ""       # its display unit
    other_centre: float = 0.0  # its centre, internal units
    # ``constant``: the constants (keys of Problem.constants) made into ONE parameter
    # started at their common value; ``fixed``: the fixed parameter freed (its name);
    # ``latency``: the instance whose readings lag (variable) and the columns it reads;
    # ``zero``: the column whose zero is off (variable) and the instances that read it
    targets: tuple[str, ...] = ()
    # the RMS of the term (internal units of what it changes) when every coefficient is
    # its scale; for constant, fixed and latency, the scale itself (the coefficient's size)
    term: float = 1e-3
    # ``latency``: the noise each target's declared noise leaves in its rate on the data
    # (root mean square, internal units per second; 0 where none is declared)
    rate_noise: tuple[float, ...] = ()

    @property
    def complexity(self) -> tuple[int, int]:
        """How simple the shape is: a share of another output (the same fit as the term
        linear in the reading it is made of, but zero where that output is) before linear
        and drift, before harmonics (by number), before quadratic, before cubic, before an
        output's gain varying with a variable, before products."""
        rank = {"approximation": 0, "constant": 0, "fixed": 0, "zero": 0, "coupling": 1,
                "linear": 2, "drift": 2, "latency": 2, "harmonic": 3, "quadratic": 4, "cubic": 5,
                "gain": 6, "product": 7, "power": 7, "angle_harmonic": 7}
        return rank.get(self.kind, 8), self.order


@dataclass
class Candidate:
    """One candidate effect and what testing it found."""

    output: str
    basis: Basis
    delta_rss: float = 0.0
    # what the term removes as written, its columns alone beyond the nuisance (the same as
    # delta_rss but for a term tested beyond simpler ones it does not write)
    written_rss: float = 0.0
    share: float = 0.0
    f_stat: float = 0.0
    p_value: float = 1.0
    log_p: float = 0.0
    significant: bool = False
    absorbed: bool = False
    biases: tuple[str, ...] = ()
    # every residual's RMS now and as predicted with the term ("DATASET/NAME" → (now, new),
    # display units), and the same of their standard deviations
    reduction: dict[str, tuple[float, float]] = field(default_factory=dict)
    scatter: dict[str, tuple[float, float]] = field(default_factory=dict)
    coefficient: tuple[float, ...] = ()
    coefficient_se: tuple[float, ...] = ()
    indistinguishable: list[str] = field(default_factory=list)
    q: np.ndarray | None = field(default=None, repr=False)
    mde: float | None = None     # the minimal detectable term's RMS, internal units
    reopens: str = ""            # why it is never proposed: it re-opens a gauge
    # the parameters a term the test misses could move by more than UNSEEN standard
    # errors, with how far (see unseen_bias)
    unseen: tuple[tuple[str, float], ...] = ()
    reach: float = 0.0           # a bound on every parameter's unseen_bias (inf: absorbed)
    # the BIC's predicted change when the term, as written, is added and the calibration
    # solved again (see bic_change); None where not predicted
    bic_change: float | None = None

    @property
    def label(self) -> str:
        """E.g. ``"s1.p_hat += harmonic 1 of s2.p"`` (the description alone for the model's
        own approximation)."""
        if self.basis.kind in STANDALONE:
            return self.basis.description
        return f"{self.output} += {self.basis.description}"


@dataclass(frozen=True)
class Design:
    """Whitened residual rows, nuisance columns, and the row blocks they come from."""

    r: np.ndarray                       # (M,)
    nuisance: np.ndarray                # (M, k)
    nuisance_names: tuple[str, ...]
    blocks: tuple[tuple[str, slice, np.ndarray, tuple[str, ...], tuple[float, ...]], ...]
    # (dataset, rows, unwhitening per observation (N × n_q × rank), quantity names,
    #  display scales)


def _orthonormal(x: np.ndarray) -> np.ndarray:
    """An orthonormal basis of the columns of ``x`` (numerically independent ones): the
    SVD of its small R factor, so that the tall matrix is touched by one QR only."""
    if x.shape[1] == 0:
        return x
    q, r = np.linalg.qr(x)
    u, s, _ = np.linalg.svd(r)
    keep = s > 1e-8 * s[0] if s.size and s[0] > 0 else np.zeros(s.shape, dtype=bool)
    return q @ u[:, keep]


def _seen_columns(x: np.ndarray, qn: np.ndarray) -> np.ndarray:
    """The columns of ``x`` (M × m) with the nuisance's span ``qn`` removed, but only
    those the nuisance does not absorb (:data:`ABSORBED` of their own norm): what is left
    of an absorbed column is rounding and, where it is a reading evaluated at its
    adjusted value, the reading's share of the residual itself, which normalised would
    explain the residual.  A shunt's linear term in its own reading (its gain absorbed
    by a Hall sensor's sensitivity), as the simpler term a product is tested beyond,
    took away the Hall sensor's temperature effect: the product's test was the same on
    data with and without it."""
    xp = _project(x, qn)
    raw = np.linalg.norm(x, axis=0)
    return xp[:, np.linalg.norm(xp, axis=0) >= ABSORBED * raw]


def _project(x: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``x`` with the span of the orthonormal ``q`` removed."""
    return x - q @ (q.T @ x) if q.shape[1] else x


def redundant_columns(design: Design, x: np.ndarray) -> list[int]:
    """The columns of a candidate's regressor (M × m) that add nothing on their own: each
    absorbed by the nuisance (a quadratic's linear part where the sensor's gain already
    is), or explaining the residual exactly (re-opening a gauge).  A term written without
    them is the same hypothesis without a parameter the data cannot determine."""
    if x.shape[1] < 2:
        return []
    qn = _basis(design)
    r = _project(design.r, qn)
    rss0 = float(r @ r)
    out = []
    for j in range(x.shape[1]):
        raw = float(np.linalg.norm(x[:, j]))
        xp = _project(x[:, j:j + 1], qn)[:, 0]
        norm = float(np.linalg.norm(xp))
        if raw == 0.0 or norm < ABSORBED * raw or (
                rss0 > 0 and float(xp @ r) ** 2 / norm**2 >= (1 - EXACT_FIT) * rss0):
            out.append(j)
    return out


def unexplained_share(design: Design, x: np.ndarray) -> float:
    """The share of a column ``x`` (M,) the nuisance does not explain: the norm of its
    part orthogonal to the nuisance's span over its own (1: orthogonal, 0: absorbed)."""
    raw = float(np.linalg.norm(x))
    if raw == 0.0:
        return 0.0
    return float(np.linalg.norm(_project(x[:, None], _basis(design)))) / raw


def unexplained(design: Design, x: np.ndarray) -> np.ndarray:
    """The part of ``x`` (M × m) the nuisance does not explain: what a test of it sees."""
    return _project(x, _basis(design))


def absorbed(design: Design, x: np.ndarray) -> bool:
    """Whether every column of ``x`` (M × m) lies in the nuisance's span: what adding it
    changes, the free parameters already do (an offset where a bias is free)."""
    qn = _basis(design)
    for j in range(x.shape[1]):
        raw = float(np.linalg.norm(x[:, j]))
        if raw > 0.0 and float(np.linalg.norm(_project(x[:, j:j + 1], qn))) >= ABSORBED * raw:
            return False
    return True


@dataclass(frozen=True)
class _Nuisance:
    """The nuisance's SVD on its numerical range: its orthonormal basis ``u``, and what
    gives the coefficients of a column in it (``x ≈ nuisance @ (solve @ x)``)."""

    u: np.ndarray
    solve: np.ndarray


#: The nuisances' SVDs of the last designs asked (by identity; a diagnosis alternates
#: between a few designs).
_SVDS: list[tuple[Design, _Nuisance]] = []
_KEPT = 4


def _nuisance(design: Design) -> _Nuisance:
    """The nuisance's SVD (one per design, however many candidates are tested on it)."""
    for kept, found in _SVDS:
        if kept is design:
            return found
    matrix = design.nuisance
    if matrix.size == 0:
        found = _Nuisance(np.zeros((matrix.shape[0], 0)), np.zeros((matrix.shape[1], 0)))
    else:
        # each column to unit norm first: the rank is that of the directions, whatever
        # the parameters' units (a drift written per hour beside ns/s parameters made a
        # column 1e13 times the others, whose directions the tolerance then dropped: a
        # term the aging rate absorbs exactly was "nearly absorbed, would move A.a 2348 SE")
        norms = np.linalg.norm(matrix, axis=0)
        d = np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 0.0)
        u, sv, vt = np.linalg.svd(matrix * d[None, :], full_matrices=False)
        keep = sv > rank_tolerance(sv, matrix.shape[0])
        found = _Nuisance(u[:, keep], d[:, None] * (vt[keep].T / sv[keep][None, :]))
    _SVDS.insert(0, (design, found))
    del _SVDS[_KEPT:]
    return found


def refit(design: Design, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The least-squares fit of the design's residual by its nuisance and the columns
    ``x`` (M × m) jointly: the nuisance's coefficients, ``x``'s coefficients, their
    covariance (residual variance times the inverse normal matrix of ``x`` beyond the
    nuisance) and the residual variance.  From the nuisance's SVD: no solve of the
    whole matrix per candidate."""
    nuisance = _nuisance(design)
    qn = nuisance.u
    xp = _project(x, qn)
    q, r_x = np.linalg.qr(xp)
    rank_x = int(np.sum(np.abs(np.diag(r_x)) > 1e-10 * max(float(np.abs(r_x).max()), 1e-300)))
    gram = xp.T @ xp
    inv = np.linalg.pinv(gram)
    coef_x = inv @ (xp.T @ design.r)
    rest = design.r - x @ coef_x
    coef_n = nuisance.solve @ (qn.T @ rest)
    left = rest - design.nuisance @ coef_n
    dof = max(len(design.r) - qn.shape[1] - rank_x, 1)
    s2 = float(left @ left) / dof
    return coef_n, coef_x, s2 * inv, s2


def bic_change(design: Design, x: np.ndarray) -> float:
    """The change of the fit's BIC (``M log(RSS/M) + rank log M``, as
    :attr:`~symcal.calibrate.result.Result.bic`) when the columns ``x`` (M × m) join the
    nuisance: the residual sum of squares the fit of both leaves, against the nuisance's
    alone, and one parameter per column the nuisance does not already hold.  Unlike the
    F-test of :func:`test_candidates`, which tests a term beyond its simpler ones, this
    is the term as it would be added, alone: what the BIC of the revision will say."""
    qn = _basis(design)
    r = _project(design.r, qn)
    rss0 = float(r @ r)
    q = _orthonormal(_project(x, qn))
    proj = q.T @ r
    rss1 = max(rss0 - float(proj @ proj), 1e-300)
    rows = len(design.r)
    if rss0 <= 0.0:
        return 0.0
    return rows * float(np.log(rss1 / rss0)) + q.shape[1] * float(np.log(rows))


def _basis(design: Design) -> np.ndarray:
    """The nuisance's orthonormal basis (see :func:`_nuisance`)."""
    return _nuisance(design).u


def gauge_fixes(design: Design, fixed: Mapping[str, np.ndarray]) -> dict[str, str]:
    """The fixed parameters (name → whitened column of ∂r/∂θ_k, rows as the design's)
    that fix a gauge, with how: freeing one either adds nothing the free parameters do
    not already do (an offset or a rotation: ``"absorbed"``), or explains the residual
    exactly (a scale: the constraints are homogeneous in a set of parameters it belongs
    to, so that its projected column is the residual itself: ``"exact"``)."""
    qn = _basis(design)
    r = _project(design.r, qn)
    rss0 = float(r @ r)
    out = {}
    for name, x in fixed.items():
        raw = float(np.linalg.norm(x))
        if raw == 0.0:
            continue
        xp = _project(x[:, None], qn)[:, 0]
        norm = float(np.linalg.norm(xp))
        if norm < ABSORBED * raw:
            out[name] = "absorbed"
        elif rss0 > 0 and float(xp @ r) ** 2 / norm**2 >= (1 - EXACT_FIT) * rss0:
            out[name] = "exact"
    return out


def test_candidates(
    design: Design, candidates: list[Candidate], regressors: list[np.ndarray], alpha: float,
    local: Callable[[Candidate], bool] | None = None,
    extras: list[np.ndarray | None] | None = None,
    gauges: Mapping[str, np.ndarray] | None = None,
    reference: Callable[[Candidate], bool] | None = None,
    flat: Callable[[Candidate], bool] | None = None,
) -> list[Candidate]:
    """Test every candidate (regressor ``(M, m)``) and rank them, best first.

    Returns the candidates (all of them: absorbed ones and those that re-open a gauge
    last), with significance at ``alpha / len(candidates)`` and groups of
    indistinguishable candidates filled in.  Within a group the data cannot choose;
    ``local`` marks the candidates to lead their group then (e.g. a term in the sensor's
    own input).  ``extras[i]`` (M × k or None): what candidate i is tested beyond (the
    simpler terms it contains).  A candidate that explains the residual exactly re-opens
    a gauge (``reopens``; never significant): on noisy data only a direction no data can
    determine does that; ``gauges`` (name → whitened column of a fixed parameter that
    fixes one) name which.  ``reference`` marks the candidates on a sensor the problem
    trusts (every parameter fixed): after the local ones, the others lead a group
    before them.  ``flat`` marks the candidates the data make affine in their variable
    (a curve in a variable held at two values): absorbed as far as the nuisance takes
    their affine part, never tested, since what is left of them is the variable's own
    noise (their test would test it).
    """
    from scipy.special import fdtrc  # here: a solve's report imports this module

    nuisance = _nuisance(design)
    qn = nuisance.u
    r = _project(design.r, qn)
    rss0 = float(r @ r)
    dof = len(r) - qn.shape[1]
    level = alpha / max(len(candidates), 1)
    fixes = {name: _project(x[:, None], qn)[:, 0] for name, x in (gauges or {}).items()}
    for i, (cand, x) in enumerate(zip(candidates, regressors, strict=True)):
        raw = float(np.linalg.norm(x))
        xp = _project(x, qn)
        if raw == 0.0:
            cand.absorbed = True
            continue
        if np.linalg.norm(xp) < ABSORBED * raw or (flat is not None and flat(cand)):
            cand.absorbed = True
            coef = nuisance.solve @ (qn.T @ x)     # x's coefficients in the nuisance
            weight = np.linalg.norm(coef, axis=1) if coef.ndim == 2 else np.abs(coef)
            weight = weight * np.linalg.norm(design.nuisance, axis=0)
            order = np.argsort(-weight)
            cand.biases = tuple(design.nuisance_names[i] for i in order[:4]
                                if weight[i] > 0.05 * weight[order[0]])
            continue
        cand.reach = _reach_bound(x, xp, level)
        extra = None if extras is None else extras[i]
        base, rb, m_extra = r, rss0, 0
        if extra is not None:       # as written: its own columns alone (else delta_rss)
            alone = r @ _orthonormal(xp)
            cand.written_rss = float(alone @ alone)
            # each column to unit norm first: the simpler terms' scales differ by up to
            # the variable's own (a reading in nV: its linear term 6e3, its square 5e12),
            # and the basis would drop the smaller as rounding (a cube in a current was
            # then tested beyond its square alone, and kept in place of the linear term)
            seen = _seen_columns(extra, qn)
            qe = _orthonormal(seen / np.linalg.norm(seen, axis=0)) if seen.shape[1] else seen
            m_extra = qe.shape[1]
            base = _project(r, qe)
            rb = float(base @ base)
            xp = _project(xp, qe)
            if np.linalg.norm(xp) < ABSORBED * raw:
                # on these data the term is the simpler terms it contains, to within the
                # readings' noise (a cubic in a variable held at two values is affine
                # there): its test would test that noise (a new user's joint, designed
                # at ±180°, named a cubic in its encoder's reading at p = 1e-20)
                cand.absorbed = True
                continue
        q = _orthonormal(xp)
        m = q.shape[1]
        if m == 0:
            cand.absorbed = True
            continue
        proj = q.T @ base
        delta = float(proj @ proj)
        cand.q = q
        cand.delta_rss = delta
        if extra is None:
            cand.written_rss = delta
        cand.share = delta / rss0 if rss0 > 0 else 0.0
        if rss0 > 0 and rss0 - delta <= EXACT_FIT * rss0:
            cand.reopens = _reopens(q, fixes)
            continue
        rest = max(dof - m_extra - m, 1)
        denom = (rb - delta) / rest
        cand.f_stat = (delta / m) / denom if denom > 0 else float("inf")
        # scipy.stats.f.sf's own function, without its argument checks (the same bits)
        cand.p_value = float(fdtrc(m, rest, cand.f_stat))
        cand.log_p = f_log_sf(cand.f_stat, m, rest)     # finite where p underflows
        cand.significant = cand.p_value < level
        cand.reduction, cand.scatter = _reduction(design, r, base - q @ proj)
        cand.mde = _detectable(xp, cand.basis.scales, m, level, denom, cand.basis.term)
    tested = [c for c in candidates if not c.absorbed and not c.reopens]
    ranked = sorted(tested, key=lambda c: (c.log_p, -c.delta_rss))
    _group(ranked, local, reference=reference)
    return ranked + [c for c in candidates if c.reopens] + \
        [c for c in candidates if c.absorbed]


def unseen_bias(design: Design, x: np.ndarray, level: float) -> np.ndarray:
    """How far a term of shape ``x`` (M × m) that the test would miss can move each of
    the nuisance's parameters: Baarda's external reliability.  A term at its minimal
    detectable size (power :data:`POWER` at ``level``, in the direction the data see
    worst for each parameter) shifts the least-squares estimate by the part of it the
    nuisance absorbs; the largest such shift of parameter k over the terms the test
    misses, in units of k's standard error, is
    ``sqrt(λ*) sqrt(s_kᵀ (X̃ᵀX̃)⁻¹ s_k) / sqrt((AᵀA)⁻¹_kk)``, ``s_k`` the shift of k per
    unit coefficient and ``X̃`` the part of ``x`` the nuisance ``A`` does not explain.
    The residual variance cancels: it is the geometry of the data alone.  Infinite for a
    term the nuisance absorbs completely; one value per nuisance column."""
    nuisance = _nuisance(design)
    qn = nuisance.u
    k = design.nuisance.shape[1]
    if x.shape[1] == 0 or not np.any(x):
        return np.zeros(k)
    xp = _project(x, qn)
    shift = nuisance.solve @ (qn.T @ x)              # k × m: each parameter per coefficient
    gram = xp.T @ xp
    sv = np.linalg.svd(gram, compute_uv=False)
    rank = int(np.sum(sv > 1e-12 * float(np.linalg.norm(x)) ** 2))
    if rank == 0:
        return np.full(k, np.inf)
    lam = noncentrality(rank, level)
    reach = np.einsum("km,mn,kn->k", shift, np.linalg.pinv(gram, rcond=1e-12), shift)
    se = np.sqrt(np.sum(nuisance.solve ** 2, axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(se > 0, np.sqrt(lam * np.maximum(reach, 0.0)) / se, 0.0)


def _reach_bound(x: np.ndarray, xp: np.ndarray, level: float) -> float:
    """A bound on :func:`unseen_bias` over every parameter (Baarda's bias-to-noise
    ratio): no parameter moves by more standard errors than the whole fit of the term's
    absorbed part does, ``sqrt(λ* max_γ |x_a γ|² / |x_p γ|²)``, ``x_a = x - x_p``;
    from the m × m Gram matrices, where :func:`unseen_bias` needs the nuisance."""
    gram_p = xp.T @ xp
    sv = np.linalg.svd(gram_p, compute_uv=False)
    rank = int(np.sum(sv > 1e-12 * float(np.sum(x * x))))
    if rank < x.shape[1]:
        return float("inf")
    whole = x.T @ x
    if whole.shape == (1, 1):      # one column: the generalised eigenvalue is the ratio
        ratio = float(whole[0, 0] / gram_p[0, 0])
    else:
        from scipy.linalg import eigvals

        ratio = float(np.max(np.real(eigvals(whole, gram_p))))
    return float(np.sqrt(noncentrality(rank, level) * max(ratio - 1.0, 0.0)))


def _reopens(q: np.ndarray, fixes: Mapping[str, np.ndarray]) -> str:
    """Why a candidate that explains the residual exactly is never proposed."""
    best = None
    for name, x in fixes.items():
        norm = float(np.linalg.norm(x))
        if norm == 0.0:
            continue
        corr = float(np.linalg.norm(q.T @ x)) / norm
        if corr > INDISTINGUISHABLE and (best is None or corr > best[0]):
            best = (corr, name)
    if best is not None:
        return (f"it re-opens the gauge that fixing {best[1]} closed: free, it explains "
                "the residual's own noise exactly")
    return ("it explains the residual exactly, noise included: it re-opens a gauge (a "
            "direction no data can determine)")


_NONCENTRALITY: dict[tuple[int, float], float] = {}


def noncentrality(m: int, level: float, power: float = POWER) -> float:
    """The non-centrality λ at which χ²_m(λ) exceeds its level-``level`` critical value
    with probability ``power``."""
    key = (m, level)
    if key not in _NONCENTRALITY:
        # imported here: scipy.stats is the largest import of a command that reports a
        # solve (0.4-1 s), and a solve's report needs none of it
        import scipy.stats
        from scipy.optimize import brentq
        from scipy.special import chdtri

        crit = float(chdtri(m, level))                    # scipy.stats.chi2.isf's own
        _NONCENTRALITY[key] = float(brentq(
            lambda lam: float(scipy.stats.ncx2.sf(crit, m, lam)) - power, 1e-9, 1e4))
    return _NONCENTRALITY[key]


def _detectable(xp: np.ndarray, scales: tuple[float, ...], m: int, level: float,
                variance: float, term: float = TERM) -> float | None:
    """The minimal detectable term of a candidate (RMS, internal units), or None."""
    if len(scales) != xp.shape[1] or not np.isfinite(variance) or variance <= 0:
        return None
    scaled = xp * np.asarray(scales)[None, :]
    sv = np.linalg.svd(scaled, compute_uv=False)
    sv = sv[sv > 1e-8 * sv[0]] if sv.size and sv[0] > 0 else sv[:0]
    if not sv.size:
        return None
    low = float(sv[-1]) ** 2     # the worst direction the data see (absorbed ones aside)
    return term * float(np.sqrt(noncentrality(m, level) * variance / low))


def rms(values: np.ndarray) -> float:
    """The root mean square of ``values``: what :func:`_reduction` and a candidate's
    predictions measure a residual by (an offset is an error like the scatter)."""
    return float(np.sqrt(np.mean(np.square(values))))


def _reduction(design: Design, before: np.ndarray, after: np.ndarray
               ) -> tuple[dict[str, tuple[float, float]], dict[str, tuple[float, float]]]:
    """The RMS of every residual before and after adding a candidate, and the same of
    their standard deviations."""
    sizes, scatter = {}, {}
    for dataset, rows, unwhiten, names, scales in design.blocks:
        rank = unwhiten.shape[2]
        # each residual's values as a contiguous row: reduced along it, each row's sum
        # is the one of that residual alone (rms, np.std: the same bits), in one call
        b = np.ascontiguousarray(
            np.einsum("nqr,nr->nq", unwhiten, before[rows].reshape(-1, rank)).T)
        a = np.ascontiguousarray(
            np.einsum("nqr,nr->nq", unwhiten, after[rows].reshape(-1, rank)).T)
        rms_b, rms_a = (np.sqrt(np.mean(np.square(v), axis=1)).tolist() for v in (b, a))
        sd_b, sd_a = (np.std(v, axis=1).tolist() for v in (b, a))
        for k, name in enumerate(names):
            key = f"{dataset}/{name}"
            sizes[key] = (rms_b[k] / scales[k], rms_a[k] / scales[k])
            scatter[key] = (sd_b[k] / scales[k], sd_a[k] / scales[k])
    return sizes, scatter


def _same(a: Candidate, b: Candidate) -> bool:
    """Whether the largest canonical correlation of two candidates' spans passes
    :data:`INDISTINGUISHABLE`."""
    if a.q is None or b.q is None:
        return False
    return top_singular_value(a.q.T @ b.q) > INDISTINGUISHABLE


def top_singular_value(c: np.ndarray) -> float:
    """The largest singular value of a small matrix: its norm where it is one row or
    column, in closed form where it is 2 × 2 (``σ² = (s + √(s² − 4 det²)) / 2``, ``s``
    the squared Frobenius norm), else from the SVD.  ``_group`` asks it of thousands
    of 1 × 1 to 2 × 2 products per diagnosis, where a library's SVD costs its calling
    overhead many times over.  The closed form loses digits where the two singular
    values nearly coincide (about 1e-8 relative): a threshold of 0.98 is all it serves."""
    if min(c.shape) == 1:
        return math.hypot(*c.ravel().tolist())
    if c.shape != (2, 2):
        return float(np.linalg.svd(c, compute_uv=False)[0]) if c.size else 0.0
    values = c.ravel().tolist()                      # Python floats: no array overhead
    big = max(abs(v) for v in values)
    if not 0.0 < big < math.inf:                     # zero, or not a number to scale
        return float(np.linalg.svd(c, compute_uv=False)[0])
    a, b, d, e = (v / big for v in values)          # no square under- or overflows
    s = a * a + b * b + d * d + e * e
    det = a * e - b * d
    return big * math.sqrt(0.5 * (s + math.sqrt(max(s * s - 4.0 * det * det, 0.0))))


def _group(ranked: list[Candidate], local: Callable[[Candidate], bool] | None,
           top: int = 8, reference: Callable[[Candidate], bool] | None = None) -> None:
    """Fill ``indistinguishable`` for the leading candidates (canonical correlation); the
    simplest member of a group that explains as much (:data:`EQUAL`), and as written
    alone what its test found (a term tested beyond simpler ones it does not write: a
    Hall sensor's gain varying with T, ``I*(T - c)``, before the product of its raw
    reading, which adds its zero times T; a magnetometer's raw reading times time, its
    bias drifting with its gain, before the gain of its output), moves up to lead it:
    a term on a sensor the problem does not trust as its reference first (``reference``:
    a pressure sensor's dependence on the temperature, where both sides of the
    constraint read it alike, belongs to the sensor being calibrated; a Hall sensor's
    offset drifting with the temperature before the same term on a reference shunt whose
    own input the temperature is), then a term in the sensor's own input (``local``),
    then the simpler shape (:attr:`Basis.complexity`)."""
    def simplicity(c: Candidate) -> tuple[bool, bool, tuple[int, int]]:
        return ((reference is not None and reference(c)),
                (local is not None and not local(c)), c.basis.complexity)

    for i in range(min(top, len(ranked))):
        lead = ranked[i]
        members = [j for j in range(i + 1, len(ranked)) if _same(lead, ranked[j])]
        equal = [j for j in members if ranked[j].delta_rss >= EQUAL * lead.delta_rss]
        # as written, alone, a member must remove (nearly) what its test found
        pool = [i, *equal]
        fits = [j for j in pool if ranked[j].written_rss >= EQUAL * ranked[j].delta_rss]
        best = min(fits or pool, key=lambda j: simplicity(ranked[j]))
        if best != i and (i not in (fits or pool)
                          or simplicity(ranked[best]) < simplicity(lead)):
            ranked[i], ranked[best] = ranked[best], ranked[i]
            lead = ranked[i]
            members = [j for j in range(i + 1, len(ranked)) if _same(lead, ranked[j])]
        lead.indistinguishable = [ranked[j].label for j in members]
