"""`symcal diagnose`: compare the calibrated model with the measurements, show where it
fails, and name the physical effect that is most likely missing (ARCHITECTURE.md).

The flow: a calibration result → evaluate every residual (constraints and reference
comparisons) on every dataset, with its sensitivity to each sensor output (exact, through
hooks) and to the free parameters → where it fails (binned structure, periodograms) →
which effect is missing:

- **calibratable** candidates are tested on what the calibration itself uses, its last
  stage's constraints on the calibration data, with the current parameters projected out;
  only these are suggested, as model extensions that load;
- a candidate that only a reference reveals (significant when the comparisons with a
  reference sensor are included, but absorbed by the current parameters or invisible in
  the constraints) is reported apart: real, but these constraints cannot determine it;
- the model's own approximation is a candidate: where an implicit variant of the problem
  or its models exists beside its files (errors evaluated at the corrected reading), the
  difference it makes is tested like any term;
- every prediction is what re-solving the calibration with the candidate would give
  (a Gauss-Newton refit on the calibration's constraints), on every dataset, held-out ones
  included.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import casadi as ca
import numpy as np

from symcal.analysis.discovery import Basis, Candidate, Design, test_candidates
from symcal.analysis.outliers import Outliers, remedy_yaml
from symcal.analysis.residuals import (
    Binned,
    Left,
    Periodogram,
    Variable,
    periodogram,
    structure,
    what_is_left,
)
from symcal.base.linalg import range_basis, whitening
from symcal.base.numeric import mapped
from symcal.base.units import ANGLE_UNITS, DISPLAY_UNITS
from symcal.calibrate.result import Result
from symcal.data.dataset import Dataset
from symcal.problem.symbolic import Problem
from symcal.revise.effects import effect_yaml
from symcal.revise.variants import Variant, implicit_variant

HARMONICS = 8
#: How many leading candidates get a prediction and a suggestion.
TOP = 10
#: Label of the model's own approximation as a candidate.
APPROXIMATION = "the model's approximation: errors evaluated at the raw readings"


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
    left: tuple[Left, ...] = ()

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
               "periodogram": self.periodogram.to_dict() if self.periodogram else None,
               "left": [a.to_dict(self.scale) for a in self.left]}
        if series:
            doc["series"] = {"x": {"name": self.x_name, "values": self.x.tolist()},
                             "before": (self.before / self.scale).tolist(),
                             "after": (self.after / self.scale).tolist()}
        return doc


@dataclass(frozen=True, eq=False)
class Diagnosis:
    """What `symcal diagnose` found.

    ``candidates`` are ranked on the calibration's own constraints, best first (only
    these are suggested); ``uncalibratable`` are effects that the comparisons with a
    reference reveal but these constraints cannot determine, each with ``needs[label]``
    saying what would (the reference, another constraint, a problem that has one).
    ``variant`` is the implicit variant tested as the model's own approximation.
    ``pointer`` names, when a comparison with a reference is above its noise floor, a
    problem beside this one with more constraints on the same sensors (or "").
    """

    result: Result
    residuals: tuple[ResidualView, ...]
    candidates: tuple[Candidate, ...]
    yaml: dict[str, str]
    alpha: float
    tested: int
    uncalibratable: tuple[Candidate, ...] = ()
    needs: dict[str, str] = field(default_factory=dict)
    variant: Variant | None = None
    own: dict[str, tuple[str, ...]] = field(default_factory=dict)
    pointer: str = ""

    @property
    def outliers(self) -> Outliers | None:
        """The observations the calibration's last stage treats as outliers."""
        return self.result.outliers

    @property
    def outliers_dominate(self) -> bool:
        """Whether outliers dominate the fit: missing effects are then not looked for (a
        robust loss comes first)."""
        return self.outliers is not None and self.outliers.dominate

    @property
    def leads(self) -> tuple[Candidate, ...]:
        """Ranked candidates, one per group of indistinguishable ones, best first."""
        return _leads(self.candidates)

    @property
    def significant(self) -> tuple[Candidate, ...]:
        """The significant calibratable candidates (group leads), best first."""
        return tuple(c for c in self.leads if c.significant)

    def candidate_text(self, cand: Candidate) -> str:
        """The candidate in words."""
        if cand in self.uncalibratable:
            return _uncalibratable_words(cand, self.needs.get(cand.label, ""), self.own)
        return _words(cand, self.alpha, self.tested, self.variant, self.own)

    def _unit(self, cand: Candidate) -> str:
        """The declared unit of a candidate's output."""
        return next((s.unit for s in self.result.problem.signals if s.name == cand.output), "")

    def to_dict(self, series: bool = False) -> dict:
        """Plain data (``--json``; with ``series`` the plotting contract)."""
        ranked = list(self.leads)
        return {
            "problem": self.result.name, "alpha": self.alpha, "tested": self.tested,
            "datasets": [{"name": d.name, "n": d.n} for d in self.result.provenance],
            "residuals": [v.to_dict(series) for v in self.residuals],
            "candidates": [
                {"rank": i + 1, "label": c.label, "output": c.output,
                 "basis": c.basis.description, "delta_rss_share": c.share,
                 "f_stat": c.f_stat, "p_value": c.p_value, "significant": c.significant,
                 "calibratable": True,
                 "coefficient": list(c.coefficient), "coefficient_se": list(c.coefficient_se),
                 "reduction": {k: list(v) for k, v in c.reduction.items()},
                 "predicted": {k: v[1] for k, v in c.reduction.items()},
                 "indistinguishable": list(c.indistinguishable),
                 "mde": None if c.mde is None else c.mde / DISPLAY_UNITS[self._unit(c)],
                 "mde_unit": self._unit(c) or "(internal)",
                 "text": self.candidate_text(c), "yaml": self.yaml.get(c.label, "")}
                for i, c in enumerate(ranked[:20])],
            "uncalibratable": [
                {"label": c.label, "output": c.output, "basis": c.basis.description,
                 "f_stat": c.f_stat, "p_value": c.p_value,
                 "indistinguishable": list(c.indistinguishable),
                 "needs": self.needs.get(c.label, ""), "text": self.candidate_text(c)}
                for c in self.uncalibratable],
            "regressions": [r.to_dict() for r in self.result.regressions],
            "absorbed": [{"label": c.label, "biases": list(c.biases)}
                         for c in self.candidates if c.absorbed and c.biases][:20],
            "outliers": None if self.outliers is None else {
                **self.outliers.to_dict(), "remedy": remedy_yaml(self.outliers)
                if self.outliers.dominate and self.outliers.squared else ""},
            "singular_values": list(self.result.identifiability.singular_values),
            "correlation": self.result.uncertainty.to_dict()["correlation"],
        }


def _leads(candidates: tuple[Candidate, ...]) -> tuple[Candidate, ...]:
    seen: set[str] = set()
    out = []
    for c in candidates:
        if c.absorbed or c.label in seen:
            continue
        out.append(c)
        seen.update(c.indistinguishable)
    return tuple(out)


def _falls(cand: Candidate) -> str:
    biggest = sorted(cand.reduction.items(), key=lambda kv: -(kv[1][0] - kv[1][1]))[:3]
    return "; ".join(f"{k.replace('/', ' ')} std {b:.3g} → {a:.3g}" for k, (b, a) in biggest)


def _group_words(cand: Candidate, own: Mapping[str, tuple[str, ...]]) -> str:
    if not cand.indistinguishable:
        return ""
    shown = "; ".join(cand.indistinguishable[:4])
    more = (f" and {len(cand.indistinguishable) - 4} more"
            if len(cand.indistinguishable) > 4 else "")
    members = [cand.label, *cand.indistinguishable]
    outputs = sorted({m.split(" += ", 1)[0] for m in members})
    instances = sorted({o.split(".", 1)[0] for o in outputs})
    gains = sorted({m.split(" += ", 1)[0] for m in members
                    if " += a term linear in " in m
                    and m.split(" += a term linear in ", 1)[1]
                    in own.get(m.split(".", 1)[0], ())})
    if len(instances) == 1 and len(gains) > 1:
        channels = " and ".join(g.split(".", 1)[1] for g in gains)
        common = (f"the {channels} channels of {instances[0]} disagree in gain (each a term "
                  "linear in its own reading); these data see only the difference")
    elif len(instances) == 1 and len(outputs) > 1:
        common = (f"they all change {instances[0]}'s outputs {', '.join(outputs)} in a way "
                  "these data see only as one effect (the channels disagree in the same "
                  "way)")
    elif len(instances) == 1:
        common = f"they all change {outputs[0]} the same way on these data"
    else:
        common = (f"they change {', '.join(outputs[:4])} in ways the constraints cannot "
                  "tell apart")
    return (f" These data cannot tell it apart from: {shown}{more}: {common}. It is "
            "named by its simplest member; only a reference sensor or another constraint "
            "can separate them.")


def _words(cand: Candidate, alpha: float, tested: int, variant: Variant | None,
           own: Mapping[str, tuple[str, ...]]) -> str:
    verdict = "significant" if cand.significant else "not significant"
    stats = (f"F = {cand.f_stat:.3g}, p = {cand.p_value:.2g}: {verdict} at {alpha:g} after "
             f"allowing for the {tested} candidates tested")
    if cand.basis.kind == "approximation" and variant is not None:
        coef = (f"; the data ask for {cand.coefficient[0]:.2f} ± "
                f"{cand.coefficient_se[0]:.2f} times its effect (1 means exactly it)"
                if cand.coefficient else "")
        return (f"The model evaluates each sensor's error at the raw reading, an "
                f"approximation that leaves a structured residual of order e'·e when the "
                f"errors are not small against their period. {variant.description} explains "
                f"{cand.share:.0%} of what the model cannot yet explain ({_falls(cand)} if "
                f"the calibration is solved again with it){coef}; {stats}. Switch to the "
                "implicit model rather than adding harmonics." + _group_words(cand, own))
    owner = cand.basis.variable.split(".", 1)[0] if "." in cand.basis.variable else None
    instance = cand.output.split(".", 1)[0]
    cross = ""
    if owner is not None and owner != instance:
        cross = (f" {cand.basis.variable} is what another sensor ({owner}) measures: "
                 f"{instance}'s output depends on a quantity it should not see, such as a "
                 "lateral or cross-axis dependence.")
    return (f"{cand.output} varies with {cand.basis.description}, a term its model lacks."
            f"{cross} Adding it would remove {cand.share:.0%} of what the calibration's "
            f"constraints cannot yet explain; solving again with it would give "
            f"{_falls(cand)}; {stats}." + _group_words(cand, own))


def _uncalibratable_words(cand: Candidate, needs: str,
                          own: Mapping[str, tuple[str, ...]]) -> str:
    return (f"{cand.output} varies with {cand.basis.description}: real (F = "
            f"{cand.f_stat:.3g}, p = {cand.p_value:.2g} with the reference comparisons), but "
            f"these constraints cannot determine it — the current parameters absorb it or it "
            f"leaves them unchanged. {needs}" + _group_words(cand, own))


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
            factor = DISPLAY_UNITS[unit]    # a column in its declared unit → internal units
            out.append((col, hp.u[k] * factor if factor != 1.0 else hp.u[k], unit, None,
                        _column_kind(hp, col)))
    for sig in hp.signals:
        derived = ca.depends_on(sig.sx, hooks)
        period = sig.period
        inst, _, name = sig.name.partition(".")
        if inst in hp.instances:
            model = hp.instances[inst].model
            point = model.evaluation_point(name)
            if point is not None and point in model.implicit:
                period = None   # harmonics where the model evaluates its error, not here
            if name in {model.evaluation_point(i) for i in model.inputs}:
                derived = False  # its own evaluation point: a term there stays inside

        out.append((sig.name, sig.sx, sig.unit, period, "derived" if derived else "signal"))
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
            factor = DISPLAY_UNITS[spec.unit]   # declared unit → internal units
            values = np.asarray(ds.columns[col])
            out.append(Variable(col, values * factor if factor != 1.0 else values, spec.unit,
                                None, _column_kind(hp, col), spec.role))
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


def _scale(values: np.ndarray) -> float:
    """A coefficient that makes a term of shape ``values`` about 1 µm (internal mm)."""
    spread = float(np.std(values))
    return 0.001 / spread if spread > 0 else 0.001


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
            shown = period / DISPLAY_UNITS[v.unit]   # the period in the variable's unit
            lib.append((Basis("harmonic", v.name,
                              f"harmonic {n} of {v.name} (period {shown:g} {v.unit})",
                              (f"h{n}_sin", f"h{n}_cos"),
                              (f"sin({2 * n}*pi*{{v}}/{{period}})",
                               f"cos({2 * n}*pi*{{v}}/{{period}})"), order=n, unit=v.unit,
                              scales=(0.0014, 0.0014), period=period),
                        _harmonic(index[v.name], w)))
    for v in variables:
        if v.kind == "drift":
            lib.append((Basis("drift", v.name, f"a slow drift in time ({v.name})", ("drift",),
                              ("{v}",), unit=v.unit, scales=(_scale(v.values),)),
                        _linear(index[v.name], 0.0)))
            continue
        mean = float(np.mean(v.values))
        centred = v.values - mean
        lib.append((Basis("linear", v.name, f"a term linear in {v.name}", ("lin",),
                          ("({v} - {centre})",), unit=v.unit,
                          scales=(_scale(centred),), centre=float(f"{mean:.6g}")),
                    _linear(index[v.name], mean)))
        lib.append((Basis("quadratic", v.name, f"a quadratic dependence on {v.name}",
                          ("lin", "quad"), ("({v} - {centre})", "({v} - {centre})**2"),
                          unit=v.unit, scales=(_scale(centred), _scale(centred ** 2)),
                          centre=float(f"{mean:.6g}")),
                    _quadratic(index[v.name], mean)))
    for a in angles:
        for v in periodic:
            period = float(v.period or 1.0)
            w = 2 * np.pi / period
            scale = _scale(a.values) * 1.4
            lib.append((Basis("angle_harmonic", v.name,
                              f"the angle {a.name} times harmonic 1 of {v.name}",
                              ("ah_sin", "ah_cos"),
                              ("{a}*sin(2*pi*{v}/{period})",
                               "{a}*cos(2*pi*{v}/{period})"), a.name, unit=v.unit,
                              angle_unit=a.unit, scales=(scale, scale), period=period),
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


Raw = Callable[[int], np.ndarray]   # block index -> unwhitened regressor (N, n_q, m)


def diagnose(result: Result, alpha: float = 0.01) -> Diagnosis:
    """Find where a calibrated model fails and which effect is most likely missing.

    Nothing is solved again: the residuals, their sensitivities and the candidate terms
    are evaluated at the result's estimate on its datasets.

    Parameters
    ----------
    result
        A calibration (:func:`symcal.solve`), or one loaded with
        :meth:`~symcal.calibrate.result.Result.load`.
    alpha
        Family-wise significance level over all candidates (Bonferroni).

    Returns
    -------
    Diagnosis
    """
    problem = result.problem
    hp = problem.diagnostic
    data = result.data
    free = np.array([n in result.stages[-1].free for n in problem.parameter_names])
    blocks = [_evaluate(hp, ds, result.theta0, result.theta, free) for ds in data.values()]
    if result.outliers is not None and result.outliers.dominate:
        # outliers first: F-tests for missing effects mean nothing while they dominate
        return Diagnosis(result, tuple(_views(blocks, result)), (), {}, alpha, 0)
    cal = list(data).index(result.problem.fit_dataset)
    own_names = [c.name for c in result.stages[-1].costs]
    own_cols = [blocks[cal].names.index(n) for n in own_names]
    own_blocks = [_subset(blocks[cal], own_cols)]
    own, own_t = _whitened(own_blocks, problem, free)
    full, full_t = _whitened(blocks, problem, free)
    keep = {v.name for v in _distinct(blocks[cal].variables) if v.kind != "derived"}
    raws = _library_regressors(hp, blocks, keep)
    variant = implicit_variant(problem)
    if variant is not None:
        diff = _variant_differences(variant, blocks, data, result.theta)
        raws.append((Candidate("(model)", Basis("approximation", "(model)", APPROXIMATION,
                                                ("approximation",), ())),
                     lambda i, d=diff: d[i]))   # type: ignore[misc]

    def own_regressor(raw: Raw) -> np.ndarray:
        return _whiten(raw(cal)[:, own_cols, :], own_t[0])

    def full_regressor(raw: Raw) -> np.ndarray:
        return np.vstack([_whiten(raw(i), t) for i, t in enumerate(full_t)])

    def local(cand: Candidate) -> bool:
        if cand.output not in hp.hooks:
            return True
        instance = cand.output.split(".", 1)[0]
        bindings = problem.instances[instance].bindings
        return cand.basis.variable.startswith(f"{instance}.") or \
            cand.basis.variable in set(bindings.values())

    candidates = [c for c, _ in raws]
    by_label = {c.label: raw for c, raw in raws}
    ranked = test_candidates(own, candidates, [own_regressor(r) for _, r in raws], alpha,
                             local)
    leads = [c for c in _leads(tuple(ranked)) if c.significant][:TOP]
    for cand in leads:
        _predict(cand, own, own_regressor(by_label[cand.label]), blocks, free,
                 by_label[cand.label])
    uncal, needs = _uncalibratable(problem, full, raws, full_regressor, leads, ranked, alpha,
                                   local)
    yaml = {c.label: (variant.overlay(Path(problem.path), f"{problem.name}_implicit",
                                      Path(problem.path).parent)
                      if c.basis.kind == "approximation" and variant is not None
                      else effect_yaml(problem, c))
            for c in leads}
    own_inputs = {name: (*(f"{name}.{k}" for k in inst.bindings), *inst.bindings.values())
                  for name, inst in problem.instances.items()}
    above = any(s.kind == "comparison" and s.noise is not None and s.noise.verdict == "above"
                for s in result.statistics)
    return Diagnosis(result, tuple(_views(blocks, result)), tuple(ranked), yaml, alpha,
                     len(candidates), tuple(uncal), needs, variant, own_inputs,
                     _better_problem(problem) if above else "")


def _library_regressors(hp: Problem, blocks: list[_Block], keep: set[str]
                        ) -> list[tuple[Candidate, Raw]]:
    """Every (sensor output × shape) candidate with its unwhitened regressor per block."""
    cal = next(i for i, b in enumerate(blocks) if b.dataset.name == hp.fit_dataset)
    shapes = _library([v for v in blocks[cal].variables if v.name in keep])
    out: list[tuple[Candidate, Raw]] = []
    for h, output in enumerate(hp.hooks):
        if all(not np.any(b.hooks[:, :, h]) for b in blocks):
            continue
        for basis, phi in shapes:
            def raw(i: int, h: int = h, phi: Callable = phi) -> np.ndarray:
                b = blocks[i]
                f = phi([v for v in b.variables if v.name in keep])
                return b.hooks[:, :, h][:, :, None] * f[:, None, :]   # (N, n_q, m)

            out.append((Candidate(output, basis), raw))
    return out


def _variant_differences(variant: Variant, blocks: list[_Block], data: Mapping[str, Dataset],
                         theta: np.ndarray) -> list[np.ndarray]:
    """What the implicit variant changes in every residual at ``theta`` (N, n_q, 1): adding
    1 times it is exactly the switch to the variant."""
    vp = variant.problem
    comparisons = {c.name: c for c in vp.comparisons}
    out = []
    for b in blocks:
        exprs = [vp.constraint(n).sx if kind == "constraint"
                 else comparisons[n].estimate - comparisons[n].reference
                 for n, kind in zip(b.names, b.kinds, strict=True)]
        fn = mapped(vp.theta, vp.u, [ca.vertcat(*exprs)], "variant")
        values = fn(theta, data[b.dataset.name].matrix(vp.columns))[0]
        out.append((values - b.after)[:, :, None])
    return out


def _whiten(x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Whitened rows of a regressor (N, n_q, m) → (N·rank, m)."""
    return np.einsum("ab,nbm->nam", t, x).reshape(-1, x.shape[2])


def _subset(block: _Block, cols: list[int]) -> _Block:
    """A block restricted to the quantities ``cols`` (e.g. the calibration's constraints)."""
    return replace(block, names=[block.names[k] for k in cols],
                   kinds=[block.kinds[k] for k in cols], units=[block.units[k] for k in cols],
                   offsets=[block.offsets[k] for k in cols], before=block.before[:, cols],
                   after=block.after[:, cols], hooks=block.hooks[:, cols, :],
                   jac=block.jac[:, cols, :])


def _whitened(blocks: list[_Block], problem: Problem, free: np.ndarray
              ) -> tuple[Design, list[np.ndarray]]:
    """The design of ``blocks`` whitened by the covariance of what the current parameters
    cannot explain (not of the raw residuals: comparisons also carry the estimate's own
    error, which a refit removes)."""
    design, _ = _design(blocks, problem, free)
    return _design(blocks, problem, free, _projected(design))


def _predict(cand: Candidate, own: Design, x_own: np.ndarray, blocks: list[_Block],
             free: np.ndarray, raw: Raw) -> None:
    """What solving the calibration again with ``cand`` would give on every dataset: a
    Gauss-Newton refit of the current parameters and the candidate's coefficients on the
    calibration's constraints, applied to every residual; fills ``reduction`` (std now →
    predicted, display units) and the coefficients of the term to add (regressors are the
    change a term of coefficient 1 makes) with standard errors."""
    a = np.column_stack([own.nuisance, x_own])
    delta, *_ = np.linalg.lstsq(a, own.r, rcond=None)
    m = x_own.shape[1]
    rows = len(own.r)
    rank = range_basis(a).shape[1]
    s2 = float(np.sum((own.r - a @ delta) ** 2)) / max(rows - rank, 1)
    cov = s2 * np.linalg.pinv(a.T @ a)
    # the fit explains the residual as X·δ; the term to add to the model is -δ
    cand.coefficient = tuple(-float(v) for v in delta[-m:])
    cand.coefficient_se = tuple(float(np.sqrt(max(cov[k, k], 0.0)))
                                for k in range(len(delta) - m, len(delta)))
    n_params = int(free.sum())
    out: dict[str, tuple[float, float]] = {}
    for i, b in enumerate(blocks):
        change = b.jac @ delta[:n_params] + raw(i) @ delta[-m:]
        predicted = b.after - change
        for k, name in enumerate(b.names):
            now, new = b.after[:, k], predicted[:, k]
            if b.offsets[k]:
                now, new = now - now.mean(), new - new.mean()
            scale = DISPLAY_UNITS[b.units[k]]
            out[f"{b.dataset.name}/{name}"] = (float(np.std(now)) / scale,
                                               float(np.std(new)) / scale)
    cand.reduction = out


def _uncalibratable(
    problem: Problem, full: Design, raws: list[tuple[Candidate, Raw]],
    full_regressor: Callable[[Raw], np.ndarray], leads: list[Candidate],
    ranked: list[Candidate], alpha: float, local: Callable[[Candidate], bool],
) -> tuple[list[Candidate], dict[str, str]]:
    """Effects the comparisons with a reference reveal, once the calibratable leads are
    allowed for, that the calibration's constraints do not: tested on every residual of
    every dataset, reported apart with what would determine them."""
    if not problem.comparisons:
        return [], {}
    own_significant = {c.label for c in ranked if c.significant}
    for c in ranked:
        if c.significant:
            own_significant.update(c.indistinguishable)
    by_label = {c.label: raw for c, raw in raws}
    extra = [full_regressor(by_label[c.label]) for c in leads]
    nuisance = np.column_stack([full.nuisance, *extra]) if extra else full.nuisance
    names = tuple(f"{c.label} ({col})" for c in leads for col in c.basis.columns)
    design = Design(full.r, nuisance, full.nuisance_names + names, full.blocks)
    others = [Candidate(c.output, c.basis) for c, _ in raws
              if c.label not in own_significant and c.basis.kind != "approximation"]
    tested = test_candidates(design, others,
                             [full_regressor(by_label[c.label]) for c in others], alpha, local)
    found = [c for c in _leads(tuple(tested)) if c.significant][:3]
    pointer = _better_problem(problem) if found else ""
    needs = {c.label: ("It shows only against the reference sensor: calibrate it with the "
                       "reference, or add a constraint that sees it"
                       + (f"; {pointer}" if pointer else "") + ".")
             for c in found}
    return found, needs


def _better_problem(problem: Problem) -> str:
    """A problem beside this one with more constraints on the same sensors, in words."""
    here = Path(problem.path).resolve()
    mine = {c.name for c in problem.constraints}
    best: tuple[int, str] | None = None
    for path in sorted(here.parent.glob("*.yaml")):
        if path.resolve() == here:
            continue
        try:
            from symcal.problem.build import load_problem

            other = load_problem(path)
        except Exception:  # noqa: BLE001 - any file that does not load is not a pointer
            continue
        theirs = {c.name for c in other.constraints}
        if mine < theirs and set(problem.instances) <= set(other.instances) \
                and not other.implicit:
            added = sorted(theirs - mine)
            text = (f"{path.name} in the same folder adds the constraints "
                    f"{', '.join(added)} on the same sensors and can determine it")
            if best is None or len(added) > best[0]:
                best = (len(added), text)
    return best[1] if best else ""


def _projected(design: Design) -> list[np.ndarray]:
    """Per block, the residuals (N × n_q, unwhitened) left after the nuisance is fitted."""
    q = range_basis(design.nuisance)
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


def _floor_variance(result: Result, dataset: str, name: str) -> float | None:
    """The variance a residual has at its noise floor (its floor², times its expected χ²
    over its observations: the fit's degrees of freedom and the estimate's share), None
    when it is not above its floor."""
    stats = next((s for s in result.statistics if (s.dataset, s.name) == (dataset, name)),
                 None)
    test = None if stats is None else stats.noise
    if test is None or test.verdict != "above" or test.floor is None or not test.dof:
        return None
    return test.floor**2 * test.dof / max(stats.n, 1)     # type: ignore[union-attr]


def _views(blocks: list[_Block], result: Result) -> list[ResidualView]:
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
            floor = _floor_variance(result, b.dataset.name, name)
            left = () if floor is None else tuple(what_is_left(
                after, [v for v in variables if v.name not in (name,)], floor))
            views.append(ResidualView(
                b.dataset.name, name, b.kinds[k], b.units[k], before, after,
                moving.name if moving is not None else "index", x,
                tuple(structure(after, variables)), best, left))
    return views
