"""`symcal diagnose`: compare the calibrated model with the measurements, show where it
fails, and name the physical effect that is most likely missing (ARCHITECTURE.md).

The flow: a calibration result → evaluate every residual (constraints and reference comparisons) on
every dataset, with its sensitivity to each sensor output (exact, through hooks) and to
the free parameters → where it fails (binned structure, periodograms) → which effect is
missing (candidate library, projected F-tests, indistinguishable groups) → words, YAML.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

from symcal.analysis.discovery import Basis, Candidate, Design, test_candidates
from symcal.analysis.residuals import Binned, Periodogram, Variable, periodogram, structure
from symcal.data import Dataset
from symcal.effects import effect_yaml
from symcal.linalg import whitening
from symcal.numeric import mapped
from symcal.problem import Problem
from symcal.result import Result
from symcal.units import ANGLE_UNITS, DISPLAY_UNITS

HARMONICS = 8


@dataclass(frozen=True)
class ResidualView:
    """One residual on one dataset: spread, series, structure, periodogram."""

    dataset: str
    name: str
    kind: str
    unit: str
    before: np.ndarray
    after: np.ndarray
    x_name: str
    x: np.ndarray
    binned: tuple[Binned, ...]
    periodogram: Periodogram | None

    @property
    def scale(self) -> float:
        """Size of the display unit in internal units."""
        return DISPLAY_UNITS[self.unit]

    def to_dict(self, series: bool = True) -> dict:
        """Plain-data form in the display unit (the plotting contract)."""
        doc = {"dataset": self.dataset, "name": self.name, "kind": self.kind,
               "unit": self.unit or "(internal)",
               "std_before": float(np.std(self.before)) / self.scale,
               "std_after": float(np.std(self.after)) / self.scale,
               "binned": [b.to_dict(self.scale) for b in self.binned],
               "periodogram": self.periodogram.to_dict() if self.periodogram else None}
        if series:
            doc["series"] = {"x": {"name": self.x_name, "values": self.x.tolist()},
                             "before": (self.before / self.scale).tolist(),
                             "after": (self.after / self.scale).tolist()}
        return doc


@dataclass(frozen=True, eq=False)
class Diagnosis:
    """What `symcal diagnose` found; ``candidates`` are ranked, best first."""

    result: Result
    residuals: tuple[ResidualView, ...]
    candidates: tuple[Candidate, ...]
    yaml: dict[str, str]
    alpha: float
    tested: int

    @property
    def leads(self) -> tuple[Candidate, ...]:
        """Ranked candidates, one per group of indistinguishable ones, best first."""
        seen: set[str] = set()
        out = []
        for c in self.candidates:
            if c.absorbed or c.label in seen:
                continue
            out.append(c)
            seen.update(c.indistinguishable)
        return tuple(out)

    @property
    def significant(self) -> tuple[Candidate, ...]:
        """The significant candidates (group leads), best first."""
        return tuple(c for c in self.leads if c.significant)

    def candidate_text(self, cand: Candidate) -> str:
        """The candidate in words."""
        return _words(cand, self.alpha, self.tested)

    def to_dict(self, series: bool = False) -> dict:
        """Plain data (``--json``; with ``series`` the plotting contract)."""
        ranked = list(self.leads)
        return {
            "problem": self.result.name, "alpha": self.alpha, "tested": self.tested,
            "datasets": [{"name": d.name, "n": d.n} for d in self.result.datasets],
            "residuals": [v.to_dict(series) for v in self.residuals],
            "candidates": [
                {"rank": i + 1, "label": c.label, "output": c.output,
                 "basis": c.basis.description, "delta_rss_share": c.share,
                 "f_stat": c.f_stat, "p_value": c.p_value, "significant": c.significant,
                 "reduction": {k: list(v) for k, v in c.reduction.items()},
                 "indistinguishable": list(c.indistinguishable),
                 "text": self.candidate_text(c), "yaml": self.yaml.get(c.label, "")}
                for i, c in enumerate(ranked[:20])],
            "absorbed": [{"label": c.label, "biases": list(c.biases)}
                         for c in self.candidates if c.absorbed and c.biases][:20],
            "singular_values": list(self.result.identifiability.singular_values),
            "correlation": self.result.uncertainty.to_dict()["correlation"],
        }


def _words(cand: Candidate, alpha: float, tested: int) -> str:
    biggest = sorted(cand.reduction.items(), key=lambda kv: -(kv[1][0] - kv[1][1]))[:2]
    falls = "; ".join(f"{k.replace('/', ' ')} std {b:.3g} → {a:.3g}" for k, (b, a) in biggest)
    verdict = ("significant" if cand.significant else "not significant")
    owner = cand.basis.variable.split(".", 1)[0] if "." in cand.basis.variable else None
    instance = cand.output.split(".", 1)[0]
    cross = ""
    if owner is not None and owner != instance:
        cross = (f" {cand.basis.variable} is what another sensor ({owner}) measures: "
                 f"{instance}'s output depends on a quantity it should not see, such as a "
                 "lateral or cross-axis dependence.")
    text = (f"{cand.output} varies with {cand.basis.description}, a term its model lacks."
            f"{cross} "
            f"Adding it would remove {cand.share:.0%} of what the model cannot yet explain "
            f"({falls}); F = {cand.f_stat:.3g}, p = {cand.p_value:.2g}: {verdict} at "
            f"{alpha:g} after allowing for the {tested} candidates tested.")
    if cand.indistinguishable:
        shown = "; ".join(cand.indistinguishable[:4])
        more = f" and {len(cand.indistinguishable) - 4} more" if len(cand.indistinguishable) > 4 \
            else ""
        text += (f" These data cannot tell it apart from: {shown}{more}. Only a reference "
                 "sensor or another constraint can separate them.")
    return text


@dataclass
class _Block:
    dataset: Dataset
    names: list[str]
    kinds: list[str]
    units: list[str]
    offsets: list[bool]
    before: np.ndarray
    after: np.ndarray
    hooks: np.ndarray      # (N, n_q, n_h)
    jac: np.ndarray        # (N, n_q, p)
    variables: list[Variable]


def _evaluate(hp: Problem, ds: Dataset, theta0: np.ndarray, theta: np.ndarray,
              free: np.ndarray) -> _Block:
    names, kinds, units, offsets, exprs = [], [], [], [], []
    for c in hp.constraints:
        names.append(c.name)
        kinds.append("constraint")
        units.append(c.unit)
        offsets.append(False)
        exprs.append(c.sx)
    for comp in hp.comparisons:
        if comp.datasets is not None and ds.name not in comp.datasets:
            continue
        if any(col not in ds.columns for col in hp.columns_of(comp.reference)):
            continue
        names.append(comp.name)
        kinds.append("comparison")
        units.append(comp.unit)
        offsets.append(comp.remove_mean)
        exprs.append(comp.estimate - comp.reference)
    hooks = ca.vertcat(*hp.hooks.values())
    u_ext = ca.vertcat(hp.u, hooks)
    e = ca.vertcat(*exprs)
    theta_free = hp.theta[np.flatnonzero(free).tolist()]
    var_specs = _variable_specs(hp)
    fn = mapped(hp.theta, u_ext, [e, ca.jacobian(e, hooks).T, ca.jacobian(e, theta_free).T,
                                  ca.vertcat(*(sx for _, sx, _, _, _ in var_specs))], "diag")
    u = np.vstack([ds.matrix(hp.columns), np.zeros((hooks.shape[0], ds.n))])
    after, dh, dj, values = fn(theta, u)
    before = fn(theta0, u)[0]
    n, nq = after.shape
    variables = [Variable(name, values[:, k], unit, period, kind, _role(hp, name))
                 for k, (name, _, unit, period, kind) in enumerate(var_specs)]
    variables += _unused_columns(hp, ds)
    return _Block(ds, names, kinds, units, offsets, before, after,
                  dh.reshape(n, nq, hooks.shape[0]),    # vec() of (n_h × n_q) is
                  dj.reshape(n, nq, int(free.sum())), variables)  # column-major


def _variable_specs(hp: Problem) -> list[tuple[str, ca.SX, str, float | None, str]]:
    """(name, SX, unit, period, kind) of every variable: columns (but the references),
    sensor inputs and outputs, and named expressions.

    Variables computed from sensor outputs have kind ``"derived"``: the residuals are
    examined along them, but no candidate term uses them (a sensor input would then
    depend on sensor outputs, a cycle in the model).
    """
    references = _references(hp)
    hooks = ca.vertcat(*hp.hooks.values())
    out: list[tuple[str, ca.SX, str, float | None, str]] = []
    for k, col in enumerate(hp.columns):
        if col not in references:
            spec = hp.column_specs.get(col)
            unit = spec.unit if spec is not None else ""
            out.append((col, hp.u[k], unit, None, _column_kind(hp, col)))
    for sig in hp.signals:
        derived = ca.depends_on(sig.sx, hooks)
        out.append((sig.name, sig.sx, sig.unit, sig.period, "derived" if derived else "signal"))
    for q in hp.expressions:
        kind = "angle" if q.unit in ANGLE_UNITS else "expression"
        out.append((q.name, q.sx, q.unit, None,
                    "derived" if ca.depends_on(q.sx, hooks) else kind))
    return out


def _references(hp: Problem) -> set[str]:
    """Columns of reference sensors: never a variable a model may use."""
    return {col for comp in hp.comparisons for col in hp.columns_of(comp.reference)}


def _unused_columns(hp: Problem, ds: Dataset) -> list[Variable]:
    """Data columns the problem does not use yet (but the references): an effect may
    depend on them, e.g. a drift in time."""
    references = _references(hp)
    out = []
    for col, spec in hp.column_specs.items():
        if col in ds.columns and col not in hp.columns and col not in references:
            out.append(Variable(col, np.asarray(ds.columns[col]), spec.unit, None,
                                _column_kind(hp, col), spec.role))
    return out


def _role(hp: Problem, name: str) -> str:
    spec = hp.column_specs.get(name)
    return spec.role if spec is not None else ""


def _column_kind(hp: Problem, col: str) -> str:
    """``drift`` for the column declared as time (``role: time``), else ``column``."""
    spec = hp.column_specs.get(col)
    return "drift" if spec is not None and spec.role == "time" else "column"


def _distinct(variables: list[Variable]) -> list[Variable]:
    """Drop variables equal to another (e.g. an input bound to a column), keeping the one
    that declares a period, else the first."""
    kept: list[Variable] = []
    for var in variables:
        if np.ptp(var.values) <= 0 or not np.all(np.isfinite(var.values)):
            continue
        tol = 1e-12 * (1 + float(np.abs(var.values).max()))
        same = next((i for i, k in enumerate(kept)
                     if np.allclose(var.values, k.values, rtol=0, atol=tol)), None)
        if same is None:
            kept.append(var)
        elif var.period and not kept[same].period:
            kept[same] = var
    return kept


def _library(variables: list[Variable]) -> list[tuple[Basis, Callable]]:
    """Candidate shapes φ(v), each with a function of the variables' values → (N, m)."""
    lib: list[tuple[Basis, Callable]] = []
    index = {v.name: i for i, v in enumerate(variables)}
    periodic = [v for v in variables if v.period]
    angles = [v for v in variables if v.kind == "angle"]
    for v in periodic:
        period = float(v.period or 1.0)
        for n in range(1, HARMONICS + 1):
            w = 2 * np.pi * n / period
            lib.append((Basis("harmonic", v.name,
                              f"harmonic {n} of {v.name} (period {period:g} {v.unit})",
                              (f"h{n}_sin", f"h{n}_cos"),
                              (f"sin({2 * n}*pi*{{v}}/{period:g})",
                               f"cos({2 * n}*pi*{{v}}/{period:g})")),
                        _harmonic(index[v.name], w)))
    for v in variables:
        if v.kind == "drift":
            lib.append((Basis("drift", v.name, f"a slow drift in time ({v.name})", ("drift",),
                              ("{v}",)), _linear(index[v.name], 0.0)))
            continue
        mean = float(np.mean(v.values))
        lib.append((Basis("linear", v.name, f"a term linear in {v.name}", ("lin",),
                          (f"({{v}} - {mean:.6g})",)), _linear(index[v.name], mean)))
        lib.append((Basis("quadratic", v.name, f"a quadratic dependence on {v.name}",
                          ("lin", "quad"), (f"({{v}} - {mean:.6g})", f"({{v}} - {mean:.6g})**2")),
                    _quadratic(index[v.name], mean)))
    for a in angles:
        for v in periodic:
            period = float(v.period or 1.0)
            w = 2 * np.pi / period
            lib.append((Basis("angle_harmonic", v.name,
                              f"the angle {a.name} times harmonic 1 of {v.name}",
                              ("ah_sin", "ah_cos"),
                              (f"{{a}}*sin(2*pi*{{v}}/{period:g})",
                               f"{{a}}*cos(2*pi*{{v}}/{period:g})"), a.name),
                        _angle_harmonic(index[a.name], index[v.name], w)))
    return lib


def _harmonic(i: int, w: float) -> Callable:
    return lambda vs: np.column_stack([np.sin(w * vs[i].values), np.cos(w * vs[i].values)])


def _linear(i: int, centre: float) -> Callable:
    return lambda vs: (vs[i].values - centre)[:, None]


def _quadratic(i: int, centre: float) -> Callable:
    return lambda vs: np.column_stack([vs[i].values - centre, (vs[i].values - centre) ** 2])


def _angle_harmonic(ia: int, iv: int, w: float) -> Callable:
    return lambda vs: vs[ia].values[:, None] * np.column_stack(
        [np.sin(w * vs[iv].values), np.cos(w * vs[iv].values)])


def diagnose(result: Result, alpha: float = 0.01) -> Diagnosis:
    """Find where a calibrated model fails and which effect is most likely missing.

    Nothing is solved again: the residuals, their sensitivities and the candidate terms
    are evaluated at the result's estimate on its datasets.

    Parameters
    ----------
    result
        A calibration (:func:`symcal.solve`), or one loaded with
        :meth:`~symcal.result.Result.load`.
    alpha
        Family-wise significance level over all candidates (Bonferroni).

    Returns
    -------
    Diagnosis
    """
    problem = result.problem
    hp = problem.diagnostic
    datasets = result.data
    theta, theta0 = result.theta, result.theta0
    free = np.array([n in result.stages[-1].free for n in problem.parameter_names])
    blocks = [_evaluate(hp, ds, theta0, theta, free) for ds in datasets.values()]
    calibration = blocks[0]
    design, whiteners = _design(blocks, problem, free)
    # the covariance of what the nuisance cannot explain, not of the raw residuals: the
    # comparisons' residuals also carry the estimate's own error, which the refit removes
    design, whiteners = _design(blocks, problem, free, _projected(design))
    variables_by_block = [b.variables for b in blocks]
    keep = {v.name for v in _distinct(calibration.variables) if v.kind != "derived"}
    shapes = _library([v for v in calibration.variables if v.name in keep])
    names = list(hp.hooks)
    candidates, regressors = [], []
    for h, output in enumerate(names):
        if all(not np.any(b.hooks[:, :, h]) for b in blocks):
            continue
        for basis, phi in shapes:
            cols = []
            for b, t, vs in zip(blocks, whiteners, variables_by_block, strict=True):
                f = phi([v for v in vs if v.name in keep])
                x = b.hooks[:, :, h][:, :, None] * f[:, None, :]   # (N, n_q, m)
                cols.append(np.einsum("ab,nbm->nam", t, x).reshape(-1, f.shape[1]))
            candidates.append(Candidate(output, basis))
            regressors.append(np.vstack(cols))
    def local(cand: Candidate) -> bool:
        instance = cand.output.split(".", 1)[0]
        bindings = problem.instances[instance].bindings
        own = {f"{instance}.{k}" for k in bindings} | set(bindings.values())
        return cand.basis.variable in own

    ranked = test_candidates(design, candidates, regressors, alpha, local)
    yaml = {c.label: effect_yaml(problem, c) for c in ranked[:10] if not c.absorbed}
    views = tuple(_views(blocks))
    return Diagnosis(result, views, tuple(ranked), yaml, alpha, len(candidates))


def _projected(design: Design) -> list[np.ndarray]:
    """Per block, the residuals (N × n_q, unwhitened) left after the nuisance is fitted."""
    q, r_factor = np.linalg.qr(design.nuisance)
    keep = np.abs(np.diag(r_factor)) > 1e-10 * max(1.0, float(np.abs(np.diag(r_factor)).max()))
    q = q[:, keep]
    r = design.r - q @ (q.T @ design.r)
    return [r[rows].reshape(-1, unwhiten.shape[1]) @ unwhiten.T
            for _, rows, unwhiten, _, _ in design.blocks]


def _design(blocks: list[_Block], problem: Problem, free: np.ndarray,
            residuals: list[np.ndarray] | None = None) -> tuple[Design, list[np.ndarray]]:
    """Whitened residuals, nuisance and block bookkeeping; the per-observation covariance
    is estimated from ``residuals`` (default: the calibrated residuals themselves)."""
    rows, nuis_rows, block_info, whiteners = [], [], [], []
    n_params = int(free.sum())
    n_offsets = sum(sum(b.offsets) for b in blocks)
    offset_index = 0
    start = 0
    for i, b in enumerate(blocks):
        resid = b.after.copy()
        for k, off in enumerate(b.offsets):
            if off:
                resid[:, k] -= resid[:, k].mean()
        noise = resid if residuals is None else residuals[i]
        t, t_inv = whitening(np.cov(noise, rowvar=False, bias=True).reshape(len(b.names), -1))
        whiteners.append(t)
        n, nq = resid.shape
        rank = t.shape[0]
        rows.append((resid @ t.T).reshape(-1))
        nuis = np.zeros((n, nq, n_params + n_offsets))
        nuis[:, :, :n_params] = b.jac
        for k, off in enumerate(b.offsets):
            if off:
                nuis[:, k, n_params + offset_index] = 1.0
                offset_index += 1
        nuis_rows.append(np.einsum("ab,nbm->nam", t, nuis).reshape(n * rank, -1))
        scales = tuple(DISPLAY_UNITS[u] for u in b.units)
        block_info.append((b.dataset.name, slice(start, start + n * rank), t_inv,
                           tuple(b.names), scales))
        start += n * rank
    free_names = [n for n, f in zip(problem.parameter_names, free, strict=True) if f]
    offsets = [f"offset of {name} on {b.dataset.name}" for b in blocks
               for name, off in zip(b.names, b.offsets, strict=True) if off]
    design = Design(np.concatenate(rows), np.vstack(nuis_rows), tuple(free_names + offsets),
                    tuple(block_info))
    return design, whiteners


def _axis(block: _Block) -> Variable | None:
    """What residuals are plotted against: the declared position reading (``role: axis``)
    that moves most on the dataset, else the time column, else None (the index)."""
    axes = [v for v in block.variables if v.role == "axis"]
    if axes:
        return max(axes, key=lambda v: float(np.std(v.values)))
    return next((v for v in block.variables if v.role == "time"), None)


def _views(blocks: list[_Block]) -> list[ResidualView]:
    views = []
    for b in blocks:
        variables = _distinct(b.variables)
        periodic = [v for v in variables if v.period]
        moving = _axis(b)
        for k, name in enumerate(b.names):
            after = b.after[:, k] - (b.after[:, k].mean() if b.offsets[k] else 0.0)
            before = b.before[:, k] - (b.before[:, k].mean() if b.offsets[k] else 0.0)
            grams = [g for g in (periodogram(after, v, unit_text=f"per period of {v.name}")
                                 for v in periodic) if g is not None]
            best = max(grams, key=lambda g: float(np.max(g.power)), default=None)
            x = moving.values if moving is not None else np.arange(len(after), dtype=float)
            views.append(ResidualView(
                b.dataset.name, name, b.kinds[k], b.units[k], before, after,
                moving.name if moving is not None else "index", x,
                tuple(structure(after, variables)), best))
    return views
