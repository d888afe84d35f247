"""Which physical effect is missing: ranking candidate terms against the residuals.

A candidate says "sensor output y lacks a term c·φ(v)".  Its regressor is (∂ρ/∂y)·φ(v)
for every residual ρ (constraints, and comparisons with a reference), with ∂ρ/∂y taken
symbolically.  Residuals and regressors are whitened per observation (constraints and
comparisons of one observation are correlated and have different noise), then the
nuisance — what the current parameters and the comparisons' arbitrary offsets can
already absorb — is projected out.  A candidate is ranked by the residual sum of squares
it removes, tested with an F-test at a Bonferroni-corrected level, ranked by its
significance (the F-test's log p-value: a one-column term that removes a little less than
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

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.stats

from symcal.base.linalg import range_basis

ABSORBED = 1e-3         # projected norm below this share of the raw norm: absorbed
POWER = 0.8             # the power at which a minimal detectable effect is stated
TERM = 1e-3             # the RMS of a term whose scaled coefficients are 1 (Basis.scales)
INDISTINGUISHABLE = 0.98  # canonical correlation above which candidates are one group
EQUAL = 0.95              # a simpler member leads a group if it explains this much as well
#: Kinds of candidate that are not a term added to one output: their label is their
#: description alone ("the constant rho (platen tooth pitch) is off").
STANDALONE = ("approximation", "constant", "fixed", "latency")


@dataclass(frozen=True)
class Basis:
    """φ(v): the shape of a candidate term, with what it takes to write it in YAML."""

    kind: str                  # harmonic | linear | quadratic | angle_harmonic | drift |
                               # product | latency | constant | fixed | approximation
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
    # ``latency``: the instance whose readings lag (variable) and the columns it reads
    targets: tuple[str, ...] = ()

    @property
    def complexity(self) -> tuple[int, int]:
        """How simple the shape is: linear and drift before harmonics (by number) before
        quadratic before angle products."""
        rank = {"approximation": 0, "constant": 0, "fixed": 0, "linear": 1, "drift": 1,
                "latency": 1, "harmonic": 2, "quadratic": 3, "product": 4,
                "angle_harmonic": 4}
        return rank.get(self.kind, 5), self.order


@dataclass
class Candidate:
    """One candidate effect and what testing it found."""

    output: str
    basis: Basis
    delta_rss: float = 0.0
    share: float = 0.0
    f_stat: float = 0.0
    p_value: float = 1.0
    log_p: float = 0.0
    significant: bool = False
    absorbed: bool = False
    biases: tuple[str, ...] = ()
    reduction: dict[str, tuple[float, float]] = field(default_factory=dict)
    coefficient: tuple[float, ...] = ()
    coefficient_se: tuple[float, ...] = ()
    indistinguishable: list[str] = field(default_factory=list)
    q: np.ndarray | None = field(default=None, repr=False)
    mde: float | None = None     # the minimal detectable term's RMS, internal units

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
    # (dataset, rows, unwhitening matrix (n_q × rank), quantity names, display scales)


def test_candidates(
    design: Design, candidates: list[Candidate], regressors: list[np.ndarray], alpha: float,
    local: Callable[[Candidate], bool] | None = None,
) -> list[Candidate]:
    """Test every candidate (regressor ``(M, m)``) and rank them, best first.

    Returns the candidates (all of them, absorbed ones last), with significance at
    ``alpha / len(candidates)`` and groups of indistinguishable candidates filled in.
    Within a group the data cannot choose; ``local`` marks the candidates to lead their
    group then (e.g. a term in the sensor's own input).
    """
    qn = range_basis(design.nuisance)
    r = design.r - qn @ (qn.T @ design.r)
    rss0 = float(r @ r)
    dof = len(r) - qn.shape[1]
    level = alpha / max(len(candidates), 1)
    for cand, x in zip(candidates, regressors, strict=True):
        raw = float(np.linalg.norm(x))
        xp = x - qn @ (qn.T @ x)
        if raw == 0.0:
            cand.absorbed = True
            continue
        if np.linalg.norm(xp) < ABSORBED * raw:
            cand.absorbed = True
            coef = np.linalg.lstsq(design.nuisance, x, rcond=None)[0]
            weight = np.linalg.norm(coef, axis=1) if coef.ndim == 2 else np.abs(coef)
            weight = weight * np.linalg.norm(design.nuisance, axis=0)
            order = np.argsort(-weight)
            cand.biases = tuple(design.nuisance_names[i] for i in order[:4]
                                if weight[i] > 0.05 * weight[order[0]])
            continue
        q, s, _ = np.linalg.svd(xp, full_matrices=False)
        q = q[:, s > 1e-8 * s[0]]
        m = q.shape[1]
        proj = q.T @ r
        delta = float(proj @ proj)
        cand.q = q
        cand.delta_rss = delta
        cand.share = delta / rss0 if rss0 > 0 else 0.0
        denom = (rss0 - delta) / max(dof - m, 1)
        cand.f_stat = (delta / m) / denom if denom > 0 else float("inf")
        cand.p_value = float(scipy.stats.f.sf(cand.f_stat, m, max(dof - m, 1)))
        cand.log_p = float(scipy.stats.f.logsf(cand.f_stat, m, max(dof - m, 1)))
        cand.significant = cand.p_value < level
        cand.reduction = _reduction(design, r, r - q @ proj)
        cand.mde = _detectable(xp, cand.basis.scales, m, level, denom)
    ranked = sorted([c for c in candidates if not c.absorbed],
                    key=lambda c: (c.log_p, -c.delta_rss))
    _group(ranked, local)
    return ranked + [c for c in candidates if c.absorbed]


_NONCENTRALITY: dict[tuple[int, float], float] = {}


def noncentrality(m: int, level: float, power: float = POWER) -> float:
    """The non-centrality λ at which χ²_m(λ) exceeds its level-``level`` critical value
    with probability ``power``."""
    key = (m, level)
    if key not in _NONCENTRALITY:
        from scipy.optimize import brentq

        crit = float(scipy.stats.chi2.isf(level, m))
        _NONCENTRALITY[key] = float(brentq(
            lambda lam: float(scipy.stats.ncx2.sf(crit, m, lam)) - power, 1e-9, 1e4))
    return _NONCENTRALITY[key]


def _detectable(xp: np.ndarray, scales: tuple[float, ...], m: int, level: float,
                variance: float) -> float | None:
    """The minimal detectable term of a candidate (RMS, internal units), or None."""
    if len(scales) != xp.shape[1] or not np.isfinite(variance) or variance <= 0:
        return None
    scaled = xp * np.asarray(scales)[None, :]
    low = float(np.linalg.eigvalsh(scaled.T @ scaled)[0])
    if low <= 0:
        return None
    return TERM * float(np.sqrt(noncentrality(m, level) * variance / low))


def _reduction(design: Design, before: np.ndarray, after: np.ndarray
               ) -> dict[str, tuple[float, float]]:
    """Standard deviation of every residual, before and after adding a candidate."""
    out = {}
    for dataset, rows, unwhiten, names, scales in design.blocks:
        rank = unwhiten.shape[1]
        b = before[rows].reshape(-1, rank) @ unwhiten.T
        a = after[rows].reshape(-1, rank) @ unwhiten.T
        for k, name in enumerate(names):
            out[f"{dataset}/{name}"] = (float(np.std(b[:, k]) / scales[k]),
                                        float(np.std(a[:, k]) / scales[k]))
    return out


def _same(a: Candidate, b: Candidate) -> bool:
    if a.q is None or b.q is None:
        return False
    return float(scipy.linalg.svdvals(a.q.T @ b.q)[0]) > INDISTINGUISHABLE


def _group(ranked: list[Candidate], local: Callable[[Candidate], bool] | None,
           top: int = 8) -> None:
    """Fill ``indistinguishable`` for the leading candidates (canonical correlation); the
    simplest member of a group that explains as much (:data:`EQUAL`) moves up to lead it:
    a term in the sensor's own input (``local``) first, then the simpler shape
    (:attr:`Basis.complexity`)."""
    def simplicity(c: Candidate) -> tuple[bool, tuple[int, int]]:
        return (local is not None and not local(c)), c.basis.complexity

    for i in range(min(top, len(ranked))):
        lead = ranked[i]
        members = [j for j in range(i + 1, len(ranked)) if _same(lead, ranked[j])]
        equal = [j for j in members if ranked[j].delta_rss >= EQUAL * lead.delta_rss]
        best = min(equal, key=lambda j: simplicity(ranked[j]), default=None)
        if best is not None and simplicity(ranked[best]) < simplicity(lead):
            ranked[i], ranked[best] = ranked[best], ranked[i]
            lead = ranked[i]
            members = [j for j in range(i + 1, len(ranked)) if _same(lead, ranked[j])]
        lead.indistinguishable = [ranked[j].label for j in members]
