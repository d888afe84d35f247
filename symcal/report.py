"""Text and JSON reports of a :class:`~symcal.result.Result`."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from symcal.files import json_text as plain_json
from symcal.result import Result

if TYPE_CHECKING:
    from symcal.diagnose import Diagnosis


def _num(x: float | None, fmt: str = ".6g") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "—"
    return format(x, fmt)


def _table(rows: list[list[str]], align: str) -> list[str]:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    out = []
    for r in rows:
        cells = [c.rjust(w) if a == "r" else c.ljust(w) for c, w, a in zip(r, widths, align,
                                                                           strict=True)]
        out.append("  " + "  ".join(cells).rstrip())
    return out


def _fit_lines(result: Result) -> list[str]:
    rows = [["dataset", "quantity", "std before", "std after", "mean before", "mean after",
             "unit"]]
    last = None
    for s in result.statistics:
        before, after = s.shown("before"), s.shown("after")
        what = s.name if s.kind == "constraint" else f"{s.name} vs reference"
        tiny = 1e-9 * max(before.std, after.std, 1e-300)
        means = (["(arbitrary zero)", ""] if s.remove_mean
                 else [f"{m:.4g}" if abs(m) > tiny else "0" for m in (before.mean, after.mean)])
        rows.append([s.dataset if s.dataset != last else "", what, f"{before.std:.4g}",
                     f"{after.std:.4g}", *means, s.unit or "(internal)"])
        last = s.dataset
    return _table(rows, "llrrrrl")


def _names(names: tuple[str, ...], limit: int = 8) -> str:
    shown = ", ".join(names[:limit])
    return shown + (f", ... ({len(names)} in all)" if len(names) > limit else "")


def _stage_lines(result: Result) -> list[str]:
    lines: list[str] = []
    for k, st in enumerate(result.stages, start=1):
        state = "" if st.success else "  *** FAILED ***"
        lines.append(f"  {k}. {st.name}: {st.method}{state}" + (f" ({st.doc})" if st.doc else ""))
        lines.append(f"     {st.message}; status {st.status}; {len(st.free)} free "
                     f"parameters; {st.iterations} iterations; {st.seconds:.3g} s")
        lines.append(f"     cost Σ(g/σ)²: {st.cost_before:.6g} → {st.cost_after:.6g}")
        for c in st.costs:
            lines.append(f"       {c.name}: RMS {c.rms_before:.4g} → {c.rms_after:.4g} "
                         f"{c.unit or '(internal)'}")
        before, after = st.conditioning_before, st.conditioning_after
        lines.append(f"     condition number of the cost's Hessian (identifiable part, "
                     f"parameters in their scales): {before.condition_number:.3g} at the "
                     f"start, {after.condition_number:.3g} at the end")
        for combo, rel in after.near_null:
            lines.append(f"       nearly flat: {combo.text}  (singular value {rel:.2g} of "
                         "the largest)")
        if st.identifiability.deficiency:
            lines.append(f"     {st.identifiability.deficiency} direction(s) not "
                         "identifiable (listed below for the last stage)")
        if st.unmoved:
            lines.append(f"     did not move: {_names(st.unmoved)}")
        if st.at_bound:
            lines.append(f"     at a bound: {_names(st.at_bound)}")
        lines += [f"     note: {n}" for n in st.notes]
    return lines


def _identifiability_lines(result: Result) -> list[str]:
    ident = result.identifiability
    lines = [f"  rank {ident.rank} of {ident.n_free} free parameters; condition number of "
             f"the identifiable part {ident.condition_number:.4g}"]
    if ident.null_space:
        lines.append(f"  {ident.deficiency} direction(s) the data cannot determine "
                     "(each leaves every constraint unchanged; the estimate keeps the initial "
                     "values along them):")
        lines += [f"    {c.text}" for c in ident.null_space]
    if ident.identifiable_combinations:
        lines.append("  determined only in combination:")
        units = {p.name: p.unit for p in result.parameters}
        for c in ident.identifiable_combinations:
            unit = {units[n] for n in c.coefficients}
            shown = f" {unit.pop()}" if len(unit) == 1 else ""
            lines.append(f"    {c.text} = {_num(c.value)} ± {_num(c.se, '.2g')}{shown}")
    return lines


def _correlation_lines(result: Result, limit: float = 0.99, most: int = 8) -> list[str]:
    unc = result.uncertainty
    corr, names = unc.correlation, unc.names
    pairs = [(abs(corr[i, j]), names[i], names[j], corr[i, j])
             for i in range(len(names)) for j in range(i + 1, len(names))
             if np.isfinite(corr[i, j]) and abs(corr[i, j]) > limit]
    if not pairs:
        return [f"  no pair of estimates is correlated beyond |ρ| = {limit}"]
    pairs.sort(reverse=True)
    lines = [f"  {a} ~ {b}: ρ = {rho:+.4f}" for _, a, b, rho in pairs[:most]]
    if len(pairs) > most:
        lines.append(f"  ... {len(pairs) - most} more pairs beyond |ρ| = {limit}")
    return lines


def _parameter_lines(result: Result) -> list[str]:
    rows = [["parameter", "value", "± se", "initial", "unit", "note"]]
    for p in result.parameters:
        note = "fixed" if p.fixed else ""
        if not p.fixed and p.se is None:
            note = "only in combination" if "combination" in (p.se_reason or "") else (
                p.se_reason or "")
        if p.at_bound:
            note = (note + "; " if note else "") + f"at {p.at_bound} bound"
        rows.append([p.name, _num(p.value), _num(p.se, ".2g"), _num(p.initial), p.unit, note])
    return _table(rows, "lrrrll")


def _implicit_lines(result: Result) -> list[str]:
    rows = [["definition", "dataset", "steps", "max |dF/dx|", "last step", "error bound",
             "converged"]]
    for c in result.implicit:
        rows.append([c.name, c.dataset, str(c.steps), f"{c.contraction:.3g}",
                     f"{c.last_step:.2g}", _num(c.remaining, ".2g"),
                     "yes" if c.contracts else "NO: not a contraction"])
    return _table(rows, "llrrrrl")


def text_report(result: Result) -> str:
    """The report a person reads: data, solver, identifiability, fit, parameters."""
    state = "" if result.success else "  *** FAILED ***"
    lines = [f"symcal: {result.name} ({result.problem_path}){state}", "", "Data"]
    lines += _table([[d.name, f"{d.n} observations", d.source
                      + (f" ({d.dropped} invalid rows dropped)" if d.dropped else "")]
                     for d in result.datasets], "lrl")
    lines += ["", "Stages (each starts from the previous estimate)"]
    lines += _stage_lines(result)
    lines += ["", f"Identifiability (last stage, '{result.stages[-1].name}')"]
    lines += _identifiability_lines(result)
    lines += ["", "Fit: standard deviation and mean of each residual with the initial "
              "parameters (before) and the estimate (after)"]
    lines += _fit_lines(result)
    lines += ["", "Parameters (standard errors from the Jacobian at the estimate, scaled by "
              "the residual variance)"]
    lines += _parameter_lines(result)
    lines += ["", "Strongly correlated estimates"]
    lines += _correlation_lines(result)
    if result.implicit:
        lines += ["", "Implicit definitions (fixed-point steps, checked at the estimate)"]
        lines += _implicit_lines(result)
    if result.notes:
        lines += ["", "Notes"] + [f"  - {n}" for n in result.notes]
    return "\n".join(lines) + "\n"


def json_report(result: Result) -> str:
    """The machine-readable document (``--json``)."""
    return plain_json(result.to_dict())


def diagnosis_report(diag: Diagnosis) -> str:
    """What `symcal diagnose` prints: where the model fails, which effect is missing."""
    lines = [f"symcal diagnose: {diag.result.name} ({diag.result.problem_path})", "",
             "Where the model fails (after calibration; std of each residual, the variables "
             "along which it varies most, and its dominant period)"]
    for v in diag.residuals:
        what = v.name if v.kind == "constraint" else f"{v.name} vs reference"
        std = float(np.std(v.after)) / v.scale
        lines.append(f"  {v.dataset} {what}: std {std:.4g} {v.unit or '(internal)'}")
        for b in v.binned[:2]:
            lines.append(f"      varies with {b.variable}: η² = {b.eta2:.2f}")
        if v.periodogram is not None and float(np.max(v.periodogram.power)) > 0.1:
            lines.append(f"      dominant frequency: {v.periodogram.peak_text} "
                         f"(power {float(np.max(v.periodogram.power)):.2f})")
    ranked = list(diag.leads)
    lines += ["", f"Which effect is missing ({diag.tested} candidate terms tested; family-wise "
              f"level {diag.alpha:g}, Bonferroni; indistinguishable candidates grouped)"]
    if not diag.significant:
        lines.append("  no candidate effect is significant: the residuals look like noise to "
                     "this library of effects")
    rows = [["rank", "candidate", "removes", "F", "p", "significant"]]
    for i, c in enumerate(ranked[:10], start=1):
        group = f" (+{len(c.indistinguishable)} alike)" if c.indistinguishable else ""
        rows.append([str(i), c.label + group, f"{c.share:.1%}", f"{c.f_stat:.3g}",
                     f"{c.p_value:.2g}", "yes" if c.significant else "no"])
    if len(rows) > 1:
        lines += _table(rows, "rlrrrl")
    for i, c in enumerate(diag.significant[:3], start=1):
        lines += ["", f"  {i}. {c.label}", "     " + diag.candidate_text(c)]
        if diag.yaml.get(c.label):
            lines += ["     To add it:"] + [f"       {ln}" if ln else ""
                                            for ln in diag.yaml[c.label].splitlines()]
    absorbed = [c for c in diag.candidates if c.absorbed and c.biases][:5]
    if absorbed:
        lines += ["", "Absorbed by the current parameters (invisible in these residuals; if "
                  "present, such an effect biases the parameters named):"]
        lines += [f"  {c.label}: would bias {', '.join(c.biases)}" for c in absorbed]
    return "\n".join(lines) + "\n"
