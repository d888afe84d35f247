"""The physics watched while terms are added: what a new term does to the parameters
already there, and whether it carries anything at all.

- **fits to zero**: the new term's coefficients, jointly, within their noise (a Wald
  test at the diagnosis's level): the term is not kept.
- **moves a parameter**: an existing parameter shifted by more than :data:`MOVED` of its
  standard error (the old estimate was biased by the missing effect, or the new term
  stands in for another one);
- **correlates**: a new coefficient correlated with an existing parameter beyond
  :data:`CORRELATED` (the data can hardly tell them apart), or an existing standard error
  grown more than :data:`GROWN` times.

None of these is ever silent: each is a sentence of the round's verdict, with the
experiment that would separate them (a ``symcal design`` target).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.special

from symcal.base.digits import estimate_text
from symcal.base.units import UnitError, parse_unit
from symcal.calibrate.result import Result
from symcal.experiment.command import design_sentence, target_arg
from symcal.revise.effects import centre_variable

#: A parameter moved by more than this many of its old standard errors is reported.
MOVED = 3.0
#: A new coefficient correlated beyond this with an existing parameter is reported.
CORRELATED = 0.99
#: An existing standard error grown more than this many times is reported.
GROWN = 3.0


def new_parameters(new: Result, old: Result) -> list[str]:
    """The free parameters of ``new`` that ``old`` does not have."""
    return [n for n, p in new.params.items() if n not in old.params and not p.fixed]


def wald(new: Result, names: list[str]) -> tuple[float, float] | None:
    """The Wald test of ``names`` jointly zero in ``new``: (χ², p), None without a
    covariance for them."""
    unc = new.uncertainty
    index = [unc.names.index(n) for n in names if n in unc.names]
    if not index or len(index) != len(names):
        return None
    cov = np.asarray(unc.covariance)[np.ix_(index, index)]
    if not np.all(np.isfinite(cov)):
        return None
    value = np.array([new.params[n].value for n in names])
    se = np.sqrt(np.diag(cov))
    if not np.all(se > 0):
        return None
    # in standard units: the coefficients' own units can differ by many orders of
    # magnitude (a quadratic's 3.8e-27 beside a linear part's 1.2e-9), where a
    # pseudo-inverse of the covariance as it is drops the smaller direction
    z = value / se
    chi2 = float(z @ np.linalg.pinv(cov / np.outer(se, se), hermitian=True) @ z)
    return chi2, float(scipy.special.chdtrc(len(index), chi2))   # scipy.stats.chi2.sf's own


@dataclass(frozen=True)
class Moved:
    """An existing parameter the new term moved: old and new value ± se, in ``unit``."""

    name: str
    old: float
    old_se: float
    new: float
    new_se: float
    unit: str

    @property
    def shift(self) -> float:
        """The shift in old standard errors."""
        return abs(self.new - self.old) / self.old_se if self.old_se > 0 else float("inf")

    def to_dict(self) -> dict:
        """Plain data."""
        return {"name": self.name, "old": self.old, "old_se": self.old_se, "new": self.new,
                "new_se": self.new_se, "unit": self.unit, "shift_se": self.shift}


@dataclass(frozen=True)
class Watch:
    """What a kept term did to the parameters already there; ``settled`` when the new
    model is at its noise floor and the old one was above it (the moves are then the
    bias the missing effect caused)."""

    moved: tuple[Moved, ...] = ()
    correlated: tuple[tuple[str, str, float], ...] = ()   # (new, existing, correlation)
    grown: tuple[tuple[str, float, float], ...] = ()      # (existing, old se, new se)
    design: str = ""
    settled: bool = False
    largest_growth: tuple[str, float] | None = None          # (existing, se ratio)
    largest_correlation: tuple[str, str, float] | None = None  # (new, existing, corr)
    # the new term's centres: (constant, variable, value, unit), where the parameters
    # already there now hold (a sensitivity at the run's mean temperature)
    centres: tuple[tuple[str, str, float, str], ...] = ()

    def words(self, added: str) -> list[str]:
        """The verdict's sentences: the term's effect on the parameters already there,
        and what is beyond the thresholds."""
        out = []
        parts = []
        if self.largest_growth is not None:
            name, ratio = self.largest_growth
            parts.append(f"standard errors of the parameters already there changed by "
                         f"{ratio:.3g}× at most ({name})")
        if self.largest_correlation is not None:
            new, existing, corr = self.largest_correlation
            parts.append(f"its largest correlation with one of them is {corr:+.3f} "
                         f"({new} with {existing})")
        if parts:
            out.append(f"with {added}: " + "; ".join(parts))
        for key, variable, value, unit in self.centres:
            local = key.split(".", 1)[-1]
            say = " (25 °C, say)" if _temperature(unit) else ""
            out.append(f"the term is zero at {variable} = {value:g} {unit} ({key}): the "
                       f"parameters already there now hold at that {variable}, not at a "
                       f"datasheet's reference; to have them hold at one{say}, "
                       f"write its value as {local}'s in the model file and solve again")
        if self.moved:
            ranked = sorted(self.moved, key=lambda m: -m.shift)
            shown = "; ".join(
                f"{m.name} {estimate_text(m.old, m.old_se)} ± {m.old_se:.2g} → "
                f"{estimate_text(m.new, m.new_se)} ± {m.new_se:.2g} "
                f"{m.unit} ({m.shift:.3g} se)".replace("  ", " ") for m in ranked[:3])
            more = f"; and {len(ranked) - 3} more" if len(ranked) > 3 else ""
            tied = sorted({m.name for m in ranked} & (
                {e for _, e, _ in self.correlated} | {n for n, _, _ in self.grown}))
            if self.settled and not tied:
                why = ("the old estimates were biased by the missing effect (the model is "
                       "now at its noise floor)")
            elif self.settled:
                why = (f"the model is now at its noise floor, but {', '.join(tied)} "
                       f"{'is' if len(tied) == 1 else 'are'} nearly aliased with the new "
                       "term (below): the new values depend on how the term is written (its "
                       "variable, its centre) as much as on the data, and the term may "
                       "stand in for another effect")
            else:
                why = ("either the old estimates were biased by the missing effect, or the "
                       "new term stands in for another one")
            out.append(f"with {added}, {len(ranked)} parameter(s) moved by more than "
                       f"{MOVED:g} of their standard errors: {shown}{more}: {why}")
        for new, existing, corr in self.correlated:
            out.append(f"{new} correlates {corr:+.4f} with {existing}: these data can hardly "
                       "tell them apart")
        for name, before, after in self.grown:
            out.append(f"the standard error of {name} grew from {before:.2g} to {after:.2g}")
        if self.design and (self.correlated or self.grown or not self.settled):
            out.append(self.design)
        return out

    def to_dict(self) -> dict:
        """Plain data (``symcal improve --json``)."""
        return {"moved": [m.to_dict() for m in self.moved],
                "correlated": [{"new": n, "existing": e, "correlation": c}
                               for n, e, c in self.correlated],
                "grown": [{"name": n, "se_before": b, "se_after": a}
                          for n, b, a in self.grown],
                "design": self.design, "settled": self.settled,
                "centres": [{"constant": k, "variable": v, "value": x, "unit": u}
                            for k, v, x, u in self.centres],
                "largest_growth": None if self.largest_growth is None else {
                    "name": self.largest_growth[0], "ratio": self.largest_growth[1]},
                "largest_correlation": None if self.largest_correlation is None else {
                    "new": self.largest_correlation[0],
                    "existing": self.largest_correlation[1],
                    "correlation": self.largest_correlation[2]}}


def watch(new: Result, old: Result, physical: set[str], problem_file: Path) -> Watch:
    """What ``new`` (with a term ``old`` lacks) did to the physical parameters ``old``
    has (free in both)."""
    moved, grown = [], []
    growth: tuple[str, float] | None = None
    for name in sorted(physical):
        a, b = old.params.get(name), new.params.get(name)
        if a is None or b is None or a.fixed or b.fixed or not a.se or not b.se:
            continue
        entry = Moved(name, a.value, a.se, b.value, b.se, a.unit)
        if entry.shift > MOVED:
            moved.append(entry)
        if b.se > GROWN * a.se:
            grown.append((name, a.se, b.se))
        if growth is None or b.se / a.se > growth[1]:
            growth = (name, b.se / a.se)
    correlated = []
    largest: tuple[str, str, float] | None = None
    for name in new_parameters(new, old):
        corr = new.params[name].correlations
        for other, value in corr.items():
            if other not in physical:
                continue
            if abs(value) > CORRELATED:
                correlated.append((name, other, float(value)))
            if largest is None or abs(value) > abs(largest[2]):
                largest = (name, other, float(value))
    worst = _worst(moved, grown, correlated, new)
    settled = new.at_floor is True and old.at_floor is False
    return Watch(tuple(moved), tuple(correlated), tuple(grown),
                 design_hint(new, problem_file, worst) if worst else "", settled, growth,
                 largest, _centres(new, old))


def _centres(new: Result, old: Result) -> tuple[tuple[str, str, float, str], ...]:
    """The centres of the terms ``new`` has and ``old`` has not (constants documented
    as :func:`~symcal.revise.effects.centre_variable` reads them)."""
    before = {c.key for c in old.problem.constants}
    out = []
    for c in new.problem.constants:
        variable = centre_variable(c.doc)
        if c.key not in before and variable is not None:
            out.append((c.key, variable, float(c.value), c.unit))
    return tuple(out)


def _worst(moved: list[Moved], grown: list[tuple[str, float, float]],
           correlated: list[tuple[str, str, float]], new: Result) -> tuple[str, float] | None:
    """The physical parameter to design for and the standard error to aim at (its
    standard error before the term), or None."""
    for name, before, _ in grown:
        return name, before
    for _, other, _ in correlated:
        se = new.params[other].se
        return (other, se / 3) if se else None
    for m in moved:
        return m.name, m.old_se
    return None


#: Two fits whose costs and residual spreads agree to this (relative) are the same fit:
#: distinct models do not meet to 1e-7 on hundreds of noisy rows by chance.
SAME_FIT = 1e-7


def same_fit(a: Result, b: Result) -> bool:
    """Whether two revisions fit the same data identically, to rounding: the last
    stage's cost and every residual's spread on every dataset (two ways of writing one
    model: a density's reference temperature freed where its expansion coefficient and
    the gain could be, say).  No experiment separates them."""
    if not a.stages or not b.stages or len(a.statistics) != len(b.statistics):
        return False

    def close(x: float, y: float) -> bool:
        return abs(x - y) <= SAME_FIT * max(abs(x), abs(y), 1e-300)

    if not close(a.stages[-1].cost_after, b.stages[-1].cost_after):
        return False
    return all(s.dataset == t.dataset and s.name == t.name
               and close(s.after.rms, t.after.rms) and close(s.after.std, t.after.std)
               for s, t in zip(a.statistics, b.statistics, strict=True))


def design_hint(result: Result, problem_file: Path, target: tuple[str, float]) -> str:
    """The ``symcal design`` command that asks for an experiment determining ``target``'s
    parameter to the given standard error (in its unit), holding every other parameter at
    its standard error on the given motion (``--hold``: a design for one parameter alone
    can make the others many times less precise, measured 240× on a power bench's
    voltage offset)."""
    name, se = target
    unit = result.params[name].unit
    scenario = next((spec.scenario for spec in result.problem.datasets.values()
                     if spec.scenario is not None), None)
    return "an experiment that separates them: " + design_sentence(
        problem_file, scenario, f"--optimize --target {target_arg(name, se, unit)} --hold")


def _temperature(unit: str) -> bool:
    """Whether ``unit`` measures a temperature (a datasheet's reference is then 25 °C)."""
    try:
        return bool(parse_unit(unit).dimensionality == parse_unit("K").dimensionality)
    except UnitError:       # a unit pint cannot read is not a temperature it knows
        return False
