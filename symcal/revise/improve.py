"""`symcal improve`: the model-improvement loop, run for the user.

diagnose → apply the top calibratable candidate (as files: a model extension and a
problem overlay, or the switch to the implicit model) → solve again on the same data →
keep it only if the held-out residuals and the BIC improve → repeat until the diagnosis
is quiet or no candidate pays.  Every revision is an overlay (``extends:``) in the output
folder, so each round is a few lines a person can read, and the last one kept is written
as ``final.yaml``.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from symcal.analysis.discovery import Candidate
from symcal.analysis.fit import Spread
from symcal.base.digits import estimate_text
from symcal.base.errors import SymcalError
from symcal.base.files import write_output
from symcal.base.progress import Bars, Report, reporting
from symcal.base.units import symbol
from symcal.calibrate.result import Result, file_hashes
from symcal.calibrate.solve import solve, solve_without_floors, with_floors
from symcal.data.dataset import Dataset
from symcal.data.loading import load_datasets
from symcal.language.fields import plain_name
from symcal.language.yamlio import dump_yaml
from symcal.problem.build import load_problem
from symcal.problem.symbolic import Problem
from symcal.revise.diagnose import GROUP as DIAGNOSED
from symcal.revise.diagnose import Diagnosis, diagnose, on_reference
from symcal.revise.effects import write_revision
from symcal.revise.previous import clear_previous
from symcal.revise.watch import Moved, Watch, new_parameters, same_fit, wald, watch

#: A candidate is not solved when the diagnosis predicts its held-out constraint
#: residuals grow by more than this (a mean log ratio, +0.1 %, of their RMS and of their
#: standard deviations alike): the solve would find the same to within the prediction's
#: accuracy and refuse it.
SURELY_WORSE = 0.001
#: How many of the leading candidates are tried in a round before giving up.
TRIES = 3
#: A reference comparison may get worse by at most this fraction.
WORSE = 0.10
#: A candidate is not solved where the diagnosis predicts that a reference comparison
#: gets worse by more than :data:`WORSE` and this share beyond it (the prediction's
#: error: on the dual courier's refused candidates it was within 1 % of the solve).
COMPARISON_MARGIN = 0.05
#: How many members of a group of indistinguishable candidates are tried.
GROUP = DIAGNOSED
#: A member of a group is solved too, after one that pays, when the diagnosis predicts
#: at least this share of that one's held-out improvement for it (it may fit as well and
#: put a physical parameter elsewhere); the others are not worth a solve.
CLOSE = 0.8
#: Two revisions whose BIC differ by less than this fit about equally (Kass and Raftery:
#: below 10 the evidence for one over the other is not strong).
EQUAL_BIC = 10.0
#: Members that pay are ranked first by whether their BIC is within this of the lowest
#: (Kass and Raftery: from 2, positive evidence), then by their held-out change.  The
#: held-out residuals' spreads alone favour a member that scales a noisy reading down (a
#: GNSS height's quadratic shrinks its 0.5 m noise in every residual it enters) over the
#: effect itself (a barometer's reference temperature, one parameter fewer, its BIC
#: lower by 5): the BIC, of the whitened fit, is not fooled by a scale.
CLEAR_BIC = 2.0
#: A BIC lower by more than this is strong evidence (Kass and Raftery's "very strong"):
#: only then does a revision that leaves a parameter already there undetermined rank
#: before one that does not (see _rank).
STRONG_BIC = 10.0
#: A revision may make an existing parameter's standard error at most this many times
#: larger (beyond it the new term is nearly aliased with what the model has).
INFLATION = 5.0


@dataclass(frozen=True)
class Round:
    """One revision: what was added (None for the starting problem), its file and fit,
    what the new term did to the parameters already there (``watch``) and what the data
    could not tell it apart from (``ambiguous``: sentences)."""

    index: int
    added: str | None
    problem_file: Path
    result: Result
    significant: int
    watch: Watch = Watch()
    ambiguous: tuple[str, ...] = ()

    def notes(self) -> list[str]:
        """The round's sentences about the physics: moved, correlated, ambiguous."""
        return [*self.watch.words(self.added or ""), *self.ambiguous]

    def to_dict(self) -> dict:
        """The round as ``symcal improve --json`` prints it."""
        return {"added": self.added, "problem": str(self.problem_file),
                "statistics": [s.to_dict() for s in self.result.statistics],
                "floor_tests": [t.to_dict() for t in self.result.floor_tests],
                "at_floor": self.result.at_floor,
                "significant": self.significant, "bic": self.result.bic,
                "aic": self.result.aic, "success": self.result.success,
                "parameters": self.watch.to_dict(), "ambiguous": list(self.ambiguous),
                "notes": self.notes()}


@dataclass(frozen=True)
class Improvement:
    """The outcome of :func:`improve`: the kept rounds (round 0 is the starting problem),
    whether the last diagnosis was quiet, the final problem file, what was tried and
    rejected (label → reason), and the significant candidates of the last diagnosis that
    are aliased with the parameters already there (label → reason).

    Quiet means the model is at the noise floor its readings' declared noise sets on every
    dataset (:attr:`at_floor`) and no *calibratable* candidate is left: a candidate the
    last round tried, with every member of its group, and found nearly aliased with
    existing parameters (their standard errors grow more than :data:`INFLATION` times)
    cannot be determined by these constraints; it is reported apart, as the diagnosis
    reports candidates only a reference reveals.  When no candidate is left above the
    floor, structure remains that no candidate explains: not quiet.  Where the floor is
    unknown (no noise declared, none estimable), quiet only means that no candidate is
    significant.  When the starting problem's solve fails, no revision is tried (a
    candidate tested where a failed solve stopped says nothing of the physics): one
    round, not quiet."""

    rounds: tuple[Round, ...]
    quiet: bool
    final_problem: Path
    rejected: tuple[tuple[str, str], ...]
    last: Diagnosis
    aliased: tuple[tuple[str, str], ...] = ()
    # the round each of ``rejected`` was tried in (a candidate refused in round 1 may be
    # tried again, and refused again, in round 2)
    rejected_rounds: tuple[int, ...] = ()
    # the round limit, where the loop stopped at it with significant candidates left
    limit: int | None = None

    @property
    def at_floor(self) -> bool | None:
        """Whether the last kept round is at the noise floor on every dataset (None: the
        floor is unknown somewhere)."""
        return self.rounds[-1].result.at_floor

    @property
    def candidates_left(self) -> bool:
        """Whether a significant calibratable candidate is left (not aliased)."""
        aliased = dict(self.aliased)
        return any(c.label not in aliased for c in self.last.significant)

    @property
    def unverified(self) -> tuple[tuple[str, tuple[Moved, ...]], ...]:
        """The kept terms no held-out run checked (:data:`UNCHECKED`) that moved a
        parameter already there by more than :data:`~symcal.revise.watch.MOVED` of its
        standard errors, with those moves: on the fitted run alone a term standing in for
        another effect (a step, a coupling the library lacks) fits as well as the true
        one, and the loop cannot tell which moved them.  A new user's clock lab, its PPS
        stepping by 25 ns/s halfway, ended quiet at the floor on one run with its aging
        rates 11 SE and turnover temperatures 22-41 SE off."""
        return tuple((r.added, r.watch.moved) for r in self.rounds[1:]
                     if r.added and UNCHECKED in r.ambiguous and r.watch.moved)

    @property
    def undecided(self) -> tuple[str, ...]:
        """The sentences of kept rounds whose term the data cannot tell from another that
        fits about as well and puts a physical parameter more than 3 standard errors
        elsewhere (:func:`_ambiguity`): the loop chose one, the data did not.  A new
        user's wind mast, its Pitot reading 0.03 m/s low (a Reynolds-number effect),
        kept an offset on the sonic that the data could not tell from one on the Pitot
        and ended quiet, exit 0, with the cup's offset 20 SE off."""
        return tuple(s for r in self.rounds[1:] for s in r.ambiguous
                     if s.startswith(AMBIGUOUS))

    @property
    def verified(self) -> bool:
        """Quiet, and nothing :attr:`unverified` or :attr:`undecided`: the loop's
        success."""
        return self.quiet and not self.unverified and not self.undecided

    def tried_in(self) -> tuple[int | None, ...]:
        """The round each rejected candidate was tried in (None where not recorded)."""
        if len(self.rejected_rounds) == len(self.rejected):
            return tuple(self.rejected_rounds)
        return (None,) * len(self.rejected)

    def to_dict(self) -> dict:
        """``{"rounds": [...], "quiet": ..., "final_problem": ..., "at_floor": ...}`` (plus
        what was rejected and why)."""
        return {"rounds": [r.to_dict() for r in self.rounds], "quiet": self.quiet,
                "verified": self.verified,
                "unverified": [{"added": label, "moved": [m.to_dict() for m in moved]}
                               for label, moved in self.unverified],
                "undecided": list(self.undecided), "round_limit": self.limit,
                "final_problem": str(self.final_problem), "at_floor": self.at_floor,
                "rejected": [{"label": label, "reason": why, "round": k}
                             for (label, why), k in zip(self.rejected, self.tried_in(),
                                                        strict=True)],
                "aliased": [{"label": label, "reason": why} for label, why in self.aliased],
                "outside": [{"label": c.label, "p_value": c.p_value,
                             "text": self.last.outside_words.get(c.label, "")}
                            for c in self.last.outside]}


def held_out_change(new: Result, old: Result, kind: str | None = None) -> float:
    """Mean log ratio of the residual sizes on the held-out datasets (every dataset but
    the fitted one; only residuals of ``kind`` when given;
    :meth:`~symcal.analysis.fit.Spread.size`), new over old: negative when the new model
    predicts them better; 0 when there is none."""
    ratios = _held_out_ratios(new, old, kind)
    return float(np.mean(ratios)) if ratios else 0.0


def _held_out_ratios(new: Result, old: Result, kind: str | None, scatter: bool = False
                     ) -> list[float]:
    """Each held-out residual's log ratio of sizes (RMS; standard deviation where the
    mean is an arbitrary zero, or where ``scatter`` asks), new over old (none: nothing
    held out, or no residual of ``kind`` there)."""
    def size(spread: Spread, remove_mean: bool) -> float:
        return spread.std if scatter else spread.size(remove_mean)

    ratios = []
    fit = new.problem.fit_dataset
    for s in new.statistics:
        if s.dataset == fit or (kind is not None and s.kind != kind):
            continue
        try:
            before = size(old.stat(s.name, s.dataset, "(internal)").after, s.remove_mean)
        except KeyError:
            continue
        after = size(s.after, s.remove_mean)
        if before > 0 and after > 0:
            ratios.append(np.log(after / before))
    return ratios


def _held_out_worse(new: Result, old: Result) -> str | None:
    """Why the held-out constraint residuals do not fall (None where they do, or where
    none are held out): on average over them, their RMS does not fall, nor does their
    standard deviation with the RMS grown by at most :data:`MEAN_SLACK`.  The RMS sees an
    offset a term removes, which moves the mean alone; the standard deviation sees a term
    the held-out run hardly exercises, whose estimate's noise moves that run's mean
    either way (the courier's fly-by and one segment's lateral term: RMS +0.2 %,
    standard deviation -0.1 %), but not a mean it moves far (a term fitted at one
    temperature that shifts a run at another).  The diagnosis predicts both
    (:func:`_predicted_worse`)."""
    sizes = _held_out_ratios(new, old, "constraint")
    if not sizes:
        return None
    return _no_fall(sizes, _held_out_ratios(new, old, "constraint", scatter=True), 0.0)


#: How far the held-out RMS may grow (a mean log ratio, +0.5 %) for a term whose held-out
#: standard deviation falls to count as falling (:func:`_held_out_worse`).
MEAN_SLACK = 0.005


def _no_fall(sizes: list[float], scatter: list[float], margin: float) -> str | None:
    """Why the held-out residuals do not fall, from their log ratios of sizes (RMS) and
    of standard deviations: the mean of the first not below ``margin``, nor that of the
    second with the first below ``margin`` + :data:`MEAN_SLACK` (None where one is)."""
    change = float(np.mean(sizes))
    spread = float(np.mean(scatter)) if scatter else change
    if change < margin or (spread < margin and change < margin + MEAN_SLACK):
        return None
    return ("the held-out constraint residuals do not fall (mean change "
            f"{np.expm1(change):+.1%} in RMS, {np.expm1(spread):+.1%} in standard "
            "deviation)")


#: How a sentence of two revisions the data cannot tell apart begins (:func:`_ambiguity`).
AMBIGUOUS = "the data cannot tell "

#: The note of a round kept where no dataset's constraints are held out.
UNCHECKED = ("kept on the BIC and the Wald test alone: no dataset's constraint residuals "
             "are held out to check that it predicts data it was not fitted on (every "
             "dataset but the fitted one is held out: add a second run)")


def _pays(new: Result, old: Result, alpha: float,
          physical: set[str] | None = None) -> str | None:
    """None when ``new`` is better than ``old``, else why not: the solve succeeds with the
    same weighting (a term reading a column of undeclared noise changes it), the BIC
    falls, the new term's coefficients are not zero within their noise (a Wald test at
    ``alpha``), the held-out constraint residuals fall (on average; where none are held
    out, this test cannot be made and the others decide), no existing
    parameter becomes much less determined (:data:`INFLATION`) while the old model was
    already at its noise floor, and no reference comparison (the fit never uses one, on
    the fitted dataset too) gets worse by more than :data:`WORSE`."""
    if not new.success:
        return "the solve failed"
    if new.problem.weighting != old.problem.weighting:
        problem = new.problem
        unread = sorted({c for q in problem.constraints for c in problem.undeclared(q.sx)})
        why = (f"it reads {', '.join(unread)} whose noise is not declared, so " if unread
               else "")
        return (f"{why}the weighting changes from '{old.problem.weighting}' to "
                f"'{problem.weighting}' and the BIC does not compare"
                + (" (declare the noise)" if unread else ""))
    if new.bic >= old.bic:
        return f"BIC does not fall ({old.bic:.1f} → {new.bic:.1f})"
    names = new_parameters(new, old)
    test = wald(new, names) if names else None
    if test is not None and test[1] >= alpha:
        return (f"its coefficients fit to zero within their noise (Wald χ² = {test[0]:.3g}, "
                f"p = {test[1]:.2g})")
    worse = _held_out_worse(new, old)              # none held out: not checked
    if worse is not None:
        return worse
    inflated = _inflated(new, old, physical) if old.at_floor is not False else None
    if inflated:
        return inflated
    for s in new.statistics:       # a reference is no part of the fit, on any dataset
        if s.kind == "comparison":
            before, after = _spread(old, s.name, s.dataset), s.after.size(s.remove_mean)
            if before and after > (1 + WORSE) * before:
                return (f"{s.dataset} {s.name} against the reference gets worse "
                        f"({before:.3g} → {after:.3g} internal units)")
    return None


def _inflated(new: Result, old: Result, physical: set[str] | None = None) -> str | None:
    """Why the new terms are nearly aliased with parameters already there (a standard
    error of one of the ``physical`` parameters, default every one, grows more than
    :data:`INFLATION` times), or None.  A term an earlier round added may trade against
    the new one: that is the terms' structure changing, not the physics."""
    before = {p.name: p.se for p in old.params.values() if p.se
              and (physical is None or p.name in physical)}
    worst = max(((p.se / before[p.name], p.name) for p in new.params.values()
                 if p.se and p.name in before), default=None)
    if worst is not None and worst[0] > INFLATION:
        return (f"it is nearly aliased with the parameters already there: the standard "
                f"error of {worst[1]} grows {worst[0]:.0f} times")
    return None


def _spread(result: Result, name: str, dataset: str) -> float | None:
    try:
        stat = result.stat(name, dataset, "(internal)")
        return stat.after.size(stat.remove_mean)
    except KeyError:
        return None


@dataclass(frozen=True)
class _Kept:
    """A revision that pays: its label, file, fit, and what it could not be told apart
    from (sentences)."""

    label: str
    path: Path
    result: Result
    ambiguous: tuple[str, ...] = ()
    written: frozenset[Path] = frozenset()    # the files written for it (path included)


def _best_of_group(
    diag: Diagnosis, lead: Candidate, directory: Path, name: str,
    datasets: Mapping[str, Dataset], result: Result, rejected: list[tuple[str, str]],
    say: Callable[[str], None], alpha: float, physical: set[str],
) -> _Kept | None:
    """Try the lead and the members of its group (the constraints cannot tell them apart;
    a held-out reference may): keep the one that pays and predicts the held-out data
    best, or None.  Members that pay as well (BIC within :data:`EQUAL_BIC`) but put a
    physical parameter elsewhere (beyond 3 standard errors) are named: the data cannot
    tell them apart."""
    labels = [lead.label, *lead.indistinguishable[:GROUP - 1]]
    predicted = {label: predicted_change(diag, label) for label in labels}
    labels.sort(key=lambda label: _level(predicted[label]))
    paying: list[tuple[float, str, Path, Result]] = []
    written: dict[str, set[Path]] = {}
    for i, label in enumerate(labels):
        if paying and not _close(predicted[label], predicted[paying[0][1]]):
            continue       # the diagnosis predicts it does much worse than one that pays
        why = _predicted_worse(diag, [label])
        if why is not None:
            rejected.append((label, why))
            say(f"{label}: {why}")
            continue
        before = _models(directory)
        path = _revision(diag, label, directory, f"{name}_try{i}")
        written[label] = {path} | (_models(directory) - before)
        revised = _load_revision(path)
        new = _trial(revised, datasets, result)
        why = _pays(new, result, alpha, physical)
        if why is None:
            paying.append((held_out_change(new, result), label, path, new))
            continue
        rejected.append((label, why))
        say(f"tried {label}: not kept, {why}")
        used = {f.resolve() for r in paying for f in r[3].problem.source_files()}
        _remove({f for f in written[label] if f.resolve() not in used})
    if not paying:
        return None
    fits = [t[3] for t in paying]
    paying.sort(key=lambda t: _rank(diag, t[1], t[3], t[0], fits, result))
    _, label, path, new = paying[0]
    used = {f.resolve() for f in new.problem.source_files()}
    for change, other, _, other_new in paying[1:]:
        _remove({f for f in written[other] if f.resolve() not in used})
        why = _not_kept(diag, label, new, paying[0][0], other, other_new, change, fits,
                        result)
        rejected.append((other, why))
        say(f"tried {other}: it pays, but not kept: {why}")
    final = _renamed(path, name)
    said = (_ambiguity(label, new, other, other_new, physical, result)
            for _, other, _, other_new in paying[1:])
    ambiguous = tuple(text for text in said if text)
    return _Kept(label, final, with_floors(_rebound(new, final)), ambiguous,
                 frozenset(written[label] - {path} | {final}))


def _rank(diag: Diagnosis, label: str, new: Result, change: float,
          paying: Sequence[Result], old: Result
          ) -> tuple[bool, bool, bool, bool, float, float]:
    """The order of revisions that pay (``new``, the revision of candidate ``label`` of
    ``diag``, solved from ``old``): those whose BIC is within :data:`STRONG_BIC` of the
    lowest first, and among them one that leaves the parameters already there determined
    before one that does not (:func:`_inflated`: its better fit is no strong evidence; a
    new user's magnetometer whose datasheet gain tempco was off kept a term linear in the
    x reading, correlation +1.0000 with the x scale factor, whose standard error grew 73
    times, on 3 of 10 seeds, quiet with the scale factor 36 of those standard errors from
    the truth, where the tempco made a parameter fitted as well);
    then those within :data:`CLEAR_BIC`; then a term on a calibrated sensor before one
    on the problem's reference (:func:`_on_reference`); then by their
    held-out change (``change``, to :data:`SAME_CHANGE`); one fit written two ways, the
    one that moves a declared value least (:func:`_declared_change`), else in the order
    it was tried, the group's lead first."""
    best = min(r.bic for r in paying)
    return (new.bic > best + STRONG_BIC, _inflated(new, old) is not None,
            new.bic > best + CLEAR_BIC,
            _on_reference(diag, label, old), _level(change), _declared_change(new, old))


def _candidate(diag: Diagnosis, label: str) -> Candidate | None:
    """The diagnosis's candidate ``label`` (None where it has none of that name)."""
    return next((c for c in diag.candidates if c.label == label), None)


def _declared_change(new: Result, old: Result) -> float:
    """How far the revision moves a value the user declared: of its new parameters that
    were a constant or a fixed parameter (a declared value, not zero), the largest
    relative change (0 for none).  Where two revisions are one fit written two ways, the
    data cannot choose; the declared values can: a flow pair's reference temperature of
    the density law made a parameter went from 20 to -2803 degC, where its expansion
    coefficient, the same fit, went from 2.1e-4 to 5.2e-4."""
    freed = [name for name, p in new.params.items() if not p.fixed
             and (name not in old.params or old.params[name].fixed)]
    found = [abs(p.value - p.initial) / abs(p.initial)
             for p in (new.params[name] for name in freed) if p.initial]
    return max(found, default=0.0)


def _on_reference(diag: Diagnosis, label: str, result: Result) -> bool:
    """Whether the candidate ``label`` changes a sensor whose every parameter is fixed (a
    term, a fixed parameter freed, a model constant, its clock:
    :func:`~symcal.revise.diagnose.on_reference`): the sensor the problem trusts.
    Where a calibrated sensor's term fits about as well, the reference is left as
    declared: a term in the reference's own noisy reading scales its noise down and fits
    a drone altimeter's barometer temperature as well (BIC equal), with the laser's
    scale 500 standard errors off."""
    cand = _candidate(diag, label)
    return cand is not None and on_reference(cand, result.problem) is not None


#: Held-out changes (mean log ratios) closer than this are the same: a term on either
#: side of a constraint that reads it alike (a reference's or the calibrated sensor's
#: dependence on the temperature) is one fit, and rounding must not choose between them.
SAME_CHANGE = 1e-9


def _level(change: float) -> float:
    """``change`` to :data:`SAME_CHANGE` (for ordering)."""
    return round(change / SAME_CHANGE) * SAME_CHANGE if np.isfinite(change) else change


def _rebound(result: Result, path: Path) -> Result:
    """``result`` of a revision, for the same revision renamed ``path`` (only its name
    changed: the estimate, statistics and analysis are those of the same model on the
    same data, so it is not solved again)."""
    problem = load_problem(path)
    if problem.parameter_names != result.problem.parameter_names:
        raise RuntimeError(f"symcal renamed a revision into {path} and it changed")
    return replace(result, problem=problem, files=file_hashes(problem))


def predicted_change(diag: Diagnosis, label: str) -> float:
    """The diagnosis's prediction for a candidate: the mean log ratio of the held-out
    constraint residuals' spreads after and before solving again with it (the fitted
    dataset's where none is held out; 0 without a prediction)."""
    found = _predicted_ratios(diag, label, True) or _predicted_ratios(diag, label, False)
    return float(np.mean(found)) if found else 0.0


def _predicted_ratios(diag: Diagnosis, label: str, held_out: bool) -> list[float]:
    """The log ratios of the spreads the diagnosis predicts for a candidate, after over
    before, of the constraint residuals held out (or fitted)."""
    cand = _candidate(diag, label)
    return [] if cand is None else _ratios(diag, cand.reduction, held_out)


def _ratios(diag: Diagnosis, reduction: Mapping[str, tuple[float, float]],
            held_out: bool) -> list[float]:
    """The log ratios of predicted spreads (``"DATASET/NAME"`` → (now, new)), new over
    now, of the constraint residuals held out (or fitted)."""
    fit = diag.result.problem.fit_dataset
    kinds = {(s.dataset, s.name): s.kind for s in diag.result.statistics}
    out = []
    for key, (now, new) in reduction.items():
        dataset, _, name = key.partition("/")
        if (dataset != fit) == held_out and kinds.get((dataset, name)) == "constraint" \
                and now > 0 and new > 0:
            out.append(float(np.log(new / now)))
    return out


def _predicted_worse(diag: Diagnosis, labels: Sequence[str]) -> str | None:
    """Why a candidate (or several added at once) is not worth a solve: the diagnosis
    predicts (by a Gauss-Newton refit, :func:`~symcal.revise.whitened.predict`) that the
    held-out constraint residuals do not fall, their RMS and their standard deviations
    alike (:func:`_held_out_worse`), by more than :data:`SURELY_WORSE`; else
    None (also where nothing is held out: that test is not made).  The model's own
    approximation is always solved: a change of the model's structure, not a small term,
    its linear prediction can miss (predicted +0.3 % on the dual courier with a latency,
    it paid when solved)."""
    if any(c.basis.kind == "approximation" for c in diag.candidates if c.label in labels):
        return None
    if len(labels) == 1:
        cand = _candidate(diag, labels[0])
        pair = ({}, {}) if cand is None else (cand.reduction, cand.scatter)
    else:
        pair = ({}, {}) if diag.together is None else diag.together(labels)
    sizes, scatter = (_ratios(diag, p, True) for p in pair)
    why = (_no_fall(sizes, scatter, SURELY_WORSE) if sizes else None) or \
        _comparison_worse(diag, pair[0])
    return None if why is None else f"not solved: the diagnosis predicts that {why}"


def _comparison_worse(diag: Diagnosis, sizes: Mapping[str, tuple[float, float]]
                      ) -> str | None:
    """Why the predicted sizes (``"DATASET/NAME"`` → (now, new)) fail the check of the
    reference comparisons :func:`_pays` makes after the solve (one grows by more than
    :data:`WORSE`, here with :data:`COMPARISON_MARGIN` for the prediction's error), or
    None.  The dual courier's last round solved ten candidates that each made a
    reference comparison 13-95 % worse, as predicted, once the held-out check passed
    terms whose RMS the prediction said would fall (6.6 s, against the 5 s a round may
    take)."""
    stats = {(s.dataset, s.name): s for s in diag.result.statistics}
    worst: tuple[float, str, float, float, str] | None = None
    for key, (now, new) in sizes.items():
        dataset, _, name = key.partition("/")
        stat = stats.get((dataset, name))
        if stat is not None and stat.kind == "comparison" and now > 0 and \
                new > (1 + WORSE) * (1 + COMPARISON_MARGIN) * now and \
                (worst is None or new / now > worst[0]):
            worst = (new / now, f"{dataset} {name}", now, new, stat.unit)
    if worst is None:
        return None
    unit = f" {symbol(worst[4])}" if worst[4] else ""
    return (f"{worst[1]} against the reference gets worse ({worst[2]:.3g} → "
            f"{worst[3]:.3g}{unit})")


def _close(score: float, best: float) -> bool:
    """Whether a predicted change is close enough to a paying one's to be solved too."""
    return best >= 0 or score <= CLOSE * best


#: What is said of two members that are the same fit written two ways.
SAME_WORDS = ("they are one fit written two ways (every residual the same to rounding): "
              "no experiment separates them, and the parameter means something else in "
              "each; keep the one whose parameters mean what you know")


#: Why no ``symcal design`` target separates two revisions that fit about equally and
#: put a parameter more than 3 standard errors apart: each already determines it better
#: than they differ (a target of a third of the difference, once printed here, is met by
#: the data as they are, and designing for it changed nothing).
APART_WORDS = ("each determines it more precisely than the two differ: the parameter means "
               "something else in each, and a more precise run of the same kind does not "
               "tell which is right; a run in other conditions, where the two predict "
               "different readings, or knowing which effect is physical, does")


def _ambiguity(label: str, new: Result, other: str, other_new: Result,
               physical: set[str], old: Result) -> str:
    """A sentence when two revisions fit about equally (BIC within :data:`EQUAL_BIC`) and
    put a physical parameter more than 3 standard errors apart, else ""; where the other
    fits better but leaves a parameter undetermined (:func:`_inflated`), it says so."""
    if abs(new.bic - other_new.bic) > EQUAL_BIC:
        return ""
    for name in sorted(physical):
        a, b = new.params.get(name), other_new.params.get(name)
        if a is None or b is None or not a.se or not b.se:
            continue
        if abs(a.value - b.value) > 3 * max(a.se, b.se):
            target = SAME_WORDS if same_fit(new, other_new) else APART_WORDS
            why = ""
            if other_new.bic < new.bic and _inflated(other_new, old) is not None and \
                    _inflated(new, old) is None:
                why = ("; the first is kept, the second leaves a parameter already there "
                       f"undetermined, its standard error more than {INFLATION:g} times "
                       "the one before")
            return (f"{AMBIGUOUS}{label} from {other} (BIC {new.bic:.1f} and "
                    f"{other_new.bic:.1f}{why}): they give {name} = "
                    f"{estimate_text(a.value, a.se)} ± {a.se:.2g} and "
                    f"{estimate_text(b.value, b.se)} ± {b.se:.2g}"
                    f"{' ' + a.unit if a.unit else ''}; {target}")
    return ""


def _trial(revised: Problem, datasets: Mapping[str, Dataset], result: Result) -> Result:
    """The revision solved on the same data, started where the last kept model ended (its
    free parameters at their estimates, a new term's coefficients at zero): the stages
    then take a few steps each instead of starting again from the file's values.  Its
    noise floors are left out (:func:`_pays` does not read them): the revision kept gets
    them (:func:`~symcal.calibrate.solve.with_floors`)."""
    start = {name: p.value for name, p in result.params.items()
             if not p.fixed and name in revised.index
             and not revised.parameters[revised.index[name]].fixed}
    return solve_without_floors(
        revised, {n: d for n, d in datasets.items() if n in revised.datasets}, start)


def _models(directory: Path) -> set[Path]:
    """The model files in the output folder's ``models/`` (revisions' own)."""
    return set((directory / "models").glob("*.yaml"))


def _remove(paths: set[Path]) -> None:
    """Remove the files a revision that was not kept wrote (never a file it found)."""
    for path in paths:
        path.unlink(missing_ok=True)


def _renamed(path: Path, name: str) -> Path:
    """The revision ``path`` (written by :func:`write_revision` or a variant's overlay,
    named after its file) as ``name.yaml`` beside it, named ``name``."""
    head, renamed = dump_yaml({"problem": path.stem}), dump_yaml({"problem": name})
    text = path.read_text(encoding="utf-8")
    assert text.startswith(head), f"{path} does not begin with {head!r}"
    final = path.with_name(f"{name}.yaml")
    write_output(final, renamed + text[len(head):])
    path.unlink()
    return final


def _load_revision(path: Path) -> Problem:
    """The revision symcal just wrote; a revision that does not load is removed (never
    left in the output folder) and reported as an internal fault."""
    try:
        return load_problem(path)
    except SymcalError as exc:
        path.unlink(missing_ok=True)
        raise RuntimeError(f"symcal wrote a revision it cannot read ({exc})") from None


def siblings(diag: Diagnosis, lead: Candidate) -> tuple[Candidate, ...]:
    """The same effect in the lead's sibling instances (instances of the same model file):
    for each, its most significant candidate of the same kind, order and period on the
    same output, when the diagnosis finds one significant, on a variable no other member
    uses (two siblings' terms in the same variable are alike in a constraint where both
    sensors enter, as the segments of one axis do in g_p: one of them is an alias).  One
    physical effect of a sensor model (a lateral dependence of every platen segment) is
    then added to every instance that shows it in one round, each with its own
    coefficients.  None while the model has an approximation of its own (an implicit
    variant): its residue, significant or not, looks like the same effect in every
    sibling."""
    problem = diag.result.problem
    inst, _, output = lead.output.partition(".")
    if inst not in problem.instances or diag.variant is not None:
        return ()   # the model's own approximation shows in every sibling: it goes first
    model = problem.instances[inst].model.path
    shape = (lead.basis.kind, lead.basis.order, lead.basis.period, bool(lead.basis.angle))
    found: dict[str, Candidate] = {}
    used = {lead.basis.variable}
    for cand in diag.significant:
        other, _, out = cand.output.partition(".")
        if (other != inst and other not in found and out == output
                and cand.basis.variable not in used
                and other in problem.instances
                and problem.instances[other].model.path == model
                and (cand.basis.kind, cand.basis.order, cand.basis.period,
                     bool(cand.basis.angle)) == shape):
            found[other] = cand
            used.add(cand.basis.variable)
    return tuple(found.values())


def _try_siblings(
    diag: Diagnosis, lead: Candidate, single: _Kept | None,
    directory: Path, name: str, datasets: Mapping[str, Dataset], result: Result,
    rejected: list[tuple[str, str]], say: Callable[[str], None], alpha: float,
    physical: set[str],
) -> _Kept | None:
    """The lead with the same effect in its sibling instances, in one revision, when it
    pays and beats the lead alone (``single``) on BIC: a sibling candidate that is only
    significant because it is aliased with the lead adds parameters the BIC refuses."""
    also = siblings(diag, lead)
    if not also:
        return single
    label = "; ".join(c.label for c in (lead, *also))
    unsolved = _predicted_worse(diag, [c.label for c in (lead, *also)])
    if unsolved is not None:
        rejected.append((label, unsolved))
        say(f"{label}: {unsolved}")
        return single
    before = _models(directory)
    path = write_revision(diag.result.problem, lead, directory, f"{name}_all", also)
    written = {path} | (_models(directory) - before)
    revised = _load_revision(path)
    new = _trial(revised, datasets, result)
    why = _pays(new, result, alpha, physical)
    if why is None and single is not None and new.bic >= single.result.bic:
        why = (f"its BIC ({new.bic:.1f}) is not below that of {single.label} alone "
               f"({single.result.bic:.1f})")
    if why is not None:
        rejected.append((label, why))
        say(f"tried {label}: not kept, {why}")
        _remove(written)
        return single
    final = _renamed(path, name)
    return _Kept(label, final, with_floors(_rebound(new, final)),
                 written=frozenset(written - {path} | {final}))


def _alternatives(diag: Diagnosis, lead: Candidate, kept: _Kept, result: Result,
                  tried: set[str]) -> list[Candidate]:
    """The significant leads not tried this round whose BIC the diagnosis predicts
    (:attr:`~symcal.analysis.discovery.Candidate.bic_change`) clearly below both the kept
    lead's prediction and the revision kept's own BIC (by more than :data:`CLEAR_BIC`),
    best first, at most :data:`TRIES`.  The most significant lead is tested beyond its
    simpler terms; added alone it can fit worse than another: a scale's thermal
    expansion is then stood in for by the encoder's product with the temperature and
    the interferometer's coefficient, hundreds of standard errors off."""
    if lead.basis.kind == "approximation" or lead.bic_change is None:
        return []
    bar = min(lead.bic_change, kept.result.bic - result.bic) - CLEAR_BIC
    found = [c for c in diag.significant if c.label not in tried
             and c.basis.kind != "approximation"
             and c.bic_change is not None and c.bic_change < bar]
    return sorted(found, key=lambda c: c.bic_change or 0.0)[:TRIES]


def _best_lead(
    diag: Diagnosis, lead: Candidate, kept: _Kept, tried: set[str], directory: Path,
    name: str, datasets: Mapping[str, Dataset], result: Result,
    rejected: list[tuple[str, str]], say: Callable[[str], None], alpha: float,
    physical: set[str],
) -> _Kept:
    """The revision kept this round: ``kept`` (the first lead's that pays) or one of the
    :func:`_alternatives` that pays and fits better (ranked as a group's members are,
    :func:`_rank`); the others' files are removed and a sentence says why each paying one
    was not kept (and where two fit about equally but put a physical parameter apart)."""
    contenders = [kept]
    for j, rival in enumerate(_alternatives(diag, lead, kept, result, tried)):
        say(f"{rival.label}: the diagnosis predicts a BIC of "
            f"{result.bic + (rival.bic_change or 0.0):.1f} with it, below the "
            f"{kept.result.bic:.1f} of {kept.label}: solved too")
        single = _best_of_group(diag, rival, directory, f"{name}_alt{j}", datasets,
                                result, rejected, say, alpha, physical)
        found = _try_siblings(diag, rival, single, directory, f"{name}_alt{j}", datasets,
                              result, rejected, say, alpha, physical)
        if found is not None:
            contenders.append(found)
    if len(contenders) == 1:
        return kept
    changes = {c.label: held_out_change(c.result, result) for c in contenders}
    fits = [c.result for c in contenders]
    contenders.sort(key=lambda c: _rank(diag, c.label, c.result, changes[c.label], fits,
                                        result))
    best, *others = contenders
    used = {f.resolve() for f in best.result.problem.source_files()}
    for other in others:
        _remove({f for f in other.written if f.resolve() not in used})
        why = _not_kept(diag, best.label, best.result, changes[best.label], other.label,
                        other.result, changes[other.label], fits, result)
        rejected.append((other.label, why))
        say(f"tried {other.label}: it pays, but not kept: {why}")
    if best is kept:
        final = kept.path
    else:
        final = _renamed(best.path, name)
        best = replace(best, path=final, result=_rebound(best.result, final),
                       written=best.written - {best.path} | {final})
    said = (_ambiguity(best.label, best.result, other.label, other.result, physical, result)
            for other in others)
    return replace(best, ambiguous=best.ambiguous + tuple(text for text in said if text))


def _not_kept(diag: Diagnosis, label: str, kept: Result, kept_change: float,
              other_label: str, other: Result, change: float,
              fits: Sequence[Result], old: Result) -> str:
    """Why a revision that pays (``other_label``'s fit ``other``) was not kept beside
    ``label``'s (``kept``): the first rule of :func:`_rank` that orders them."""
    mine = _rank(diag, label, kept, kept_change, fits, old)
    theirs = _rank(diag, other_label, other, change, fits, old)
    bics = f"BIC {kept.bic:.1f} against {other.bic:.1f}"
    rule = next((k for k, (a, b) in enumerate(zip(mine, theirs, strict=True)) if a != b),
                None)
    if rule in (0, 2) or (rule is None and kept.bic < other.bic - EQUAL_BIC):
        return f"{label} fits these data better ({bics})"
    if rule == 1:
        return (f"{label} fits about as well ({bics}) and leaves the parameters already "
                f"there determined; with the other, {_inflated(other, old)}")
    if rule == 3:
        return (f"{label} fits about as well ({bics}) on a sensor the problem calibrates; "
                "the other revises its reference")
    if rule == 4:
        return (f"{label} fits about as well ({bics}) and predicts the held-out data "
                "better")
    if rule == 5:
        return f"{label} fits about as well ({bics}) and moves a declared value less"
    return (f"{label} fits as well ({bics}) and the data cannot choose: it was tried "
            "first")


def _revision(diag: Diagnosis, cand_label: str, directory: Path, name: str) -> Path:
    problem = diag.result.problem
    cand = next(c for c in (*diag.candidates, *diag.uncalibratable) if c.label == cand_label)
    if cand.basis.kind == "approximation":
        assert diag.variant is not None
        path = directory / f"{name}.yaml"
        for target, text in diag.variant.files(directory).items():
            write_output(target, text)
        write_output(path, diag.variant.overlay(Path(problem.path), name, directory))
        return path
    return write_revision(problem, cand, directory, name)


def improve(
    problem: Problem | str | Path,
    out: str | Path,
    data: Mapping[str, Dataset | str | Path] | None = None,
    max_rounds: int = 5,
    alpha: float = 0.01,
    drop_invalid: bool = False,
    progress: Callable[[str], None] | None = None,
    bars: Bars | None = None,
) -> Improvement:
    """Run the improvement loop on ``problem`` and write every revision into ``out``.

    Parameters
    ----------
    problem
        The starting problem file, or a loaded :class:`~symcal.problem.symbolic.Problem`
        (its file: every revision is an overlay that extends it).
    out
        The folder for the revisions (``PROBLEM_roundK.yaml``, named after the problem's
        file, their models in ``models/``) and ``final.yaml``; created if absent.
    data
        Datasets replacing the problem's (objects or files), as ``--data``.
    max_rounds
        At most this many revisions are kept.
    alpha
        The diagnosis's family-wise significance level.
    drop_invalid
        Drop rows with NaN/inf instead of refusing the data.
    progress
        Called with each line of progress (:mod:`symcal.base.progress`): what each round
        tries and keeps (None: no lines).
    bars
        Progress bars (:func:`symcal.base.progress.terminal_bars`): one meter counting
        the rounds kept (at most ``max_rounds``), the latest round's line beside it
        (then not passed to ``progress``).  None: no bars.

    Returns
    -------
    Improvement
    """
    with reporting(progress, bars, "improve", total=max_rounds, unit="round") as report:
        return _improve(problem, out, data, max_rounds, alpha, drop_invalid, report)


def _improve(problem: Problem | str | Path, out: str | Path,
             data: Mapping[str, Dataset | str | Path] | None, max_rounds: int, alpha: float,
             drop_invalid: bool, report: Report) -> Improvement:
    say = report.line
    directory = Path(out)
    directory.mkdir(parents=True, exist_ok=True)
    if isinstance(problem, Problem):
        current, problem = problem, Path(problem.path)
    else:
        current = load_problem(problem)
    datasets = load_datasets(current, data, drop_invalid)
    stem = plain_name(Path(problem).stem)   # revisions are named after the file
    cleared = clear_previous(directory, stem)
    if cleared:
        say(f"removed the previous run's {len(cleared)} file(s) from {directory}")
    result = solve(current, datasets)
    diag = diagnose(result, alpha, report=False)
    rounds = [Round(0, None, Path(problem), result, len(diag.significant))]
    physical = {n for n, p in result.params.items() if not p.fixed}
    rejected: list[tuple[str, str]] = []
    if result.success:
        say(f"round 0: {current.name}: {len(diag.significant)} significant candidate(s)")
    else:    # candidates tested where a failed solve stopped say nothing of the physics
        say(f"round 0: {current.name}: the solve failed: no revision is tried")
    last_try = len(rejected)
    tried_in: list[int] = []      # the round of each of rejected
    ran = 0
    for k in range(1, max_rounds + 1):
        tried_in += [ran] * (len(rejected) - len(tried_in))
        if not diag.significant or not result.success:
            break
        ran = k
        last_try = len(rejected)
        kept = None
        name = f"{stem}_round{k}"

        def say_round(line: str, k: int = k) -> None:
            say(f"round {k}: {line}")

        # every round tries its leads afresh: what did not pay against the last model
        # may pay against this one (the approximation once the effect is in, say)
        leads = list(diag.significant)
        # the model's own approximation is a known defect, not a hypothesis: it goes
        # first, and the effects are then looked for in the model that has it right
        leads.sort(key=lambda c: c.basis.kind != "approximation")
        tried: set[str] = set()
        for lead in leads[:TRIES]:
            tried.update((lead.label, *lead.indistinguishable))
            single = _best_of_group(diag, lead, directory, name, datasets, result,
                                    rejected, say_round, alpha, physical)
            kept = _try_siblings(diag, lead, single, directory, name, datasets, result,
                                 rejected, say_round, alpha, physical)
            if kept is not None:
                kept = _best_lead(diag, lead, kept, tried, directory, name, datasets,
                                  result, rejected, say_round, alpha, physical)
                break
        if kept is None:
            break
        seen = watch(kept.result, result, physical, kept.path)
        zero = _now_zero(kept.result, rounds, alpha) + _reads_ahead(diag, kept, result)
        if not _held_out_ratios(kept.result, result, "constraint"):
            zero += (UNCHECKED,)
        result = kept.result
        last_try = len(rejected)
        diag = diagnose(result, alpha, report=False)
        rounds.append(Round(k, kept.label, kept.path, result, len(diag.significant), seen,
                            kept.ambiguous + zero))
        report.step(f"round {k}: added {kept.label}: {len(diag.significant)} significant "
                    "candidate(s) left")
        for line in rounds[-1].notes():
            say(f"round {k}: {line}")
    final = directory / "final.yaml"
    base = Path(os.path.relpath(rounds[-1].problem_file.resolve(), directory.resolve()))
    given, unnamed = _given_files(current, data, directory)
    doc = f"the last revision symcal improve kept ({len(rounds) - 1} round(s))"
    if unnamed:
        doc += (f"; fitted on data given in memory ({', '.join(unnamed)}), not on the "
                "datasets the problem file names: solve it with the same data")
    write_output(final, dump_yaml({
        "problem": f"{stem}_final", "extends": base.as_posix(), "doc": doc,
        **({"datasets": given} if given else {})}))
    aliased = _aliased(diag, rejected[last_try:])
    left = [c for c in diag.significant if c.label not in dict(aliased)]
    quiet = (result.success and not left and result.at_floor is not False
             and not diag.outside)
    tried_in += [ran] * (len(rejected) - len(tried_in))
    limit = max_rounds if len(rounds) - 1 == max_rounds and left else None
    return Improvement(tuple(rounds), quiet, final, tuple(rejected), diag, aliased,
                       tuple(tried_in), limit)


def _reads_ahead(diag: Diagnosis, kept: _Kept, old: Result) -> tuple[str, ...]:
    """Where the kept revision is a delay and the data put it clearly below zero (by more
    than 2 standard errors): the sentence that says so.  No sensor reads ahead: a negative
    delay of one sensor is, to first order, the other readings of its constraints lagging
    by as much, written on this one (a flow pair's Coriolis meter, the reference, 0.2 s
    early, where the turbine was 0.2 s late)."""
    cand = _candidate(diag, kept.label)
    if cand is None or cand.basis.kind != "latency":
        return ()
    out = []
    for name in new_parameters(kept.result, old):
        p = kept.result.params[name]
        if p.se is not None and p.value < -2.0 * p.se:
            delay = f"{estimate_text(-p.value, p.se)} ± {p.se:.2g} {p.unit}".rstrip()
            out.append(f"{cand.basis.variable}'s delay {name} is negative: its readings "
                       f"come {delay} early, which no sensor does; to first order it is "
                       f"the other readings of its constraints lagging by {delay}, "
                       f"written on {cand.basis.variable}: check which sensor's clock is "
                       "late before you keep it")
    return tuple(out)


def _given_files(problem: Problem, data: Mapping[str, Dataset | str | Path] | None,
                 directory: Path) -> tuple[dict[str, dict[str, str]], list[str]]:
    """``final.yaml``'s ``datasets``: each dataset given as a file (``--data NAME=PATH``)
    in place of the problem's own, its path relative to ``directory`` and its role as
    the problem resolved it, so that the final problem is solved on the data the loop
    was; and the names of those given in memory (a file cannot name them)."""
    files: dict[str, dict[str, str]] = {}
    unnamed = []
    for name, given in (data or {}).items():
        if isinstance(given, Dataset):
            unnamed.append(name)
            continue
        target = Path(given).resolve()
        try:
            where = Path(os.path.relpath(target, directory.resolve())).as_posix()
        except ValueError:         # another drive: no relative path
            where = target.as_posix()
        files[name] = {"path": where, "role": problem.datasets[name].role}
    return files, unnamed


def _now_zero(new: Result, rounds: list[Round], alpha: float) -> tuple[str, ...]:
    """Sentences for terms earlier rounds added that fit to zero in ``new``: the new term
    explains what they stood in for (they stay in the chain of revisions; the verdict
    says so rather than keep them silently)."""
    out = []
    for earlier, later in zip(rounds, rounds[1:], strict=False):
        names = new_parameters(later.result, earlier.result)
        test = wald(new, names) if names else None
        if test is not None and test[1] >= alpha:
            out.append(f"{later.added} (round {later.index}) now fits to zero (Wald χ² = "
                       f"{test[0]:.3g}, p = {test[1]:.2g}): the new term explains what it "
                       "stood in for")
    return tuple(out)


def _aliased(diag: Diagnosis, tried: list[tuple[str, str]]) -> tuple[tuple[str, str], ...]:
    """The last diagnosis's significant candidates that the last round found aliased with
    existing parameters: every member of their group that was tried (the lead, and those
    the diagnosis predicted as good) was."""
    why = dict(tried)
    out = []
    for cand in diag.significant:
        members = [cand.label, *cand.indistinguishable[:GROUP - 1]]
        reasons = [why[m] for m in members if m in why]
        if reasons and all(r.startswith("it is nearly aliased") for r in reasons):
            out.append((cand.label, reasons[0]))
    return tuple(out)
