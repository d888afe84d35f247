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

import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import casadi as ca
import numpy as np

from symcal.analysis.discovery import (
    STANDALONE,
    Basis,
    Candidate,
    Design,
    absorbed,
    gauge_fixes,
    redundant_columns,
    test_candidates,
    unexplained_share,
)
from symcal.analysis.noise_bias import NOISE_BIAS, noise_shift
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
from symcal.base.digits import estimate_text
from symcal.base.numeric import mapped
from symcal.base.units import DISPLAY_UNITS, internal_unit
from symcal.calibrate.result import Result
from symcal.calibrate.solve import stage_fit
from symcal.data.dataset import Dataset
from symcal.problem.symbolic import Problem
from symcal.revise.blocks import Block, distinct, evaluate
from symcal.revise.centres import NEARLY, centred_product
from symcal.revise.effects import coefficient_names, effect_yaml
from symcal.revise.library import (
    Entry,
    Raw,
    Space,
    constant_entries,
    fixed_entries,
    latency_entries,
    output_entries,
    outside_entries,
    zero_entries,
)
from symcal.revise.library import (
    own_names as own_names_of,
)
from symcal.revise.reliability import CURVES, mark_two_level, mark_unseen, two_levels
from symcal.revise.variants import Variant, implicit_variant
from symcal.revise.whitened import Sizes, design, predict, predicted_spreads, whiten

#: How many leading candidates get a prediction and a suggestion.
TOP = 10
#: How many members of a group (the lead included) get a prediction: those `improve`
#: may try.
GROUP = 4
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
    ``spaces`` says, per instance, which space of candidates was searched;
    ``gauge_fixes`` names the fixed parameters that fix a gauge (never tested as "off",
    and no candidate that re-opens one is proposed: :attr:`reopened`).  ``together``
    predicts, as a candidate's ``reduction`` and ``scatter``, what solving again with
    several candidates at once would give (their labels; None where none were tested).
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
    spaces: tuple[str, ...] = ()
    gauge_fixes: dict[str, str] = field(default_factory=dict)
    together: Callable[[Sequence[str]], tuple[Sizes, Sizes]] | None = field(
        default=None, repr=False)
    # how to test a coupling what is left points at but no search space holds
    unsearched: tuple[str, ...] = ()
    # where no candidate of the search spaces is significant: the couplings outside them
    # that are (:func:`symcal.revise.library.outside_entries`), and how to test each
    outside: tuple[Candidate, ...] = ()
    outside_words: dict[str, str] = field(default_factory=dict)

    @cached_property
    def _noise(self) -> tuple[tuple[tuple[str, float, float], ...], str]:
        return _noise_bias(self.result, _in_memory(self.result.data))

    @property
    def noise_bias(self) -> tuple[tuple[str, float, float], ...]:
        """Each free parameter's expected shift by the readings' own noise, second order
        (:mod:`symcal.analysis.noise_bias`): (name, shift in its unit, shift in its SE);
        empty where it is not computed (:attr:`noise_bias_reason` says why).  Computed
        when first asked (the verdict of the last round, not every trial's)."""
        return self._noise[0]

    @property
    def noise_bias_reason(self) -> str:
        """Why :attr:`noise_bias` is empty (``""``: it is not)."""
        return self._noise[1]

    @property
    def biased_by_noise(self) -> tuple[tuple[str, float, float], ...]:
        """The parameters whose shift by the readings' noise reaches
        :data:`~symcal.analysis.noise_bias.NOISE_BIAS` standard errors, largest first."""
        return tuple(sorted((b for b in self.noise_bias if abs(b[2]) >= NOISE_BIAS),
                            key=lambda b: -abs(b[2])))

    @property
    def reopened(self) -> tuple[Candidate, ...]:
        """Candidates never proposed: each would re-open a gauge (a direction the user, or
        the problem, fixed because no data can determine it)."""
        return tuple(c for c in self.candidates if c.reopens)

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
        return _words(cand, self.alpha, self.tested, self.variant, self.own) + \
            _reference_words(cand, self.result)

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
                 "reduction_std": {k: list(v) for k, v in c.scatter.items()},
                 "predicted": {k: v[1] for k, v in c.reduction.items()},
                 "indistinguishable": list(c.indistinguishable),
                 **_mde_fields(self.result, c),
                 "text": self.candidate_text(c), "yaml": self.yaml.get(c.label, "")}
                for i, c in enumerate(ranked[:20])],
            "uncalibratable": [
                {"label": c.label, "output": c.output, "basis": c.basis.description,
                 "f_stat": c.f_stat, "p_value": c.p_value,
                 "indistinguishable": list(c.indistinguishable),
                 "needs": self.needs.get(c.label, ""), "text": self.candidate_text(c)}
                for c in self.uncalibratable],
            "regressions": [r.to_dict() for r in self.result.regressions],
            "searched": list(self.spaces),
            "reopened": [{"label": c.label, "reason": c.reopens} for c in self.reopened],
            "gauge_fixes": dict(self.gauge_fixes),
            "absorbed": [{"label": c.label, "biases": list(c.biases)}
                         for c in self.candidates if c.absorbed and c.biases][:20],
            "nearly_absorbed": [
                {"label": c.label, "moves": {name: v for name, v in c.unseen},
                 **_mde_fields(self.result, c)}
                for c in self.candidates if c.unseen and not c.absorbed][:20],
            "outliers": None if self.outliers is None else {
                **self.outliers.to_dict(), "remedy": remedy_yaml(self.outliers)
                if self.outliers.dominate and self.outliers.squared else ""},
            "singular_values": list(self.result.identifiability.singular_values),
            "correlation": self.result.uncertainty.to_dict()["correlation"],
            "noise_bias": self.noise_bias_dict(),
        }

    def noise_bias_dict(self) -> dict:
        """``{"level_se": ..., "parameters": [{"name", "shift", "shift_se", "unit"}],
        "not_computed": ...}``: every free parameter's shift by the readings' own noise,
        the level from which the verdict names it, and why it was not computed (null
        where it was)."""
        return {"level_se": NOISE_BIAS, "parameters": [
            {"name": n, "shift": b, "shift_se": z, "unit": self.result.params[n].unit}
            for n, b, z in self.noise_bias], "not_computed": self.noise_bias_reason or None}


def _leads(candidates: tuple[Candidate, ...]) -> tuple[Candidate, ...]:
    seen: set[str] = set()
    out = []
    for c in candidates:
        if c.absorbed or c.reopens or c.label in seen:
            continue
        out.append(c)
        seen.update(c.indistinguishable)
    return tuple(out)


def _read_by_output(problem: Problem) -> dict[str, tuple[str, ...]]:
    """Each sensor output's own readings: the instance's inputs bound to a column that
    its expression reads (a magnetometer's Bx reads mx, not mz: a term linear in mz on
    Bx is a coupling, not a disagreement in gain)."""
    index = {c: k for k, c in enumerate(problem.columns)}
    out: dict[str, tuple[str, ...]] = {}
    for sig in problem.signals:
        inst, _, local = sig.name.partition(".")
        instance = problem.instances.get(inst)
        if instance is None or local not in instance.model.outputs:
            continue
        read = [(f"{inst}.{k}", text) for k, text in instance.bindings.items()
                if text in index and ca.depends_on(sig.sx, problem.u[index[text]])]
        if read:        # else (inputs bound to expressions) the instance's own stand
            out[sig.name] = tuple(n for pair in read for n in pair)
    return out


def _falls(cand: Candidate) -> str:
    biggest = sorted(cand.reduction.items(), key=lambda kv: -(kv[1][0] - kv[1][1]))[:3]
    return "; ".join(f"{k.replace('/', ' ')} RMS {b:.3g} → {a:.3g}" for k, (b, a) in biggest)


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
                    in own.get(m.split(" += ", 1)[0], own.get(m.split(".", 1)[0], ()))})
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
    if cand.basis.kind in ("fixed", "constant", "latency", "zero"):
        return _value_words(cand, stats) + _group_words(cand, own)
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


def references(problem: Problem) -> set[str]:
    """The instances whose every parameter is fixed: the sensors the problem trusts."""
    found: dict[str, list[bool]] = {}
    for p in problem.parameters:
        inst, dot, _ = p.name.partition(".")
        if dot and inst in problem.instances:
            found.setdefault(inst, []).append(p.fixed)
    return {inst for inst, fixed in found.items() if all(fixed)}


def changed_instances(cand: Candidate) -> set[str]:
    """The instances a candidate changes: its output's; a latency's lagging instance; the
    instance of a fixed parameter freed or of a model constant made a parameter (none for
    the problem's own constants and the model's approximation)."""
    basis = cand.basis
    if basis.kind == "latency":
        return {basis.variable}
    if basis.kind == "zero":
        return set(basis.targets)
    if basis.kind in ("fixed", "constant"):
        return {t.split(".", 1)[0] for t in basis.targets if "." in t}
    if basis.kind in STANDALONE:
        return set()
    return {cand.output.split(".", 1)[0]}


def on_reference(cand: Candidate, problem: Problem) -> str | None:
    """The reference (:func:`references`) the candidate changes, or None."""
    found = sorted(changed_instances(cand) & references(problem))
    return found[0] if found else None


def _reference_words(cand: Candidate, result: Result) -> str:
    """A warning where the candidate changes a sensor whose every parameter is fixed: the
    problem's reference (a certified load cell).  A term there (or its fixed parameter
    freed, its constant or its clock changed) says the reference reads wrong, and its
    shape in the reference's reading is often the same effect in a calibrated sensor's
    (a stack of load cells carries one force): that one leaves the reference as
    certified and puts the other sensors' parameters elsewhere."""
    instance = on_reference(cand, result.problem)
    if instance is None:
        return ""
    return (f" Every parameter of {instance} is fixed: the problem trusts it as its "
            f"reference, and this candidate says the reference itself reads wrong. Where "
            f"a calibrated sensor's candidate explains about as much, prefer it (symcal "
            f"improve compares them on their BIC), and check {instance} against its own "
            f"calibration before changing it.")


def _value_words(cand: Candidate, stats: str) -> str:
    """A value the model takes as known that the data say is off: a fixed parameter, a
    constant, the delay between a sensor's clock and the others', or a reading's zero."""
    basis = cand.basis
    asks = ""
    if cand.coefficient:
        c, se = cand.coefficient[0], cand.coefficient_se[0]
        if basis.kind == "latency":
            asks = (f": the data ask for a delay of {c * 1e3:.4g} ± {se * 1e3:.2g} ms "
                    "(readings stamped that much late)")
        elif basis.kind == "zero":
            size = DISPLAY_UNITS[basis.unit]
            asks = (f": the data say its readings are {-c / size:+.4g} ± {se / size:.2g} "
                    f"{basis.unit} off (the model would read {basis.variable} "
                    f"{'+' if c >= 0 else '-'} {abs(c) / size:.4g} {basis.unit})")
        else:
            size = 1.0 if basis.kind == "fixed" else DISPLAY_UNITS[basis.unit]
            value, change = basis.centre / size, c / size
            rel = (f" ({100 * change / value:+.3g} % ± {100 * se / size / abs(value):.2g} %)"
                   if value else "")
            asks = (f": the data ask for {estimate_text(value + change, se / size)} ± "
                    f"{se / size:.2g} "
                    f"{basis.unit} instead of {value:.6g}, a change of {change:+.3g}{rel}")
    what = {"fixed": "Freeing it", "constant": "Making it a parameter",
            "latency": "Allowing for the delay", "zero": "Allowing for it"}[basis.kind]
    # a sentence starts with a capital, a name keeps its own ("orf's c_quad_dp ...")
    text = basis.description
    if text.startswith("the "):
        text = "T" + text[1:]
    return (f"{text}{asks}. {what} would "
            f"remove {cand.share:.0%} of what the calibration's constraints cannot yet "
            f"explain; solving again with it would give {_falls(cand)}; {stats}.")


def _uncalibratable_words(cand: Candidate, needs: str,
                          own: Mapping[str, tuple[str, ...]]) -> str:
    return (f"{cand.output} varies with {cand.basis.description}: real (F = "
            f"{cand.f_stat:.3g}, p = {cand.p_value:.2g} with the reference comparisons), but "
            f"these constraints cannot determine it — the current parameters absorb it or it "
            f"leaves them unchanged. {needs}" + _group_words(cand, own))


def diagnose(result: Result, alpha: float = 0.01, *, report: bool = True) -> Diagnosis:
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
    report
        Whether to find everything the report shows: each residual along every variable
        (binned structure, periodograms, what is left) and the effects only a reference
        reveals; ``False`` tests the calibratable candidates only (what the improve
        loop's rounds need).

    Returns
    -------
    Diagnosis
    """
    problem = result.problem
    data = _in_memory(result.data)
    free = np.array([n in result.stages[-1].free for n in problem.parameter_names])
    blocks = [evaluate(problem, ds, result.theta0, result.theta, free)
              for ds in data.values()]
    if result.outliers is not None and result.outliers.dominate:
        # outliers first: F-tests for missing effects mean nothing while they dominate
        return Diagnosis(result, tuple(_views(blocks, result)) if report else (), (), {},
                         alpha, 0)
    fit = list(data).index(problem.fit_dataset)
    own_names = [c.name for c in result.stages[-1].costs]
    own_cols = [blocks[fit].names.index(n) for n in own_names]
    own, own_t = design([blocks[fit].subset(own_cols)], problem, free)

    def own_regressor(raw: Raw) -> np.ndarray:
        return whiten(raw(fit)[:, own_cols, :], own_t[0])

    fixed = [n for n, f in zip(problem.parameter_names, free, strict=True) if not f]
    fixed_columns = {name: whiten(blocks[fit].jac_fixed[:, own_cols, k:k + 1], own_t[0])[:, 0]
                     for k, name in enumerate(fixed)}
    fixes = gauge_fixes(own, fixed_columns)
    entries, found = output_entries(problem, blocks, fit)
    entries += fixed_entries(problem, blocks, fit, free, set(fixes))
    entries += latency_entries(problem, blocks, fit, found)
    entries += constant_entries(problem, blocks, fit)
    entries += zero_entries(problem, blocks, fit, found, free)
    variant = implicit_variant(problem)
    if variant is not None:
        diff = _variant_differences(variant, blocks, data, result.theta)
        entries.append(Entry(Candidate("(model)", Basis(
            "approximation", "(model)", APPROXIMATION, ("approximation",), ())),
            lambda i, d=diff: d[i]))   # type: ignore[misc]

    def local(cand: Candidate) -> bool:
        if cand.output not in problem.diagnostic.hooks or cand.basis.kind in ("gain",
                                                                              "coupling"):
            return True     # not a sensor's term, its own gain or a share of its output
        instance = cand.output.split(".", 1)[0]
        return cand.basis.variable in own_names_of(problem, instance)

    entries = [centred_product(_without_redundant(e, own, own_regressor), own,
                               own_regressor, blocks[fit]) for e in entries]
    candidates = [e.candidate for e in entries]
    by_label = {e.candidate.label: e for e in entries}
    gauge_columns = {name: fixed_columns[name] for name in fixes}
    levels: dict[str, bool] = {}

    def flat(cand: Candidate) -> bool:     # a curve in a variable held at two values
        name = cand.basis.variable
        if cand.basis.kind not in CURVES:
            return False
        if name not in levels:
            levels[name] = two_levels(blocks[fit].values(name))
        return levels[name]

    ranked = test_candidates(
        own, candidates, [own_regressor(e.raw) for e in entries], alpha, local,
        [None if e.extra is None else own_regressor(e.extra) for e in entries],
        gauge_columns, lambda c: on_reference(c, problem) is not None, flat)
    have = set(problem.parameter_names)

    def restates(cand: Candidate) -> bool:
        """A term linear in its own reading (a gain), or one an earlier round added,
        tested again (its sensor already has its coefficients: what it absorbs is what
        calibrating them means); the zero of a reading only sensors without a free
        parameter read (the problem trusts them, as it trusts their gain: a bath
        thermometer's zero "would move th.R25 779 SE" on every clean run)."""
        if cand.basis.kind == "linear" and cand.output in problem.diagnostic.hooks \
                and local(cand):
            return True
        if cand.basis.kind == "zero" and not any(
                p.name.split(".", 1)[0] in cand.basis.targets and not p.fixed
                for p in problem.parameters):
            return True
        inst = cand.output.split(".", 1)[0]
        return any(all(f"{inst}.{n}" in have for n in names)
                   for names in coefficient_names(cand))

    def suspected(cand: Candidate) -> bool:    # a coupling the user asked about
        if cand.output not in problem.diagnostic.hooks or local(cand):
            return False
        space = found.get(cand.output.split(".", 1)[0])
        return space is not None and not space.origin.startswith("default")

    def kept(cand: Candidate) -> frozenset[str]:
        """The coefficients earlier rounds added to the candidate's sensor (named as the
        library names a term's coefficients)."""
        inst = cand.output.split(".", 1)[0] + "."
        return frozenset(n for n in have if n.startswith(inst)
                         and COEFFICIENT.match(n[len(inst):]) is not None)

    physical = [n for n, f in zip(problem.parameter_names, free, strict=True) if f]
    mark_unseen(own, entries, ranked, own_regressor, alpha / max(len(candidates), 1),
                physical, restates, suspected, kept)
    mark_two_level(ranked, physical, blocks[fit].values)
    leads = [c for c in _leads(tuple(ranked)) if c.significant][:TOP]
    outside: tuple[Candidate, ...] = ()
    tested_outside: set[tuple[str, str]] = set()
    if not leads:
        outside, tested_outside = _outside(problem, blocks, fit, found, own, own_regressor,
                                           alpha, len(candidates), gauge_columns)
    members = {label for c in leads for label in c.indistinguishable[:GROUP - 1]}
    for cand in [*leads, *(c for c in ranked if c.label in members)]:
        predict(cand, own, own_regressor(by_label[cand.label].raw), blocks, free,
                by_label[cand.label].raw)

    def together(labels: Sequence[str]) -> tuple[Sizes, Sizes]:
        parts = [by_label[label].raw for label in labels]

        def raw(i: int) -> np.ndarray:
            return np.concatenate([part(i) for part in parts], axis=-1)

        return predicted_spreads(own, own_regressor(raw), blocks, free, raw)[2]

    uncal: list[Candidate] = []
    needs: dict[str, str] = {}
    if report:
        full, full_t = design(blocks, problem, free)

        def full_regressor(raw: Raw) -> np.ndarray:
            return np.vstack([whiten(raw(i), t) for i, t in enumerate(full_t)])

        uncal, needs = _uncalibratable(problem, full, entries, full_regressor, leads,
                                       ranked, alpha, local)
    yaml = {c.label: (variant.overlay(Path(problem.path), f"{problem.name}_implicit",
                                      Path(problem.path).parent)
                      if c.basis.kind == "approximation" and variant is not None
                      else effect_yaml(problem, c))
            for c in leads}
    own_inputs = {name: (*(f"{name}.{k}" for k in inst.bindings), *inst.bindings.values())
                  for name, inst in problem.instances.items()}
    own_inputs.update(_read_by_output(problem))
    above = any(s.kind == "comparison" and s.noise is not None and s.noise.verdict == "above"
                for s in result.statistics)
    views = tuple(_views(blocks, result)) if report else ()
    return Diagnosis(result, views, tuple(ranked),
                     yaml, alpha,
                     len(candidates), tuple(uncal), needs, variant, own_inputs,
                     _better_problem(problem) if above else "",
                     tuple(sp.describe() for sp in found.values()), dict(fixes),
                     together, unsearched(problem, found, views, tested_outside,
                                          _reached(problem, blocks) if views else None,
                                          leads[0] if leads else None),
                     outside,
                     {c.label: outside_words(problem, found, c) for c in outside})


def _noise_bias(result: Result, data: Mapping[str, Dataset]
                ) -> tuple[tuple[tuple[str, float, float], ...], str]:
    """Each free parameter's shift by the readings' noise on the fitted dataset
    (:func:`~symcal.analysis.noise_bias.noise_shift`): (name, shift, shift / SE), and
    why there are none where it is not computed.  Not for a robust loss (its weights
    depend on the residuals, which the expansion leaves out: the shift predicted for a
    Cauchy loss was 2.8 times what repeated fits averaged) nor where an earlier stage
    estimated parameters the last one holds (their own shifts carry through it: the
    sign came out wrong)."""
    problem, last = result.problem, result.stages[-1]
    if problem.fit_dataset not in data:
        return (), "the fitted dataset is not at hand"
    if last.outliers is not None and not last.outliers.squared:
        return (), "a robust loss weighs the rows by their residuals"
    earlier = {n for st in result.stages[:-1] for n in st.free} - set(last.free)
    if earlier:
        return (), (f"an earlier stage estimated {', '.join(sorted(earlier)[:3])}, which "
                    "the last one holds")
    fit = stage_fit(problem, data, result.theta, last)
    names = [n for n, f in zip(problem.parameter_names, fit.free, strict=True) if f]
    scales = np.array([p.scale for p in problem.parameters])[np.asarray(fit.free, bool)]
    shift = noise_shift(problem, data[problem.fit_dataset], result.theta, fit, scales)
    if isinstance(shift, str):
        return (), shift
    out = []
    for name, b in zip(names, shift, strict=True):
        se = result.params[name].se
        if se:
            out.append((name, float(b), float(b) / se))
    return tuple(out), ""


def _outside(problem: Problem, blocks: list[Block], fit: int, found: Mapping[str, Space],
             own: Design, own_regressor: Callable[[Raw], np.ndarray], alpha: float,
             tested_in: int, gauges: Mapping[str, np.ndarray]
             ) -> tuple[tuple[Candidate, ...], set[tuple[str, str]]]:
    """The couplings outside every search space, tested apart from the spaces' candidates
    (which they may not lead) at the level each would have among them: ``alpha`` over
    the ``tested_in`` candidates and these (Bonferroni), so that clean data raise an
    alarm of either kind at about ``alpha``.  The significant ones (group leads), and the
    (instance, column) pairs tested."""
    entries = [_without_redundant(e, own, own_regressor)
               for e in outside_entries(problem, blocks, fit, found)]
    tested = {(e.candidate.output.split(".", 1)[0], e.candidate.basis.variable)
              for e in entries}
    if not entries:
        return (), tested
    share = alpha * len(entries) / (tested_in + len(entries))
    ranked = test_candidates(own, [e.candidate for e in entries],
                             [own_regressor(e.raw) for e in entries], share, None,
                             [None] * len(entries), gauges)
    return tuple(c for c in _leads(tuple(ranked)) if c.significant), tested


def outside_words(problem: Problem, found: Mapping[str, Space], cand: Candidate) -> str:
    """How to test an outside coupling in the loop: the instance's ``candidates:
    variables`` with the column beside the readings its default space holds."""
    instance = cand.output.split(".", 1)[0]
    column = cand.basis.variable
    inst = problem.instances[instance]
    twice = {f"{instance}.{k}" for k, text in inst.bindings.items()
             if text in problem.column_specs}       # the column's name says it
    names = [n for n in found[instance].variables if n not in twice] + [column]
    return (f"{cand.label} is significant (p = {cand.p_value:.2g}; the couplings no "
            "search space holds are tested apart, each at the level of a candidate among "
            "the spaces') but is in no search "
            f"space: {column} is read by another sensor; to test it in the loop, add "
            f"`candidates: {{variables: [{', '.join(names)}]}}` to the instance {instance} "
            f"in the problem file (its own readings, time and state columns, and {column}) "
            "and run again")


def _reached(problem: Problem, blocks: list[Block]) -> dict[tuple[str, str], set[str]]:
    """Per (dataset, residual), the instances a term on one of their outputs changes."""
    hooks = list(problem.diagnostic.hooks)      # in the order of the blocks' hooks
    out: dict[tuple[str, str], set[str]] = {}
    for b in blocks:
        for k, name in enumerate(b.names):
            out[(b.dataset.name, name)] = {
                output.split(".", 1)[0] for h, output in enumerate(hooks)
                if np.any(b.hooks[:, k, h])}
    return out


def unsearched(problem: Problem, found: Mapping[str, Space],
               views: Sequence[ResidualView],
               tested: set[tuple[str, str]] | None = None,
               reached: Mapping[tuple[str, str], set[str]] | None = None,
               lead: Candidate | None = None) -> tuple[str, ...]:
    """Where what is left of a residual lies most along a sensor's own reading that no
    other sensor's search space holds: a coupling of that reading into another sensor
    (crosstalk from a current channel into a voltage channel) is not tested, unless the
    outside family tested it (``tested``: instance, column), and only into a sensor
    whose outputs that residual reads (``reached``: :func:`_reached`; a coupling into a
    sensor the residual does not read cannot explain it); the sentence says how to test
    it, and where a significant candidate (``lead``) removes most of what the constraints
    cannot yet explain, that it comes first (what is left lies along every variable that
    moves with the effect: a new user's orifice rig, its pressure's zero 97 % of it, was
    pointed at couplings of the reference's flow)."""
    column_of: dict[str, str] = {}      # a column an instance reads, by either name
    readers: dict[str, list[str]] = {}  # the instances that read each column
    for name, inst in problem.instances.items():
        for key, text in inst.bindings.items():
            if text in problem.column_specs:
                column_of[text] = column_of[f"{name}.{key}"] = text
                if name not in readers.setdefault(text, []):
                    readers[text].append(name)
    found_in: dict[tuple[str, tuple[str, ...], tuple[str, ...]], list[str]] = {}
    for v in views:
        left = getattr(v, "left", ())
        for var in left[0].variables if left else ():
            if var not in column_of:
                continue
            column = column_of[var]
            who = readers[column]
            into = None if reached is None else reached.get((v.dataset, v.name))
            others = tuple(n for n, sp in found.items() if n not in who and sp.kinds != ()
                           and column not in sp.variables
                           and (n, column) not in (tested or set())
                           and (into is None or n in into))
            if others:
                names = found_in.setdefault((column, tuple(who), others), [])
                if v.name not in names:
                    names.append(v.name)
    first = ""
    if lead is not None and lead.share >= MOST:
        first = (f" (first add the leading candidate, {lead.label}: it removes "
                 f"{lead.share:.0%} of what the constraints cannot yet explain, and what is "
                 "left here may go with it)")
    return tuple(
        f"{column}, along which what is left of {', '.join(names)} lies most, is read by "
        f"{', '.join(who)} and is in no search space of {', '.join(others)}: a coupling of "
        f"it into {'that sensor' if len(others) == 1 else 'them'} is not tested; to test "
        f"one, name {column} in {others[0]}'s `candidates: variables` beside its own "
        f"readings (the list replaces the default){first}"
        for (column, who, others), names in found_in.items())


#: A significant candidate that removes at least this share of what the constraints
#: cannot yet explain comes before the couplings :func:`unsearched` names.
MOST = 0.5


#: How the library names a term's coefficients (``lin_T``, ``h3_sin_u``, ``gain_T``,
#: ``prod_mx_t``): a parameter so named on a sensor is taken for a term an earlier round
#: added (a user's own parameter named so, ``drift_x``, is taken for one too).
COEFFICIENT = re.compile(r"(lin|quad|drift|prod|gain|cpl|h\d+_(sin|cos)|ah\d*_(sin|cos))_")

#: A log kept as shards is diagnosed on at most this many of its rows, spread evenly.
LOG_ROWS = 100_000


def _in_memory(data: Mapping[str, Dataset]) -> dict[str, Dataset]:
    """The datasets in memory: a log kept as shards by at most :data:`LOG_ROWS` of its
    rows, spread evenly over the whole log (the dataset's source says so)."""
    from symcal.data.shards import ShardedDataset

    return {name: ds.spread(LOG_ROWS) if isinstance(ds, ShardedDataset) else ds
            for name, ds in data.items()}


def _without_redundant(entry: Entry, own: Design,
                       regressor: Callable[[Raw], np.ndarray]) -> Entry:
    """The candidate without the columns that add nothing on their own (a quadratic's
    linear part the sensor's gain already is): the same hypothesis, written without a
    parameter the data cannot determine.  A linear part the gain only nearly is stays:
    left out, the quadratic alone stood in for the courier's own physics on the dual
    problem and ended quiet with 4 of its 42 parameters beyond 3 standard errors."""
    entry = _uncentred(entry, own, regressor)
    basis = entry.candidate.basis
    if basis.kind != "quadratic" or len(basis.terms) != len(basis.columns):
        return entry        # a harmonic's sine and cosine are one phase: both or none
    drop = redundant_columns(own, regressor(entry.raw))
    keep = [j for j in range(len(basis.columns)) if j not in drop]
    if not drop or not keep:
        return entry
    reduced = replace(basis, columns=tuple(basis.columns[j] for j in keep),
                      terms=tuple(basis.terms[j] for j in keep),
                      scales=tuple(basis.scales[j] for j in keep) if basis.scales else ())

    def pick(raw: Raw) -> Raw:
        return lambda i: raw(i)[:, :, keep]

    return Entry(Candidate(entry.candidate.output, reduced), pick(entry.raw),
                 None if entry.extra is None else entry.extra, entry.lower)


def _uncentred(entry: Entry, own: Design, regressor: Callable[[Raw], np.ndarray]) -> Entry:
    """A linear or quadratic term written about the variable's zero, ``lin*v`` and
    ``quad*v**2``, where what its centre c moves between it and the rest (a constant, and a
    quadratic's linear part) the free parameters absorb, or nearly (:data:`NEARLY`: a
    gain times a density varying by a few per cent): the same hypothesis, tested alike,
    but one that leaves them their meaning (centred, ``quad*(v - c)**2`` would make a
    sensor's scale factor its slope at c, and its bias its reading there).  A quadratic
    goes about the model's own centre instead where its gain in the variable is written
    about another point (:func:`_model_centre`: ``k*(T - Tc)`` makes k the slope at Tc,
    which a ``quad*T**2`` would move).  Where zero is no point of the run
    (:func:`_far_from_zero`: a temperature in kelvin or degC) and the model has no centre
    of its own, the term stays about the run's centre: the bias a gyro had in the run is
    its meaning there, not its extrapolation to 0 K.  Where the model already has a
    square or a cube in the variable (:func:`_power_centre`), a quadratic or a cubic goes
    about its centre; a cubic otherwise stays about the run's (uncentred, it would hold a
    quadratic part too)."""
    basis = entry.candidate.basis
    lower = entry.lower
    if lower is None or basis.centre == 0.0:
        return entry
    x_lower = regressor(lower)
    if not absorbed(own, x_lower) and not all(
            unexplained_share(own, x_lower[:, j]) < NEARLY for j in range(x_lower.shape[1])):
        return entry        # the parameters do not (nearly) take what the centre moves
    c = basis.centre
    power = _power_centre(own, x_lower, c) if basis.kind in ("quadratic", "cubic") else None
    if basis.kind == "cubic":
        return entry if power is None else _recentred_cubic(entry, c - power, power)
    v0 = power if power is not None else (
        _model_centre(own, x_lower, c) if basis.kind == "quadratic" else 0.0)
    if power is None and v0 == 0.0 and \
            _far_from_zero(regressor(entry.raw)[:, 0], x_lower[:, 0], c):
        return entry        # about the data: zero is no point of the run (0 K, 0 degC)
    d = c - v0
    if basis.kind in ("linear", "gain"):    # v = (v - c) + c (times the output)
        def raw(i: int) -> np.ndarray:
            return entry.raw(i) + d * lower(i)
    else:                               # (v - v0)² = (v - c)² + 2d (v - c) + d², d = c - v0
        def raw(i: int) -> np.ndarray:
            centred, ones = entry.raw(i), lower(i)[:, :, :1]
            return np.concatenate([centred[:, :, :1] + d * ones,
                                   centred[:, :, 1:] + 2 * d * centred[:, :, :1]
                                   + d * d * ones], axis=2)
    terms = basis.terms if v0 != 0.0 else tuple(
        t.replace("({v} - {centre})", "{v}") for t in basis.terms)
    return Entry(Candidate(entry.candidate.output, replace(basis, centre=v0, terms=terms)),
                 raw, entry.extra, lower)


def _recentred_cubic(entry: Entry, d: float, centre: float) -> Entry:
    """``entry``'s cubic written about ``centre`` (``c - d``, c its own): the centre of
    the square or cube in the variable the model already has, so that the parameters
    hold at one point (a quadratic about 0 and a cubic about the data's centre left a
    magnetometer's scale factor the slope at neither).  With that term in the model,
    moving the cube's centre moves only what the parameters take: the same test."""
    lower = entry.lower
    assert lower is not None
    basis = entry.candidate.basis

    def raw(i: int) -> np.ndarray:      # (v - centre)³ = ((v - c) + d)³, times the hooks
        both = lower(i)
        ones, lin = both[:, :, :1], both[:, :, 1:2]
        safe = np.where(ones != 0.0, ones, 1.0)
        return np.where(ones != 0.0, ones * (lin / safe + d) ** 3, 0.0)

    terms = basis.terms if centre != 0.0 else tuple(
        t.replace("({v} - {centre})", "{v}") for t in basis.terms)
    return Entry(Candidate(entry.candidate.output, replace(basis, centre=centre,
                                                           terms=terms)),
                 raw, entry.extra, lower)


def _power_centre(own: Design, x_lower: np.ndarray, centre: float) -> float | None:
    """The centre C of a square or a cube of the variable the model already has on this
    output: a free parameter whose column is ``q*(v - C)**2`` or ``k*(v - C)**3`` (a
    quadratic or cubic an earlier round added), rounded as a centre is; None where there
    is none, or where two disagree.  ``x_lower`` is the whitened ``[1, v - c]`` of the
    term's output (``c`` = ``centre``)."""
    ones, slope = x_lower[:, 0], x_lower[:, 1]
    rows = np.abs(ones) > 1e-9 * float(np.max(np.abs(ones), initial=0.0))
    if int(rows.sum()) < 8:
        return None
    w, x = ones[rows], slope[rows] / ones[rows]
    spread = float(np.std(x))
    if spread == 0.0:
        return None
    t = x / spread
    powers = np.column_stack([w * t**k for k in range(4)])
    found = []
    for k in range(own.nuisance.shape[1]):
        column = own.nuisance[rows, k]
        size = float(np.linalg.norm(column))
        if size == 0.0:
            continue
        a, *_ = np.linalg.lstsq(powers, column, rcond=None)
        if float(np.linalg.norm(column - powers @ a)) > POWER * size:
            continue                    # not a polynomial of degree 3 in the variable
        big = float(np.max(np.abs(a)))
        if abs(a[3]) > POWER * big:     # a cube about d: a3 (t - d)³
            d, pure = -a[2] / (3 * a[3]), w * a[3] * (t + a[2] / (3 * a[3])) ** 3
        elif abs(a[2]) > POWER * big:   # a square about d: a2 (t - d)²
            d, pure = -a[1] / (2 * a[2]), w * a[2] * (t + a[1] / (2 * a[2])) ** 2
        else:
            continue
        if float(np.linalg.norm(column - pure)) <= POWER * size:
            found.append(centre + d * spread)
    if not found or max(found) - min(found) > POWER * spread:
        return None
    return float(f"{found[0]:.6g}") if abs(found[0]) > POWER * spread else 0.0


#: A parameter's column is a pure power of a variable where a polynomial leaves less than
#: this share of it.
POWER = 1e-6


#: A variable's zero is no point of the run when it lies more than this many of the
#: variable's standard deviations from the run's centre (0 K under a temperature of
#: 293-313 K, 0 degC under 20-40 degC): a term in it is then written about the run's
#: centre, and the parameters that absorb what that moves (a gyro's bias) keep their
#: value in the run, instead of becoming an extrapolation to zero (the bias at 0 K, 74
#: standard errors from the bias in the run and 9 times less determined).
FAR = 3.0


def _far_from_zero(centred: np.ndarray, ones: np.ndarray, centre: float) -> bool:
    """Whether zero is more than :data:`FAR` standard deviations of the variable from
    its centre ``centre`` (:func:`_spread` of ``centred`` and ``ones``)."""
    spread = _spread(centred, ones)
    return spread is not None and abs(centre) > FAR * spread


def _spread(centred: np.ndarray, ones: np.ndarray) -> float | None:
    """The variable's standard deviation over the rows, from the whitened ``v - c`` and
    ``1`` of a term's output (their ratio, row by row, is ``v - c``); None where no row
    sees it."""
    rows = np.abs(ones) > 1e-12 * float(np.max(np.abs(ones), initial=0.0))
    return float(np.std(centred[rows] / ones[rows])) if rows.any() else None


#: A free parameter's column is the model's own affine dependence on a variable when the
#: part of it that is not is below this share of it.
AFFINE = 1e-6
#: The model's own centre of a variable within this share of the variable's spread of
#: zero is zero (a triad's bias: its scale factor multiplies ``a - b``).
NEAR_ZERO = 0.1


def _model_centre(own: Design, x_lower: np.ndarray, centre: float) -> float:
    """Where the model's own linear dependence on a variable is written about: the root
    v0 of a free parameter's column that is an affine function of the variable (a gain
    ``k*(v - v0)``: its column is ``[1, v - c]·(c - v0, 1)``), rounded as a centre is;
    0 where there is none, where the parameters disagree, or where v0 is within
    :data:`NEAR_ZERO` of the variable's spread of zero.  ``x_lower`` is the whitened
    ``[1, v - c]`` of the term's output (each observation's rows the same multiple of
    the variable's distance to ``centre``)."""
    ones, slope = x_lower[:, 0], x_lower[:, 1]
    spread = _spread(slope, ones)
    if spread is None:
        return 0.0
    coef, *_ = np.linalg.lstsq(x_lower, own.nuisance, rcond=None)
    left = own.nuisance - x_lower @ coef
    roots = []
    for k in range(own.nuisance.shape[1]):
        size = float(np.linalg.norm(own.nuisance[:, k]))
        a0, a1 = coef[:, k]
        if size == 0.0 or float(np.linalg.norm(left[:, k])) > AFFINE * size or \
                abs(a1) * float(np.linalg.norm(slope)) <= AFFINE * size:
            continue                    # not affine in the variable, or a constant
        roots.append(centre - a0 / a1)
    if not roots or max(roots) - min(roots) > AFFINE * max(spread, 1e-300) or \
            abs(roots[0]) <= NEAR_ZERO * spread:
        return 0.0
    return float(f"{roots[0]:.6g}")


def _variant_differences(variant: Variant, blocks: list[Block], data: Mapping[str, Dataset],
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


def _uncalibratable(
    problem: Problem, full: Design, entries: list[Entry],
    full_regressor: Callable[[Raw], np.ndarray], leads: list[Candidate],
    ranked: list[Candidate], alpha: float, local: Callable[[Candidate], bool],
) -> tuple[list[Candidate], dict[str, str]]:
    """Effects the comparisons with a reference reveal, once the calibratable leads are
    allowed for, that the calibration's constraints do not: tested on every residual of
    every dataset, reported apart with what would determine them."""
    if not problem.comparisons:
        return [], {}
    own_significant = {c.label for c in ranked if c.significant or c.reopens}
    for c in ranked:
        if c.significant:
            own_significant.update(c.indistinguishable)
    by_label = {e.candidate.label: e for e in entries}
    extra = [full_regressor(by_label[c.label].raw) for c in leads]
    nuisance = np.column_stack([full.nuisance, *extra]) if extra else full.nuisance
    names = tuple(f"{c.label} ({col})" for c in leads for col in c.basis.columns)
    design_ = Design(full.r, nuisance, full.nuisance_names + names, full.blocks)
    others = [e for e in entries if e.candidate.label not in own_significant
              and e.candidate.basis.kind != "approximation"]
    tested = test_candidates(
        design_, [Candidate(e.candidate.output, e.candidate.basis) for e in others],
        [full_regressor(e.raw) for e in others], alpha, local,
        [None if e.extra is None else full_regressor(e.extra) for e in others])
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


def _axis(block: Block) -> Variable | None:
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


def _views(blocks: list[Block], result: Result) -> list[ResidualView]:
    views = []
    for b in blocks:
        variables = distinct(b.variables)
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
            along = [v for v in variables if not _contains(b.after[:, k], v.values)]
            left = () if floor is None else tuple(what_is_left(
                after, [v for v in along if v.name not in (name,)], floor))
            views.append(ResidualView(
                b.dataset.name, name, b.kinds[k], b.units[k], before, after,
                moving.name if moving is not None else "index", x,
                tuple(structure(after, along)), best, left))
    return views


def _contains(residual: np.ndarray, values: np.ndarray) -> bool:
    """Whether a residual is a variable whole, up to its sign and a constant (``g_n = Bn
    - B0``, B0 a parameter): binned along it, it "varies with" it trivially (η² 0.96,
    and 150 % of its excess "along Bn", where a magnetometer's gain varied with T)."""
    if len(values) != len(residual) or not np.all(np.isfinite(values)) or \
            np.ptp(values) == 0:
        return False
    size = float(np.max(np.abs(residual)) + np.max(np.abs(values)))
    return any(float(np.ptp(residual - sign * values)) <= 1e-9 * size for sign in (1, -1))


def output_unit(result: Result, output: str) -> str:
    """The unit a term on a sensor output is shown in: that of the first constraint of its
    dimension (the residuals' scale, e.g. µm), else the output's declared unit."""
    unit = next((s.unit for s in result.problem.signals if s.name == output), "")
    return next((c.unit for c in result.problem.constraints
                 if internal_unit(c.unit) == internal_unit(unit)), unit)


def _mde_fields(result: Result, cand: Candidate) -> dict[str, float | str | None]:
    """``mde`` and ``mde_unit`` of a candidate's JSON (:func:`detectable`)."""
    found = detectable(result, cand)
    return {"mde": None if found is None else found[0],
            "mde_unit": "(internal)" if found is None else found[1] or "1"}


def detectable(result: Result, cand: Candidate) -> tuple[float, str] | None:
    """A candidate's minimal detectable effect in the unit it is shown in, and that unit
    (None: not known): a fixed parameter's change in its declared unit, a constant's or a
    delay's in theirs, a term's in its output's (:func:`output_unit`)."""
    if cand.mde is None:
        return None
    kind = cand.basis.kind
    if kind == "fixed":        # a fixed parameter's change, already in its declared unit
        return cand.mde, cand.basis.unit
    unit = cand.basis.unit if kind in ("constant", "latency", "zero") else \
        output_unit(result, cand.output)
    return cand.mde / DISPLAY_UNITS[unit], unit
