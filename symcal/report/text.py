"""Text and JSON reports of a :class:`~symcal.calibrate.result.Result` and of a diagnosis.

Human-facing text writes units as symbols (µm, µrad; :func:`symcal.base.units.symbol`); the
JSON documents keep the declared unit strings.  Each report opens with a verdict a person
reads at a glance.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any

import casadi as ca
import numpy as np

from symcal.analysis.declared_errors import NOTE as SANDWICH_NOTE
from symcal.analysis.outliers import THRESHOLD, Outliers, remedy, remedy_yaml
from symcal.analysis.verdicts import family_bands, family_verdicts
from symcal.base.digits import estimate_text
from symcal.base.files import json_text as plain_json
from symcal.base.units import DISPLAY_UNITS, symbol
from symcal.base.units import size as unit_size
from symcal.calibrate.result import REGRESSION_TOLERANCE, Regression, Result
from symcal.experiment.command import design_sentence, target_arg

if TYPE_CHECKING:
    from symcal.analysis.fit import SeriesStats
    from symcal.experiment.optimize import Design
    from symcal.revise.diagnose import Diagnosis

#: At most this many regressions are listed in a verdict (all are in the tables).
VERDICT_REGRESSIONS = 4
#: A residual's binned structure counts as a finding above this share of its variance.
STRUCTURE_ETA2 = 0.1


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


def noise_floors(result: Result) -> dict[tuple[str, str], float]:
    """The noise floor of each residual and comparison, as the solve found it.

    A floor is the standard deviation the readings' declared noise leaves in a residual,
    propagated through it at the estimate, or estimated from time-ordered data where no
    noise is declared (:mod:`symcal.analysis.floors`); it is stored in the result's
    statistics (and in ``result.json``): nothing is read or simulated here.

    Parameters
    ----------
    result
        A calibration result.

    Returns
    -------
    dict
        ``(dataset, name)`` → the floor in internal units, where it is known and positive.
    """
    return {(s.dataset, s.name): float(s.floor) for s in result.statistics
            if s.floor is not None and s.floor > 0}


def _band_text(band: tuple[float, float] | None) -> str:
    return "" if band is None else f", band {band[0]:.2f}–{band[1]:.2f}"


def _chi2_text(test: Any) -> str:
    """``χ²/dof 1.02, band 0.91–1.09`` of a floor test."""
    value = test.chi2_dof
    shown = f"{value:.3g}" if value is not None and value < 10 else (
        f"{value:.3g}" if value is not None else "—")
    return f"χ²/dof {shown}{_band_text(test.band)}"


def floor_verdict(test: Any) -> str:
    """A dataset's global test in words: ``at the noise floor (χ²/dof 1.02, band
    0.91–1.09)``, ``3.4× the noise floor (...)``, ``below the noise floor (...)``."""
    verdict = test.verdict
    if verdict == "at":
        return f"at the noise floor ({_chi2_text(test)})"
    if verdict == "above":
        return f"{test.ratio:.3g}× the noise floor ({_chi2_text(test)})"
    if verdict == "below":
        return (f"below the noise floor ({_chi2_text(test)}): overfitting, or noise declared "
                "larger than the sensors' — not a success")
    return "noise floor unknown"


def undeclared_readings(result: Result) -> list[str]:
    """The columns the constraints read whose noise nobody declared."""
    problem = result.problem
    return sorted({c for q in problem.constraints for c in problem.undeclared(q.sx)},
                  key=list(problem.columns).index)


def how_to_declare(result: Result) -> str:
    """How to make an unknown floor known, naming the readings without noise."""
    missing = undeclared_readings(result)
    names = ", ".join(missing[:6]) + (f" and {len(missing) - 6} more" if len(missing) > 6
                                      else "")
    return (f"no noise is declared for {names or 'the readings'} and the rows are not "
            "time-ordered; declare each reading's noise ('noise: 0.5 um' on the column or the "
            "model input, or in the problem's 'noise:' section) to test the model against "
            "its floor")


def outcome_text(improvement: Any) -> str:
    """How ``symcal improve`` ended, in words (an
    :class:`~symcal.revise.improve.Improvement`): quiet at the floor, quiet with the floor
    unknown (only: no candidate is significant; how to declare the noise), structure that
    no candidate explains above the floor, below the floor, or candidates that do not pay."""
    aliased = (" (what is left is aliased with the parameters already there)"
               if improvement.aliased else "")
    result = improvement.rounds[-1].result
    if not result.success:
        return (f"the starting problem's solve failed, so no revision was tried: "
                f"{result.failure}; fix it first (symcal solve shows the failure)")
    outside = getattr(improvement.last, "outside", ())
    if outside and not improvement.candidates_left:
        return ("the diagnosis is not quiet: no candidate of the search spaces is "
                "significant, but a coupling outside them is: "
                + "; ".join(improvement.last.outside_words[c.label] for c in outside))
    unverified = getattr(improvement, "unverified", ())
    moved = sorted((m for _, ms in unverified for m in ms), key=lambda m: -m.shift)
    names = ", ".join(f"{m.name} by {m.shift:.3g} SE" for m in moved[:4]) + (
        f" and {len(moved) - 4} more" if len(moved) > 4 else "")
    if improvement.quiet and improvement.at_floor and unverified:
        return (f"the diagnosis is quiet on the fitted data alone, which does not verify "
                f"the model: no held-out run checked {len(unverified)} of the terms kept, "
                f"and they moved {names}; either a missing effect had biased those, or a "
                "term stands in for another effect (a step, a coupling the library lacks) "
                "that fits this run as well: add a held-out run (a dataset with 'role: "
                "check', another day's log) and improve again" + aliased)
    undecided = getattr(improvement, "undecided", ())
    if improvement.quiet and improvement.at_floor and undecided:
        return ("the diagnosis is quiet, but the data do not decide the model: "
                + undecided[0] + (f" (and {len(undecided) - 1} more such choice"
                                  f"{'s' if len(undecided) > 2 else ''}, below)"
                                  if len(undecided) > 1 else "") + aliased)
    if improvement.quiet and improvement.at_floor:
        return "the diagnosis is quiet: every dataset is at its noise floor" + aliased
    if improvement.quiet:
        return ("the diagnosis is quiet, which here only means that no candidate is "
                f"significant: the noise floor is unknown ({how_to_declare(result)})"
                + aliased)
    unchecked = (f"; no held-out run checked {len(unverified)} of the terms kept, which "
                 f"moved {names}" if unverified else "")
    if not improvement.candidates_left:
        if any(t.verdict == "below" for t in result.floor_tests) and not any(
                t.verdict == "above" for t in result.floor_tests):
            return ("the diagnosis is not quiet: below the noise floor (overfitting, or noise "
                    "declared larger than the sensors')" + unchecked)
        return ("the diagnosis is not quiet: structure remains that no candidate explains "
                "(above the noise floor, and no candidate of the library is significant; "
                "or the readings are noisier than declared)" + unchecked)
    limit = getattr(improvement, "limit", None)
    if limit is not None:
        return (f"the diagnosis is not quiet: the loop stopped at its limit of {limit} "
                "rounds with significant candidates left (--max-rounds sets it; so many "
                "terms may stand in for one effect the library lacks)" + unchecked)
    return "the diagnosis is not quiet (nothing else pays)" + unchecked


def family_note(tests: Any, index: int) -> str:
    """Where a dataset is off its own band but inside its band in the family-wise test of
    ``at_floor`` (all datasets together at 95 %, Šidák), that note; else ``""``."""
    test = tests[index]
    band = family_bands(tuple(tests))[index]
    if band is None or test.verdict not in ("above", "below") or \
            family_verdicts(tuple(tests))[index] != "at":
        return ""
    known = sum(t.verdict is not None for t in tests)
    return (f"; at the floor as one of {known} datasets tested together (family-wise band "
            f"{band[0]:.2f}–{band[1]:.2f}, 95 % for all of them, Šidák)")


def alone_lines(result: Result) -> list[str]:
    """One line per constraint above its own floor at 1 % over the constraints tested
    alone (:attr:`~symcal.calibrate.result.Result.above_alone`) whose dataset's joint
    test is at the floor (where it is not, the dataset's line says so already)."""
    above = getattr(result, "above_alone", ())
    if not above:
        return []
    family = dict(zip((t.dataset for t in result.floor_tests),
                      family_verdicts(result.floor_tests), strict=True))
    k = len(result.alone)
    lines = []
    for s, bound in above:
        if s.noise is None or family.get(s.dataset) != "at":
            continue            # its dataset is off its floor already: said there
        lines.append(f"{s.dataset} {s.name}: above its own floor ({_chi2_text(s.noise)}; "
                     f"beyond {bound:.3g}, its bound at 1 % over the {k} constraints "
                     "tested alone): the dataset's joint test, which weighs its "
                     "constraints by their shared noise, is at the floor, but a signal "
                     "the constraints share lies along that noise and the joint test "
                     "dilutes it")
    return lines


def floor_lines(result: Result) -> list[str]:
    """One verdict line per dataset: its constraints' global test against the floor (and
    where the family-wise decision of ``at_floor`` differs from its own band, why)."""
    lines = []
    for i, t in enumerate(result.floor_tests):
        note = family_note(result.floor_tests, i)
        # below its own band but at the floor with the others: not "not a success"
        text = (f"below its own band ({_chi2_text(t)})" if note and t.verdict == "below"
                else floor_verdict(t)) + note
        if t.verdict is None:
            text += f": {how_to_declare(result)}"
        elif t.method == "combined" and any(
                s.noise is not None and s.noise.method == "successive differences"
                for s in result.statistics if s.dataset == t.dataset):
            text += " (some floors estimated from the data: successive differences)"
        lines.append(f"{t.dataset}: {text}")
    return lines + alone_lines(result)


def _what(s: Any) -> str:
    """A residual's name; a comparison's as ``NAME vs reference``."""
    return s.name if s.kind == "constraint" else f"{s.name} vs reference"


def _spread_text(value: float, unit: str) -> str:
    return f"{value:.4g} {symbol(unit)}"


def _regression_text(r: Regression) -> str:
    """E.g. ``calibration made flyby position_y vs reference worse: std 2.94 → 10.55 µm``."""
    return (f"calibration made {r.dataset} {_what(r)} worse: {r.measure} {r.before:.4g} → "
            f"{r.after:.4g} {symbol(r.unit)}")


#: How a residual against its floor is marked in the fit table.
_MARKS = {"above": "ABOVE", "below": "BELOW", "at": "at", None: ""}


def _fit_lines(result: Result, floors: Mapping[tuple[str, str], float]) -> list[str]:
    worse = {(r.dataset, r.name) for r in result.regressions}
    rows = [["dataset", "quantity", "std before", "std after", "mean before", "mean after",
             "unit", "noise floor", "χ²/dof", "95 % band", "floor", ""]]
    last = None
    estimated = False
    for s in result.statistics:
        before, after = s.shown("before"), s.shown("after")
        tiny = 1e-9 * max(before.std, after.std, 1e-300)
        means = (["(arbitrary zero)", ""] if s.remove_mean
                 else [f"{m:.4g}" if abs(m) > tiny else "0" for m in (before.mean, after.mean)])
        floor = floors.get((s.dataset, s.name))
        shown = floor / DISPLAY_UNITS[s.unit] if floor is not None else None
        test = s.noise
        mark = "" if shown is None or test is None else (
            "*" if test.method == "successive differences" else "")
        estimated = estimated or bool(mark)
        band = test.band if test is not None else None
        rows.append([s.dataset if s.dataset != last else "", _what(s), f"{before.std:.4g}",
                     f"{after.std:.4g}", *means, symbol(s.unit),
                     "" if shown is None else f"{shown:.4g}{mark}",
                     _num(test.chi2_dof if test is not None else None, ".3g")
                     if shown is not None else "",
                     "" if band is None or shown is None else f"{band[0]:.2f}–{band[1]:.2f}",
                     _MARKS[test.verdict if test is not None and shown is not None else None],
                     "WORSE" if (s.dataset, s.name) in worse else ""])
        last = s.dataset
    if not floors:       # no floor known anywhere: no empty columns
        rows = [r[:7] + r[11:] for r in rows]
        return _table(rows, "llrrrrll")
    lines = _table(rows, "llrrrrlrrrll")
    if estimated:
        lines.append("  * estimated from the data (successive differences of the time-ordered "
                     "rows: what varies slowly is left out); no noise is declared for its "
                     "readings")
    return lines


def _worst_against_floor(result: Result, floors: Mapping[tuple[str, str], float]
                         ) -> tuple[SeriesStats, float, float] | None:
    """The residual or comparison farthest above its known floor by its test: (stats, std
    after in the display unit, √(χ²/dof))."""
    best: tuple[SeriesStats, float, float] | None = None
    for s in result.statistics:
        if (s.dataset, s.name) not in floors or s.noise is None or s.noise.ratio is None:
            continue
        ratio = s.noise.ratio
        if best is None or ratio > best[2]:
            best = (s, s.shown("after").std, ratio)
    return best


def _worst_text(result: Result, floors: Mapping[tuple[str, str], float]) -> str | None:
    """``worst against its noise floor: flyby g_p std 2.1 µm; by its test 2.05 × the
    floor 1.02 µm (χ²/dof 4.2, band 0.87–1.14)``, or None when no floor is known.  The
    ratio is √(χ²/dof): the mean counts, and each row's own floor where it varies."""
    worst = _worst_against_floor(result, floors)
    if worst is None:
        return None
    s, after, ratio = worst
    floor = floors[(s.dataset, s.name)] / DISPLAY_UNITS[s.unit]
    assert s.noise is not None
    return (f"worst against its noise floor: {s.dataset} {_what(s)} std "
            f"{_spread_text(after, s.unit)}; by its test {ratio:.2f} × the floor "
            f"{_spread_text(floor, s.unit)} ({_chi2_text(s.noise)})")


def references_above(result: Result) -> list[SeriesStats]:
    """The comparisons with a reference above their noise floor, on any dataset (judged
    by their test, not by a threshold)."""
    return [s for s in result.statistics if s.kind == "comparison" and s.noise is not None
            and s.noise.verdict == "above"]


def _failure_text(result: Result) -> str | None:
    failure = result.failure
    return None if failure is None else f"FAILED: {failure}"


def _null_space_text(result: Result) -> str:
    ident = result.identifiability
    if not ident.deficiency:
        return (f"every free parameter is determined by the data (rank {ident.rank} of "
                f"{ident.n_free})")
    return (f"{ident.deficiency} parameter direction(s) the data cannot determine (their "
            "initial values are kept; see Identifiability)")


def outlier_text(outliers: Outliers) -> str | None:
    """The outliers of a fit in one sentence (None when there are none), e.g.
    ``outliers dominate: 8 of 1000 observations of calibration ... carry 94% of the cost``."""
    if outliers.count == 0:
        return None
    n_obs = outliers.rows // max(len(outliers.units), 1)
    kind = "standardized residual" if outliers.standardized_std is not None else "residual"
    what = (f"{outliers.observations} of {n_obs} observations of {outliers.dataset} have a "
            f"{kind} beyond {THRESHOLD:g} robust standard deviations")
    if outliers.squared:
        carry = f"they carry {outliers.share:.0%} of the cost Σ(g/σ)²"
    else:
        carry = (f"down-weighted by the robust loss ({outliers.loss}), they carry "
                 f"{outliers.share:.0%} of the weighted cost's gradient variance")
    if outliers.dominate:
        remedy = ("; a robust loss is the remedy (see Outliers)" if outliers.squared else
                  "; a loss that down-weights them more (cauchy, arctan) or a smaller scale "
                  "is the remedy")
        return f"outliers dominate: {what}; {carry}{remedy}"
    return f"{what}; {carry}"


def _outlier_lines(outliers: Outliers) -> list[str]:
    """The Outliers section of the text report."""
    spread = ", ".join(f"{name} {std:.4g} {symbol(outliers.units.get(name, ''))}"
                       for name, std in outliers.robust_std.items())
    loss = "squared residuals" if outliers.squared else f"robust loss {outliers.loss}"
    lines = [f"  {loss}; robust standard deviation (1.4826 × MAD) of each residual: {spread}"]
    if outliers.standardized_std is not None:
        scaled = ", ".join(f"{name} {std:.3g}"
                           for name, std in outliers.standardized_std.items())
        lines.append("  each residual tested over its row's own standard deviation propagated "
                     "from the readings' noise (as the propagated weighting weighs it); "
                     f"robust standard deviation of those standardized residuals: {scaled}")
    sentence = outlier_text(outliers)
    if sentence is None:
        lines.append(f"  no residual lies beyond {THRESHOLD:g} robust standard deviations")
        return lines
    lines.append(f"  {sentence}")
    rows = [["dataset", "row", "time", "constraint", "residual", "unit", "× robust std",
             "weight"]]
    for o in outliers.listed:
        rows.append([o.dataset, str(o.row), _num(o.time), o.constraint, f"{o.residual:.4g}",
                     symbol(o.unit), f"{o.whitened:.3g}", f"{o.weight:.3g}"])
    lines += _table(rows, "lrrlrlrr")
    if outliers.count > len(outliers.listed):
        lines.append(f"  ... {outliers.count - len(outliers.listed)} more (the largest are "
                     "listed; rows count the dataset's observations from 0)")
    if outliers.dominate and outliers.squared:
        kind, factor, spreads_of = remedy(outliers)
        what = ("Cauchy, which all but ignores gross errors" if kind == "cauchy"
                else "Huber")
        measured = ("spread of the residuals once the fit is solved again without the "
                    "outliers" if outliers.clean_std is not None
                    else "robust standard deviation of the residual")
        spreads = ", ".join(f"{name} {std:.4g} {symbol(outliers.units.get(name, ''))}"
                            for name, std in spreads_of.items())
        lines.append(f"  To give these constraints a robust loss ({what}; scale {factor:g} × "
                     f"the {measured}: {spreads}), add to the problem file:")
        if outliers.standardized_std is not None:
            lines.append("  (a robust loss replaces the propagated weighting: one scale for "
                         "rows whose noise differs, so the noisiest are down-weighted too)")
        lines += [f"    {ln}" for ln in remedy_yaml(outliers).splitlines()]
    return lines


def _regression_lines(found: tuple[Regression, ...], indent: str) -> list[str]:
    lines = [indent + _regression_text(r) for r in found[:VERDICT_REGRESSIONS]]
    if len(found) > VERDICT_REGRESSIONS:
        lines.append(f"{indent}... and {len(found) - VERDICT_REGRESSIONS} more (marked WORSE "
                     "in the fit table)")
    return lines


def verdict_lines(result: Result,
                  floors: Mapping[tuple[str, str], float] | None = None) -> list[str]:
    """The verdict at the top of :func:`text_report`, one finding per line.

    Success or failure; each dataset's global test against its noise floor (at, above
    or below it, or unknown and how to declare it); the residual farthest above its
    floor, where floors are known (:func:`noise_floors`); the comparisons with a
    reference above their floor; every residual or comparison calibration made worse
    (:attr:`~symcal.calibrate.result.Result.regressions`); how many parameter directions the data
    cannot determine.

    Parameters
    ----------
    result
        A calibration result.
    floors
        Known noise floors (default: :func:`noise_floors` of ``result``).

    Returns
    -------
    list of str
        The lines, without indentation.
    """
    floors = noise_floors(result) if floors is None else floors
    n = len(result.stages)
    lines = [_failure_text(result)
             or f"solved: {n} stage{'s' if n > 1 else ''} converged ({result.method})"]
    sentence = None if result.outliers is None else outlier_text(result.outliers)
    if sentence is not None:
        lines.append(sentence)
    if not result.success and result.floor_tests:
        lines.append("the tests below are of the estimate where the solve stopped, not of "
                     "a solution: they say nothing of the model")
    lines += floor_lines(result)
    worst = _worst_text(result, floors)
    if worst is not None:
        lines.append(worst)
    above = references_above(result)
    if above:
        shown = ", ".join(f"{s.dataset} {s.name} ({s.noise.ratio:.2f} ×)"   # type: ignore[union-attr]
                          for s in above[:VERDICT_REGRESSIONS])
        more = (f" and {len(above) - VERDICT_REGRESSIONS} more"
                if len(above) > VERDICT_REGRESSIONS else "")
        lines.append(f"against the reference, above the noise floor: {shown}{more}")
    serial = result.stages[-1].serial if result.stages else None
    if serial is not None and serial.detected:
        lines.append(serial.text)
    found = result.regressions
    if found:
        lines += _regression_lines(found, "")
    else:
        lines.append(f"no residual or comparison is worse after calibration by more than its "
                     f"noise allows (by more than {REGRESSION_TOLERANCE:.0%} where its floor "
                     "is unknown)")
    lines.append(_null_space_text(result))
    gauges = _gauges(result)
    if gauges:
        kinds = "; ".join(f"{g.kind} of {', '.join(g.parameters)}" for _, g in gauges)
        lines.append(f"{len(gauges)} gauge(s) found before the solve, which no data can "
                     f"determine ({kinds}); see Gauges for the fix")
    held = centre_line(result)
    if held:
        lines.append(held)
    return lines


def centre_line(result: Result) -> str:
    """Where the parameters hold when the model has terms written about a centre (a
    constant ``symcal improve`` documented as one: the term is zero there), or ``""``:
    an offset or a gain is then its value at that centre, not at a datasheet's
    reference (``symcal improve`` says so when it adds the term; a later solve of the
    final problem said nothing)."""
    from symcal.revise.effects import centre_variable

    found = []
    for c in result.problem.constants:
        variable = centre_variable(c.doc)
        if variable is not None:
            unit = f" {c.unit}" if c.unit else ""
            found.append(f"{variable} = {float(c.value):.6g}{unit} ({c.key})")
    if not found:
        return ""
    return ("the parameters hold where the terms written about a centre are zero: "
            + ", ".join(found) + "; to have them hold at a datasheet's reference, write it "
            "as that constant's value in the model file and solve again")


def _gauges(result: Result) -> list[tuple[str, Any]]:
    """Every stage's gauges as ``(stage, gauge)``, each text once."""
    seen: set[str] = set()
    out = []
    for st in result.stages:
        for g in st.gauges.gauges if st.gauges is not None else ():
            if g.text not in seen:
                seen.add(g.text)
                out.append((st.name, g))
    return out


def _gauge_lines(result: Result) -> list[str]:
    lines = []
    for stage, g in _gauges(result):
        lines.append(f"  {stage}: {g.text}")
        where = "" if g.kind == "offset" else " at the start"
        lines += [f"    direction{where}: {c.text}" for c in g.directions]
    return lines


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
        lines.append(f"     cost Σ(g/σ)², σ each constraint's sigma (the weighting aside): "
                     f"{st.cost_before:.6g} → {st.cost_after:.6g}")
        for c in st.costs:
            lines.append(f"       {c.name}: RMS {c.rms_before:.4g} → {c.rms_after:.4g} "
                         f"{symbol(c.unit)}")
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
        if st.serial is not None:
            lines.append(f"     {st.serial.text}")
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
        units = {p.name: p.unit for p in result.params.values()}
        for c in ident.identifiable_combinations:
            unit = {units[n] for n in c.coefficients}
            shown = f" {symbol(unit.pop())}" if len(unit) == 1 else ""
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
    for p in result.params.values():
        note = "fixed" if p.fixed else ""
        if not p.fixed and p.se is None:
            note = "only in combination" if "combination" in (p.se_reason or "") else (
                p.se_reason or "")
        if p.at_bound:
            note = (note + "; " if note else "") + f"at {p.at_bound} bound"
        value = "—" if not math.isfinite(p.value) else estimate_text(p.value, p.se)
        rows.append([p.name, value, _num(p.se, ".2g"), _num(p.initial),
                     symbol(p.unit) if p.unit else "", note])
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
    """The report a person reads: the verdict, then data, solver, identifiability, fit,
    parameters."""
    state = "" if result.success else "  *** FAILED ***"
    floors = noise_floors(result)
    lines = [f"symcal: {result.name} ({result.problem_path}){state}", "", "Verdict"]
    lines += [f"  {ln}" for ln in verdict_lines(result, floors)]
    if _gauges(result):
        lines += ["", "Gauges (symmetries found before the solve, at the start and at random "
                  "points: no data can determine them)"]
        lines += _gauge_lines(result)
    lines += ["", "Data"]
    lines += _table([[d.name, f"{d.n} observations", d.source
                      + (f" ({d.dropped} invalid rows dropped)" if d.dropped else "")]
                     for d in result.provenance], "lrl")
    lines += ["", "Stages (each starts from the previous estimate)"]
    lines += _stage_lines(result)
    lines += ["", f"Identifiability (last stage, '{result.stages[-1].name}')"]
    lines += _identifiability_lines(result)
    lines += ["", "Fit: standard deviation and mean of each residual with the initial "
              "parameters (before) and the estimate (after)"
              + ("; its noise floor (the readings' declared noise propagated through it), "
                 "χ²/dof against it and the 95 % band of χ²/dof at the floor" if floors
                 else "")]
    lines += _fit_lines(result, floors)
    if result.outliers is not None:
        lines += ["", f"Outliers (last stage, '{result.stages[-1].name}': residual rows "
                  f"beyond {THRESHOLD:g} robust standard deviations)"]
        lines += _outlier_lines(result.outliers)
    robust = result.outliers is not None and not result.outliers.squared
    serial = result.stages[-1].serial
    lines += ["", "Parameters (standard errors from the Jacobian at the estimate, "
              + ("the robust sandwich with the final weights)" if robust else
                 f"the Newey-West sandwich over {serial.lags} lags: the rows are serially "
                 "correlated)" if serial is not None and serial.detected else
                 "the sandwich with each observation's covariance from the declared noise, "
                 "scaled by the residuals' variance over what it predicts)"
                 if any(n.startswith(SANDWICH_NOTE)
                        for n in result.stages[-1].notes) else
                 "scaled by the residual variance)")]
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


def self_referential(result: Result) -> dict[str, frozenset[str]]:
    """For each residual and comparison, the variables it contains whole.

    A residual binned against such a variable "varies with" it trivially: a comparison
    ``theta_x`` (estimate minus reference) against the expression ``theta_x`` whose error
    it is.  These are the residual's own name and, for a comparison, every named
    expression or sensor signal that is its estimate.

    Parameters
    ----------
    result
        A calibration result.

    Returns
    -------
    dict
        Residual or comparison name → names of the variables to leave out.
    """
    problem = result.problem
    named = [(q.name, q.sx) for q in problem.expressions]
    named += [(sig.name, sig.sx) for sig in problem.signals]
    out = {c.name: frozenset({c.name}) for c in problem.constraints}
    for comp in problem.comparisons:
        out[comp.name] = frozenset({comp.name} | {n for n, sx in named
                                                  if ca.is_equal(sx, comp.estimate, 64)})
    return out


def _findings(binned: Iterable[Any], skip: frozenset[str] | set[str]) -> list[Any]:
    """Binned structure but along variables the residual contains whole (also along their
    phase)."""
    def own(variable: str) -> bool:
        return variable in skip or any(variable.startswith(f"phase of {n} (")
                                       for n in skip)
    return [b for b in binned if not own(str(b.variable))]


def _floor_note(value: float, floor: float | None, unit: str, test: Any = None) -> str:
    if floor is None:
        return ""
    shown = floor / DISPLAY_UNITS[unit]
    chi2 = "" if test is None or test.chi2_dof is None else f"; {_chi2_text(test)}"
    return f" (noise floor {_spread_text(shown, unit)}; {value / shown:.2f} ×{chi2})"


def references_apart(diag: Any) -> list[str]:
    """The comparisons with a reference above their noise floor on a dataset whose
    constraints are at theirs: real, but not calibratable by these constraints; each with
    the variable it follows most (binned, η²) and, where one exists, the problem that can
    determine it (:attr:`Diagnosis.pointer <symcal.revise.diagnose.Diagnosis.pointer>`)."""
    result = diag.result
    at = {t.dataset for t in result.floor_tests if t.verdict == "at"}
    skip = self_referential(result)
    views = {(v.dataset, v.name): v for v in getattr(diag, "residuals", ())}
    pointer = str(getattr(diag, "pointer", "") or "")
    out = []
    for s in references_above(result):
        if s.dataset not in at:
            continue
        assert s.noise is not None
        text = f"{s.dataset} {s.name} vs reference, {s.noise.ratio:.2f}× its noise floor"
        view = views.get((s.dataset, s.name))
        found = [] if view is None else _findings(view.binned,
                                                  skip.get(s.name, frozenset({s.name})))
        if found:
            text += f", varies with {found[0].variable} (η² = {found[0].eta2:.2f})"
        out.append(text + (f"; {pointer}" if pointer else ""))
    return out


def _own(variable: str, skip: frozenset[str] | set[str]) -> bool:
    return variable in skip or any(variable.startswith(f"phase of {n} (") for n in skip)


def left_lines(diag: Any) -> list[str]:
    """What is left above the floor, for each residual above it: the variables and pairs
    its excess lies along (binned means), strongest first, with their share of the excess;
    variables a residual contains whole are left out."""
    skip = self_referential(diag.result)
    joint = {t.dataset: t.verdict for t in diag.result.floor_tests}
    out = []
    for v in getattr(diag, "residuals", ()):
        own = skip.get(v.name, frozenset({v.name}))
        left = [a for a in getattr(v, "left", ()) if not any(_own(n, own) for n in a.variables)]
        if left:
            # a residual above its own floor in a dataset whose joint test is at its floor
            # (a new user's altimeter: "validation g1" listed under "validation: at the
            # noise floor", what was above being the calibration)
            alone = (f" (above its own floor; {v.dataset} as a whole is at its floor)"
                     if joint.get(v.dataset) == "at" else "")
            out.append(f"{v.dataset} {_what(v)}{alone}: " + "; ".join(a.text for a in left))
    return out


def _strongest_left(diag: Any) -> str:
    lines = left_lines(diag)
    return f"; what is left: {lines[0]}" if lines else ""


def detectable_text(result: Result, cand: Any) -> str:
    """A candidate's minimal detectable effect in its unit (``—`` unknown;
    :func:`~symcal.revise.diagnose.detectable`)."""
    from symcal.revise.diagnose import detectable

    found = detectable(result, cand)
    if found is None:
        return "—"
    # a constant's, a parameter's or a reading's zero without a unit is a pure number (an
    # emissivity, a ratio), not a value in symcal's internal units
    plain = not found[1] and cand.basis.kind in ("fixed", "constant", "zero")
    return f"{found[0]:.4g}" if plain else _spread_text(*found)


def outliers_dominate(diag: Diagnosis) -> bool:
    """Whether outliers dominate the diagnosed fit (then they come before any missing
    effect)."""
    return bool(getattr(diag, "outliers_dominate", False))


def diagnosis_verdict(diag: Diagnosis) -> list[str]:
    """The verdict at the top of :func:`diagnosis_report`: where it fails, what to add,
    what cannot be calibrated.

    Uses only the diagnosis' result (success, its noise floors where known, its
    regressions and its null space), its significant candidates, and its
    ``uncalibratable`` candidates (real effects the constraints cannot determine) when it
    has them.

    Parameters
    ----------
    diag
        A diagnosis.

    Returns
    -------
    list of str
        The lines, without indentation: success or failure first.
    """
    result = diag.result
    floors = noise_floors(result)
    lines = [verdict_lines(result, floors)[0]]
    where = []
    outliers = getattr(diag, "outliers", None)
    if outliers is not None and outliers_dominate(diag):
        where.append(outlier_text(outliers) or "")
    tests = result.floor_tests
    family = family_verdicts(tests)
    where += [f"{t.dataset}: {floor_verdict(t)}" for t, v in zip(tests, family, strict=True)
              if v in ("above", "below")]
    where += alone_lines(result)
    worst = _worst_against_floor(result, floors)
    if worst is not None and worst[0].noise is not None and worst[0].noise.verdict == "above":
        where.append(str(_worst_text(result, floors)))
    above = references_above(result)
    if above:
        where.append("against the reference, above the noise floor: " + ", ".join(
            f"{s.dataset} {s.name} ({s.noise.ratio:.2f} ×)"    # type: ignore[union-attr]
            for s in above[:VERDICT_REGRESSIONS]))
    where += [_regression_text(r) for r in result.regressions[:VERDICT_REGRESSIONS]]
    if len(result.regressions) > VERDICT_REGRESSIONS:
        where.append(f"{len(result.regressions) - VERDICT_REGRESSIONS} more got worse (below)")
    if not where:
        if result.at_floor:
            where.append("nowhere: every dataset is at its noise floor ("
                         + "; ".join(f"{t.dataset} {_chi2_text(t)}" for t in tests) + ")")
        elif diag.significant:
            where.append("the residuals carry structure the model lacks (below)")
        else:
            where.append(f"nowhere these tests can see (noise floor unknown: "
                         f"{how_to_declare(result)})")
    lines.append(f"where it fails: {where[0]}")
    lines += where[1:]
    significant = diag.significant
    if not result.success:
        lines.append("what to add: nothing yet: the solve failed (above), and a candidate "
                     "tested where the solve stopped, not at a solution, says nothing about "
                     "the physics; fix the failure first" + (
                         f" (the {len(significant)} candidate(s) below are for reference "
                         "only)" if significant else ""))
    elif outliers is not None and outliers_dominate(diag):
        lines.append("what to add: a robust loss on the constraints with outliers (YAML "
                     "below); missing effects are looked for once outliers no longer "
                     "dominate")
    elif significant:
        more = (f" (and {len(significant) - 1} more significant, below)"
                if len(significant) > 1 else "")
        lines.append(f"what to add: {significant[0].label}{more}")
    elif getattr(diag, "outside", ()):
        lines.append("what to add: nothing of the search spaces; outside them: "
                     + "; ".join(diag.outside_words[c.label] for c in diag.outside))
    elif "above" in family:
        lines.append("what to add: no candidate effect passes the test, yet the residuals are "
                     "above the noise floor: structure remains that no candidate explains "
                     "(or the readings are noisier than declared)" + _strongest_left(diag))
    else:
        lines.append("what to add: nothing significant (no candidate effect passes the test)")
    cannot = []
    uncalibratable = tuple(getattr(diag, "uncalibratable", ()) or ())
    if uncalibratable:
        shown = ", ".join(c.label for c in uncalibratable[:3])
        more = f" and {len(uncalibratable) - 3} more" if len(uncalibratable) > 3 else ""
        cannot.append(f"{shown}{more} (real, but these constraints cannot determine it)")
    apart = references_apart(diag)
    if apart:
        cannot.append(f"{apart[0]} (real, not calibratable by these constraints: they are "
                      "at their floor)" + (f"; and {len(apart) - 1} more against the "
                                           "reference" if len(apart) > 1 else ""))
    if result.identifiability.deficiency:
        cannot.append(f"{result.identifiability.deficiency} parameter direction(s) the data "
                      "cannot determine")
    lines.append("what cannot be calibrated: " + ("; ".join(cannot) if cannot else
                                                  "nothing found"))
    reach = unvouched(diag)
    if reach:
        lines.append(unvouched_line(reach, '"Absorbed" and "Nearly absorbed" below'))
    shifted = noise_bias_line(diag)
    if shifted:
        lines.append(shifted)
    declared = declared_gauges_line(diag)
    if declared:
        lines.append(declared)
    lines += design_pointer(result)
    return lines


def noise_bias_line(diag: Any) -> str:
    """The verdict's line on the parameters the readings' own noise shifts by at least
    :data:`~symcal.analysis.noise_bias.NOISE_BIAS` standard errors (``""``: none)."""
    shifted = tuple(getattr(diag, "biased_by_noise", ()))
    if not shifted:
        return ""
    params = diag.result.params
    parts = []
    for name, shift, z in shifted[:4]:
        p = params[name]
        unit = f" {symbol(p.unit)}" if p.unit else ""
        parts.append(f"{name} by {z:+.1f} SE ({shift:+.3g}{unit}; corrected "
                     f"{estimate_text(p.value - shift, p.se)})")
    more = f" and {len(shifted) - 4} more" if len(shifted) > 4 else ""
    return ("what the readings' own noise shifts: " + ", ".join(parts) + more
            + ": second order in the declared noise, the constraints not linear in the "
              "readings (errors in variables): more rows shrink the standard errors, "
              "not the shift")


def declared_gauges_line(diag: Any) -> str:
    """The fixed parameters that set a gauge (a field's known magnitude, a shunt's
    certified resistance; those at zero apart, which may define a frame), and the
    constants the free parameters absorb exactly, or ``""``: the data cannot check them,
    and the parameters sharing their gauge are only as right as they are (a
    magnetometer's three scale factors 128-274 SE off, quiet, where the field's magnitude
    was 200 nT off)."""
    result = diag.result
    named: list[str] = []
    zeros: list[str] = []
    for name in sorted(dict(getattr(diag, "gauge_fixes", {}) or {})):
        p = result.params.get(name)
        if p is not None:
            (named if p.value != 0 else zeros).append(
                f"{name} = {p.value:.6g}{' ' + p.unit if p.unit else ''}")
    constants = _absorbed_constants(diag)
    if not named and not constants and not zeros:
        return ""
    parts = []
    if named:
        one = len(named) == 1
        parts.append(", ".join(named) + (" (fixed, it sets a gauge: " if one else
                                          " (fixed, each sets a gauge: ")
                     + "the parameters that share it follow its value unseen)")
    parts += constants
    if zeros:
        # a zero may define a frame (an axis's orientation: nothing to check) or claim a
        # sensor's zero: a new user's thermocouple offset was 97 SE off, quiet, where the
        # connector thermistor it shares a gauge with, fixed at 0 K, read 0.8 K high
        parts.append(", ".join(zeros) + " (fixed at zero, "
                     + ("it sets" if len(zeros) == 1 else "each sets")
                     + " a gauge: a definition where it orients or places a frame, else a "
                       "sensor's zero the data cannot check)")
    return ("the estimates are only as right as the declared "
            + ("value" if len(named) + len(constants) + len(zeros) == 1 else "values")
            + " the data cannot check: " + "; ".join(parts))


def _absorbed_constants(diag: Any) -> list[str]:
    """The constants whose being off the free parameters absorb exactly (a ground
    station's pressure that a barometer's scale factor multiplies; the local gravity a
    load cell's sensitivity multiplies), each with the parameters that follow it: on a
    drone's altimeter a pressure 1 hPa off put both scale factors 5-6 SE off, quiet,
    named only under "Absorbed" where the same value declared as a fixed parameter was
    named here."""
    declared = {k.key: k for k in diag.result.problem.constants}
    out = []
    for c in getattr(diag, "candidates", ()):
        if c.basis.kind != "constant" or not c.absorbed or not c.biases or \
                not c.basis.targets or c.basis.targets[0] not in declared:
            continue
        const = declared[c.basis.targets[0]]     # its key, value and unit as declared
        if const.value == 0:     # a reference point at zero (no power, no offset)
            continue
        shown = list(c.biases[:3]) + ([f"{len(c.biases) - 3} more"]
                                      if len(c.biases) > 3 else [])
        follow = shown[0] if len(shown) == 1 else ", ".join(shown[:-1]) + " and " + shown[-1]
        unit = const.unit
        out.append(f"{const.key} = {const.value:.6g}{' ' + symbol(unit) if unit else ''} "
                   f"(a constant {follow} absorb{'s' if len(c.biases) == 1 else ''} "
                   "exactly, following its value unseen)")
    return out


def design_pointer(result: Result) -> list[str]:
    """A verdict line pointing to ``symcal design`` when the last stage leaves a nearly
    flat direction (a parameter poorly determined by this motion), naming the scenario
    the calibration data were simulated from when there is one."""
    if not result.stages:
        return []
    near = result.stages[-1].conditioning_after.near_null
    if not near:
        return []
    spec = result.problem.datasets.get(result.problem.fit_dataset)
    scenario = getattr(spec, "scenario", None) if spec is not None else None
    combination = near[0][0]
    # the command as it runs: the combination's leading parameter at half its standard
    # error, the others held (a placeholder NAME=SE, run as printed, was refused)
    known = [(abs(c), name, se) for name, c in combination.coefficients.items()
             if name in result.params and (se := result.params[name].se)]
    options = "--optimize --target NAME=SE"
    if known:
        _, name, se = max(known)
        target = target_arg(name, 0.5 * se, result.params[name].unit)
        options = f"--optimize --target {target} --hold"
    return [f"poorly determined by this motion: {combination.text} (singular value "
            f"{near[0][1]:.1g} of the largest); "
            + design_sentence(result.problem.path, scenario or None, options)
            + " predicts another motion's standard errors before recording it"]


def diagnosis_report(diag: Diagnosis) -> str:
    """What `symcal diagnose` prints: the verdict, where the model fails, what got worse,
    which effect is missing."""
    result = diag.result
    floors = noise_floors(result)
    skip = self_referential(result)
    state = "" if result.success else "  *** FAILED ***"
    lines = [f"symcal diagnose: {result.name} ({result.problem_path}){state}", "", "Verdict"]
    lines += [f"  {ln}" for ln in diagnosis_verdict(diag)]
    lines += ["", "Where the model fails (after calibration; std of each residual and its "
              "noise floor where known, and, where it is not at its floor, the variables "
              "along which it varies most and its dominant period)"]
    for v in diag.residuals:
        std = float(np.std(v.after)) / v.scale
        stats = next((s for s in result.statistics
                      if (s.dataset, s.name) == (v.dataset, v.name)), None)
        floor = _floor_note(std, floors.get((v.dataset, v.name)), v.unit,
                            None if stats is None else stats.noise)
        lines.append(f"  {v.dataset} {_what(v)}: std {_spread_text(std, v.unit)}{floor}")
        noise = None if stats is None else stats.noise
        if noise is not None and noise.verdict in ("at", "below"):
            continue    # at its floor: binned by a noisy reading, η² is that noise's own
        for b in _findings(v.binned, skip.get(v.name, frozenset({v.name})))[:2]:
            lines.append(f"      varies with {b.variable}: η² = {b.eta2:.2f}")
        if v.periodogram is not None and float(np.max(v.periodogram.power)) > 0.1:
            lines.append(f"      dominant frequency: {v.periodogram.peak_text} "
                         f"(power {float(np.max(v.periodogram.power)):.2f})")
    left = left_lines(diag)
    if left:
        lines += ["", "What is left above the noise floor (binned means of each residual "
                  "along every variable and the strongest pairs, beyond what bins explain by "
                  "chance, as a share of its excess over the floor; shown whether or not a "
                  "candidate explains it)"]
        lines += [f"  {ln}" for ln in left]
        lines += [f"  {ln}" for ln in getattr(diag, "unsearched", ())]
    if result.regressions:
        lines += ["", "Worse after calibration (above its noise floor, χ²/dof grown from the "
                  "initial parameters by more than noise moves it; where the floor is "
                  f"unknown, a spread more than {REGRESSION_TOLERANCE:.0%} larger)"]
        lines += [f"  {_regression_text(r)} ({r.ratio:.2f} ×)" for r in result.regressions]
    ranked = list(diag.leads)
    outliers = getattr(diag, "outliers", None)
    if outliers is not None and (outliers.count or outliers_dominate(diag)):
        lines += ["", f"Outliers (checked before missing effects: residual rows beyond "
                  f"{THRESHOLD:g} robust standard deviations)"]
        lines += _outlier_lines(outliers)
    if outliers_dominate(diag):
        lines += ["", "Which effect is missing: not examined, since outliers dominate the fit "
                  "(tests for missing effects would follow the outliers); add the robust "
                  "loss above, solve and diagnose again"]
        return "\n".join(lines) + "\n"
    lines += ["", f"Which effect is missing ({diag.tested} candidate terms tested; family-wise "
              f"level {diag.alpha:g}, Bonferroni; indistinguishable candidates grouped)"]
    if not diag.significant and "above" in family_verdicts(result.floor_tests):
        lines.append("  no candidate effect is significant, yet the residuals are above the "
                     "noise floor: structure remains that no candidate of this library "
                     "explains")
    elif not diag.significant:
        lines.append("  no candidate effect is significant: the residuals look like noise to "
                     "this library of effects")
    rows = [["rank", "candidate", "removes", "F", "p", "significant", "detectable from"]]
    for i, c in enumerate(ranked[:10], start=1):
        group = f" (+{len(c.indistinguishable)} alike)" if c.indistinguishable else ""
        rows.append([str(i), c.label + group, f"{c.share:.1%}", f"{c.f_stat:.3g}",
                     f"{c.p_value:.2g}", "yes" if c.significant else "no",
                     detectable_text(result, c)])
    if len(rows) > 1:
        lines += _table(rows, "rlrrrlr")
        lines.append("  detectable from: the smallest such term (its RMS over the calibration "
                     "data, in the worst phase) the test finds with power 80 % at its level")
    for i, c in enumerate(diag.significant[:3], start=1):
        lines += ["", f"  {i}. {c.label}", "     " + diag.candidate_text(c)]
        if diag.yaml.get(c.label):
            lines += ["     To add it:"] + [f"       {ln}" if ln else ""
                                            for ln in diag.yaml[c.label].splitlines()]
    apart = references_apart(diag)
    if apart:
        lines += ["", "Against the reference, above the noise floor where the constraints "
                  "are at theirs (real, not calibratable by these constraints):"]
        lines += [f"  {ln}" for ln in apart]
    uncalibratable = tuple(getattr(diag, "uncalibratable", ()) or ())
    if uncalibratable:
        lines += ["", "Real, but these constraints cannot determine them (a reference or "
                  "another constraint can):"]
        for c in uncalibratable:
            lines += [f"  {c.label}", "     " + diag.candidate_text(c)]
    absorbed = [c for c in diag.candidates if c.absorbed and c.biases][:5]
    if absorbed:
        lines += ["", "Absorbed by the current parameters (invisible in these residuals; if "
                  "present, such an effect biases the parameters named):"]
        lines += [f"  {c.label}: would bias {', '.join(c.biases)}" for c in absorbed]
    lines += _nearly_lines(diag)
    lines += _space_lines(diag)
    return "\n".join(lines) + "\n"


#: Nearly absorbed candidates shown in the text (the JSON has up to 20).
NEARLY_SHOWN = 6


def unvouched(diag: Any) -> list[tuple[str, float]]:
    """The parameters a candidate the tests would miss could move far (see
    :mod:`symcal.revise.reliability`), each with the farthest, farthest first."""
    out: dict[str, float] = {}
    for c in getattr(diag, "candidates", ()):
        for name, value in getattr(c, "unseen", ()):
            out[name] = max(out.get(name, 0.0), value)
    return sorted(out.items(), key=lambda kv: -kv[1])


def unvouched_line(reach: list[tuple[str, float]], where: str) -> str:
    """The verdict's line on :func:`unvouched` parameters, pointing to ``where``."""
    return ("what the floor cannot vouch for: " + ", ".join(
        f"{name} (up to {_reach_text(value)} SE)" if math.isfinite(value)
        else f"{name} (by any amount: an effect it absorbs)" for name, value in reach[:4])
        + (f" and {len(reach) - 4} more" if len(reach) > 4 else "")
        + f": effects the parameters absorb, or nearly, would move them that far unseen "
          f"({where})")


def _reach_text(value: float) -> str:
    if not math.isfinite(value):
        return "any number of"
    return f"{value:.0f}" if value >= 10 else f"{value:.1f}"


def _nearly_lines(diag: Diagnosis) -> list[str]:
    """The candidates the parameters nearly absorb: how large each can be unseen and how
    far it would move them."""
    nearly = [c for c in diag.candidates if getattr(c, "unseen", ()) and not c.absorbed]
    if not nearly:
        return []
    lines = ["", "Nearly absorbed by the current parameters (each may be present up to "
             "the size shown and go unseen, moving the parameters named by up to that many "
             "of their standard errors: the noise floor does not vouch for them)"]
    for c in nearly[:NEARLY_SHOWN]:
        moved = ", ".join(f"{name} {_reach_text(v)} SE" for name, v in c.unseen)
        lines.append(f"  {c.label}: unseen up to {detectable_text(diag.result, c)}; "
                     f"would move {moved}")
    if len(nearly) > NEARLY_SHOWN:
        lines.append(f"  and {len(nearly) - NEARLY_SHOWN} more (the JSON lists up to 20)")
    return lines


def _space_lines(diag: Diagnosis) -> list[str]:
    """Which candidates were searched, which fixed parameters fix a gauge, and the
    candidates never proposed because they would re-open one."""
    lines = []
    spaces = tuple(getattr(diag, "spaces", ()) or ())
    if spaces:
        lines += ["", "Searched (each sensor's candidate effects; a `candidates:` section on "
                  "the model, the instance or the problem changes it)"]
        lines += [f"  {text}" for text in spaces]
    fixes = dict(getattr(diag, "gauge_fixes", {}) or {})
    if fixes:
        lines += ["", "Fixed parameters that fix a gauge (never tested as off; no candidate "
                  f"that re-opens one is proposed): {', '.join(sorted(fixes))}"]
    reopened = tuple(getattr(diag, "reopened", ()) or ())
    if reopened:
        lines += ["", "Never proposed:"]
        lines += [f"  {c.label}: {c.reopens}" for c in reopened[:8]]
        if len(reopened) > 8:
            lines.append(f"  and {len(reopened) - 8} more")
    return lines


def variable_units(result: Result) -> dict[str, str]:
    """The declared unit of every variable a residual may be binned along or drawn
    against: data columns, sensor signals and named expressions (values are in internal
    units; see :func:`symcal.base.units.axis_unit`)."""
    problem = result.problem
    units = {col: spec.unit for col, spec in problem.column_specs.items()}
    units.update({sig.name: sig.unit for sig in problem.signals})
    units.update({q.name: q.unit for q in problem.expressions})
    return units


def _unit_of(units: Mapping[str, str], name: Any) -> str:
    name = str(name)
    if name in units:
        return units[name]
    if name.startswith("phase of ") and " (mod " in name:
        return units.get(name[len("phase of "):].split(" (mod ", 1)[0], "")
    return ""


def diagnosis_document(diag: Diagnosis, series: bool = False) -> dict[str, Any]:
    """The diagnosis as plain data for ``--json``, the figures and the HTML page.

    :meth:`Diagnosis.to_dict <symcal.revise.diagnose.Diagnosis.to_dict>` with, where it lacks
    them: ``regressions`` (:attr:`Result.regressions <symcal.calibrate.result.Result.regressions>`),
    ``verdict`` (:func:`diagnosis_verdict`), the result's ``statistics`` (each with its
    ``floor`` and ``chi2_dof``), ``floor_tests`` and ``at_floor``, and per residual its
    ``noise_floor`` (display unit, None where unknown) and ``chi2_dof``, the variables it
    ``contains`` whole
    (:func:`self_referential`, left out of its findings and figures) and the ``unit`` of
    each variable its structure and series are drawn along.

    Parameters
    ----------
    diag
        A diagnosis.
    series
        Include every residual's series (the plotting contract).

    Returns
    -------
    dict
        JSON-ready; unit strings as declared.
    """
    doc = diag.to_dict(series=series)
    result = diag.result
    floors = noise_floors(result)
    skip = self_referential(result)
    units = variable_units(result)
    doc.setdefault("regressions", [r.to_dict() for r in result.regressions])
    doc.setdefault("verdict", diagnosis_verdict(diag))
    doc.setdefault("statistics", [s.to_dict() for s in result.statistics])
    doc.setdefault("floor_tests", [t.to_dict() for t in result.floor_tests])
    doc.setdefault("at_floor", result.at_floor)
    doc.setdefault("references_apart", references_apart(diag))
    doc.setdefault("left", left_lines(diag))
    doc.setdefault("unsearched", list(getattr(diag, "unsearched", ())))
    doc.setdefault("outside", [
        {"label": c.label, "output": c.output, "variable": c.basis.variable,
         "f_stat": c.f_stat, "p_value": c.p_value, "text": diag.outside_words[c.label]}
        for c in getattr(diag, "outside", ())])
    tests = {(s.dataset, s.name): s.chi2_dof for s in result.statistics}
    for row in doc.get("residuals") or []:
        name = str(row.get("name"))
        unit = "" if row.get("unit") in (None, "(internal)") else str(row.get("unit"))
        floor = floors.get((str(row.get("dataset")), name))
        row.setdefault("noise_floor",
                       None if floor is None or unit not in DISPLAY_UNITS
                       else floor / DISPLAY_UNITS[unit])
        row.setdefault("chi2_dof", tests.get((str(row.get("dataset")), name)))
        row.setdefault("contains", sorted(skip.get(name, frozenset({name}))))
        for b in row.get("binned") or []:
            b.setdefault("unit", _unit_of(units, b.get("variable")))
        x = (row.get("series") or {}).get("x")
        if isinstance(x, dict):
            x.setdefault("unit", _unit_of(units, x.get("name")))
    return doc


# ----------------------------------------------------------------------- experiment design


def _se_text(value: float | None) -> str:
    return "only in combination" if value is None else f"{value:.4g}"


def _motion_text(value: Any) -> str:
    if isinstance(value, tuple):
        return f"[{value[0]:.4g}, {value[1]:.4g}]"
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def design_report(design: Design, result: Result | None = None) -> str:
    """The text report of ``symcal design``: the motion before and after, the binding
    limits, the targets, and per parameter the predicted standard error before and after
    design (and the one a given result reports).

    Parameters
    ----------
    design
        What :func:`symcal.experiment.optimize.design` returned (or a design of the given scenario
        alone).
    result
        A calibration result to compare the predictions with (``--result``).
    """
    base, final = design.baseline, design.final
    optimised = design.designed is not None and design.designed is not design.baseline
    lines = [f"Design of run '{base.run}' of scenario '{base.scenario.name}' "
             f"(last stage '{base.stage.name}': what the calibration reports)"]
    detect = design.detect
    if optimised:
        texts = [t.text for t in design.targets] + ([detect.text] if detect else [])
        goal = (f"criterion {design.criterion} with the most observations the limits allow"
                if design.criterion else "targets " + ", ".join(texts)
                + " with the fewest observations")
        early = not design.converged and design.all_met
        lines.append(f"  goal: {goal}; {design.message}"
                     + (" (stopped before converging: the targets are met on the exact "
                        "prediction, but fewer observations may do)" if early else ""))
        space = base.scenario.design
        limits = {} if space is None else space.bounds
        rows = [["motion", "given", "designed", "limits"]]
        units = design.units
        for key in design.before:
            lim = limits.get(key)
            shown = f"{key} ({units[key]})" if units.get(key) else key
            rows.append([shown, _motion_text(design.before[key]),
                         _motion_text(design.after[key]),
                         "fixed" if lim is None else _motion_text(tuple(lim))])
        lines += ["  " + r for r in _table(rows, "llll")]
        lines.append("  binding limits: " + (", ".join(design.binding) or "none"))
        for t in design.targets:
            se = final.se.get(t.name)
            ok = design.met.get(t.name, False)
            unit = final.units.get(t.name, "")
            lines.append(f"  target {t.text}: predicted {_se_text(se)} {unit} "
                         f"({'met' if ok else 'NOT met: the best reachable within the limits'})")
        if detect is not None:
            ok = design.met.get(detect.label, False)
            lines.append(f"  target {detect.text}: {detect.label} detectable from "
                         f"{_mde_text(design.mde_after, detect.unit)} (given motion: "
                         f"{_mde_text(design.mde_before, detect.unit)}; "
                         f"{detect.describe()}) "
                         f"({'met' if ok else 'NOT met: the best reachable within the limits'})")
        worse = design.worse
        if design.held:
            lines.append("  held (--hold): every other parameter at most its standard error "
                         "on the given motion" + (": all held" if design.holds_met else ""))
        if (design.targets or detect is not None) and (
                not all(design.met.values()) or not design.holds_met):
            lines.append(f"  meeting every target on the designed motion would need about "
                         f"{design.needed_n} observations")
        if worse:
            trade = ("" if design.held or not (design.targets or detect is not None) else
                     "; to keep them, design with --hold (or give one a --target of its own)")
            lines.append("  less precise than on the given motion: " + ", ".join(
                f"{name} (no longer determined on its own)" if f is None
                else f"{name} ({f:.3g}× the standard error)" for name, f in worse.items())
                + trade)
        blind = design.blind
        if blind:
            two = [k for k, v in blind.items() if v == 0.0]
            narrow = [f"{k} (over {v:.2%} of its given range)" for k, v in blind.items()
                      if v > 0.0]
            said = []
            if two:
                one = len(two) == 1
                said.append(f"{', '.join(two)} only at the two ends of "
                            f"{'its' if one else 'their'} range (every draw dwells there): "
                            f"no term curved in {'it' if one else 'them'} (a quadratic) can "
                            "be told from an offset and a gain")
            if narrow:
                said.append(f"{', '.join(narrow)} barely varies: hardly any term in "
                            f"{'it' if len(narrow) == 1 else 'them'} can be seen")
            lines.append("  what the designed motion cannot show: " + "; ".join(said)
                         + ". A calibration on it alone can end at the floor with such "
                         "an effect absorbed into the parameters; to keep it testable, "
                         "limit dwell below 1 (or the state's range) in the design "
                         "section, or add the term you fear as a target "
                         "(--target 'mde(TERM)=AMPLITUDE')")
        repeats = design.repeats
        if repeats:
            units = {c.name: c.unit for c in design.scenario.columns}
            rounded = ", ".join(f"{name} (rounded to {step:g}"
                                f"{' ' + units[name] if units.get(name) else ''})"
                                for name, step in repeats.items())
            lines.append(
                f"  what the designed motion cannot average: the rounding of {rounded}, "
                "which the motion reads at repeated poses: each pose rounds the same value "
                "every time, so its rounding does not average over the draws, whereas the "
                "standard errors predicted here (and those a solve reports on such data) "
                "take it for independent noise; what depends on that reading can end far "
                "more wrong than its standard error, at the floor. Limit dwell below 1 in "
                "the design section (poses that differ round differently), or record the "
                "reading with a dither of at least half a step")
    ident0, ident1 = base.identifiability, final.identifiability
    lost = (f" (the given motion's: {ident0.rank}; the designed motion loses "
            f"{ident0.rank - ident1.rank})" if optimised and ident1.rank < ident0.rank else "")
    lines.append(f"  rank {ident1.rank} of {ident1.n_free} free parameters{lost}; condition "
                 f"number of the identifiable part {ident0.condition_number:.4g}"
                 + (f" -> {ident1.condition_number:.4g}" if optimised else ""))
    for combo in ident1.null_space:
        lines.append(f"    cannot be determined: {combo.text}")
    for combo in ident1.identifiable_combinations:
        lines.append(f"    determined only in combination: {combo.text} ± "
                     f"{_se_text(combo.se)}")
    res = ", ".join(
        f"{name} {base.residual_std[name]:.3g}"
        + (f" -> {final.residual_std[name]:.3g}" if optimised else "")
        + f" {symbol(base.units[name])} (noise alone {final.residual_noise[name]:.3g})"
        for name in base.stage.constraints)
    lines.append(f"  predicted residual std: {res}")
    head = ["parameter", "unit", "SE given motion"] + (["SE designed"] if optimised else [])
    head += ["SE of --result"] if result is not None else []
    rows = [head]
    reported = {} if result is None else {p.name: p.se for p in result.params.values()}
    for name, se in base.se.items():
        row = [name, symbol(base.units.get(name, "")), _se_text(se)]
        if optimised:
            row.append(_se_text(final.se.get(name)))
        if result is not None:
            row.append(_se_text(reported.get(name)))
        rows.append(row)
    lines.append("")
    lines.append("Predicted standard errors (no data recorded)")
    lines += ["  " + r for r in _table(rows, "ll" + "r" * (len(head) - 2))]
    return "\n".join(lines) + "\n"


def _mde_text(value: float | None, unit: str) -> str:
    """A minimal detectable effect (internal units) in ``unit``."""
    if value is None:
        return "nowhere (determined only in combination)"
    return f"{value / unit_size(unit or '1'):.3g} {symbol(unit)}"


def design_document(design: Design, scenario_path: str | None) -> dict[str, Any]:
    """The ``--json`` document of ``symcal design``: ``{"parameters": {NAME:
    {"predicted_se": ..., "baseline_se": ...}}, "binding": [...], "scenario": PATH}``, with
    standard errors in each parameter's unit (null: determined only in combination),
    ``"held"`` (the parameters ``--hold`` held at their given standard errors),
    ``"blind"`` (``{STATE: share}``: 0 for a state the designed motion holds at the two
    ends of its range, else the share of its given range it still spans, below 5 %),
    ``"repeats"`` (``{COLUMN: step}``: a quantized reading the designed motion reads at
    repeated poses, whose rounding does not average, the step in the column's unit) and
    ``"worse"`` (``{NAME: factor}``: the growth of a standard error on the designed motion
    beyond 1.1×; null: no longer determined on its own); with
    a term to make detectable also ``"detectable": {"term", "target", "parameters",
    "amplitude", "unit", "alpha", "tested", "level", "power", "baseline_mde",
    "predicted_mde", "met"}`` (amplitudes in ``unit``; an MDE null where the term's
    coefficients are determined only in a combination)."""
    final = design.final
    doc: dict[str, Any] = {
        "parameters": {name: {"predicted_se": final.se.get(name), "baseline_se": se}
                       for name, se in design.baseline.se.items()},
        "binding": list(design.binding),
        "held": [t.name for t in design.held],
        "blind": design.blind,
        "repeats": design.repeats,
        "worse": design.worse,
        "scenario": scenario_path,
    }
    detect = design.detect
    if detect is not None:
        from symcal.analysis.discovery import POWER

        scale = unit_size(detect.unit or "1")
        doc["detectable"] = {
            "term": detect.label, "target": detect.text, "parameters": list(detect.names),
            "amplitude": detect.value / scale, "unit": detect.unit, "alpha": detect.alpha,
            "tested": detect.tested, "level": detect.level, "power": POWER,
            "baseline_mde": None if design.mde_before is None else design.mde_before / scale,
            "predicted_mde": None if design.mde_after is None else design.mde_after / scale,
            "met": design.met.get(detect.label, False)}
    return doc
