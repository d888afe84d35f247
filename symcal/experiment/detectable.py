"""A term made detectable: a candidate's minimal detectable effect as a design target.

``symcal diagnose`` states, for each candidate term it tests, the smallest such term its
F-test would find (:mod:`symcal.analysis.discovery`): with X̃ the candidate's regressor
projected off what the problem's free parameters absorb, whitened, its columns scaled by
:attr:`~symcal.analysis.discovery.Basis.scales` (a coefficient of one scaled unit is a
term of RMS :data:`~symcal.analysis.discovery.TERM`), σ² the residual variance per
whitened row and λ* the non-centrality at which the test at its level has power
:data:`~symcal.analysis.discovery.POWER`,

    MDE = TERM · sqrt(λ* σ² / λ_min(X̃ᵀX̃)),

the RMS of the term in the direction of its columns the data see worst.

Before any data the same number follows from the problem *with the term added*: the
covariance C of the term's coefficients in its calibration is ``σ² (X̃ᵀX̃)⁻¹`` in
unscaled coefficients (the Schur complement of the Fisher information: the other free
parameters are what the projection removes), so that

    MDE = term · sqrt(λ* · λ_max(D⁻¹ C D⁻¹)),    D = diag(scales),

with C the covariance :func:`~symcal.experiment.predict.predict` states for the motion
(the scenario's noise through the constraints, the solve's weighting).  It shrinks as
1/√n, so a target amplitude is met with the fewest observations like a standard-error
target (:mod:`symcal.experiment.optimize`).

The level is the diagnosis's: its family-wise α over the number of candidates it tests
(Bonferroni), found by the command line from a diagnosis of data simulated from the
scenario, which also names the term and writes it into a revised problem
(:mod:`symcal.revise`, a later layer); a term already written into a problem is named by
its coefficient parameters, each scaled to a term of RMS ``TERM`` over the motion.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import casadi as ca
import numpy as np

from symcal.analysis.discovery import POWER, TERM, noncentrality
from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import SymcalError
from symcal.base.numeric import chunks, mapped
from symcal.base.units import internal_unit, size
from symcal.experiment.predict import (
    Prediction,
    design_run,
    last_stage,
    noiseless_data,
    operating_point,
)
from symcal.problem.symbolic import Problem
from symcal.simulation import Scenario

#: ``mde(TERM)=VALUE[unit]``: a term's minimal detectable effect as a target.  TERM may
#: contain parentheses (a label's period); the value is what follows the last ``)=``.
_MDE = re.compile(r"^\s*mde\((?P<term>.*)\)\s*=\s*"
                  r"(?P<number>[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(?P<unit>.*?)\s*$")
#: A term named by its coefficients: parameter names separated by commas.
_NAMES = re.compile(r"^\s*[A-Za-z_][\w.]*(\s*,\s*[A-Za-z_][\w.]*)*\s*$")


@dataclass(frozen=True)
class MdeText:
    """A parsed ``mde(TERM)=VALUE`` target, before its term is resolved."""

    term: str
    number: float
    unit: str
    text: str

    @property
    def coefficients(self) -> tuple[str, ...] | None:
        """The coefficient parameters, when the term is named by them (else None: a
        candidate's label)."""
        if "+=" in self.term or not _NAMES.match(self.term):
            return None
        return tuple(n.strip() for n in self.term.split(","))


def parse_mde(text: str) -> MdeText | None:
    """``mde(TERM)=VALUE[unit]`` (``mde(s1.p_hat += harmonic 5 of s1.p)=1um``), or None
    for a target of another form.

    Raises
    ------
    SymcalError
        For ``mde(`` text without ``)=VALUE``, or a value that is not positive.
    """
    if not text.lstrip().startswith("mde("):
        return None
    match = _MDE.match(text)
    if match is None or not match.group("term").strip():
        raise SymcalError(f"--target {text}: expected mde(TERM)=VALUE with an optional unit, "
                          "TERM a candidate as symcal diagnose names it or the coefficient "
                          "parameters of a term in the problem, e.g. "
                          "'mde(s1.p_hat += harmonic 5 of s1.p)=1um'")
    number = float(match.group("number"))
    if number <= 0:
        raise SymcalError(f"--target {text}: a detectable amplitude must be positive")
    return MdeText(" ".join(match.group("term").split()), number, match.group("unit"),
                   text.strip())


@dataclass(frozen=True, eq=False)
class Detectable:
    """A target: make a term detectable at an amplitude.

    Attributes
    ----------
    label
        The term, as symcal diagnose names it (or its coefficients).
    problem
        The problem with the term's coefficients as parameters (the given one, or the
        revision that adds the candidate).
    names
        The coefficient parameters, free in the last stage of ``problem``.
    scales
        Per coefficient, the value (internal units) that makes a term of RMS ``term``.
    level
        The level of the candidate's F-test (α over the candidates tested).
    value
        The amplitude to detect: the term's RMS, internal units.
    unit
        The unit ``value`` is shown in.
    text
        The target as given.
    alpha, tested
        The diagnosis's family-wise level and its number of candidates.
    term
        The RMS (internal units) of the term when every coefficient is its scale: the
        candidate's own (:attr:`~symcal.analysis.discovery.Basis.term`, about one noise
        standard deviation of the output, as diagnose scales it), or ``TERM`` for a term
        named by its coefficients (:func:`coefficient_scales`).
    """

    label: str
    problem: Problem
    names: tuple[str, ...]
    scales: tuple[float, ...]
    level: float
    value: float
    unit: str
    text: str
    alpha: float = 0.01
    tested: int = 1
    term: float = TERM

    @property
    def noncentrality(self) -> float:
        """λ*: the F-test's non-centrality at power :data:`POWER` (χ², as diagnose)."""
        return noncentrality(len(self.names), self.level)

    def to_internal(self) -> np.ndarray:
        """Per coefficient, the size of its unit (parameter value → internal)."""
        params = {p.name: p for p in self.problem.parameters}
        return np.array([size(params[n].unit) for n in self.names])

    def mde(self, prediction: Prediction) -> float | None:
        """The minimal detectable effect (RMS, internal units) on ``prediction``'s motion;
        None when a coefficient is determined only in a combination there."""
        unc = prediction.uncertainty
        if any(unc.se.get(n) is None for n in self.names):
            return None
        idx = [unc.names.index(n) for n in self.names]
        scaled = self.to_internal() / np.asarray(self.scales)
        m = unc.covariance[np.ix_(idx, idx)] * np.outer(scaled, scaled)
        top = float(np.linalg.eigvalsh(0.5 * (m + m.T))[-1])
        return self.term * float(np.sqrt(self.noncentrality * max(top, 0.0)))

    def describe(self) -> str:
        """The level in words: ``level 0.01 over 232 candidates (4.3e-05 each), power
        80 %``."""
        return (f"level {self.alpha:g} over {self.tested} candidates ({self.level:.2g} "
                f"each), power {POWER * 100:.0f} %")


def amplitude(parsed: MdeText, output_unit: str) -> tuple[float, str]:
    """The target's amplitude in internal units, and the unit to show it in: the unit
    given (of the same kind as the output the term adds to), else the output's own."""
    unit = parsed.unit or output_unit
    try:
        same = internal_unit(unit or "1") == internal_unit(output_unit or "1")
    except SymcalError as exc:
        raise SymcalError(f"--target {parsed.text}: {exc}") from None
    if not same:
        raise SymcalError(f"--target {parsed.text}: '{unit}' is not a unit of the term, which "
                          f"adds to an output in '{output_unit or '1'}'")
    return parsed.number * size(unit or "1"), unit


def check_coefficients(problem: Problem, names: tuple[str, ...], text: str) -> None:
    """Refuse names that are not free parameters of the last stage."""
    stage, free = last_stage(problem)
    for name in names:
        if name not in problem.index:
            raise SymcalError(f"--target {text}: the problem has no parameter '{name}'"
                              f"{did_you_mean(name, problem.parameter_names)}; name a "
                              "candidate as symcal diagnose prints it, or the coefficients of "
                              "a term the problem has")
        if not free[problem.index[name]]:
            raise SymcalError(f"--target {text}: '{name}' is not free in the last stage "
                              f"'{stage.name}', so the calibration cannot detect its term")
    if len(set(names)) != len(names):
        raise SymcalError(f"--target {text}: a coefficient is named twice")


def coefficient_scales(problem: Problem, scenario: Scenario, names: tuple[str, ...],
                       run: str | None = None, seed: int = 0
                       ) -> tuple[tuple[float, ...], str]:
    """Per coefficient, the value (internal units) that makes its term of RMS ``TERM``
    over the run's motion: ``TERM / RMS(∂y/∂c)``, y the problem's signal (an instance's
    output) that the coefficients move most, at the operating point on the noiseless run
    (a harmonic's sine: ``TERM·√2``, as the candidate library scales it); and that
    output's unit.

    Raises
    ------
    SymcalError
        If no signal of the problem depends on a coefficient.
    """
    run = design_run(problem, scenario) if run is None else run
    data = noiseless_data(problem, scenario, run, seed)
    theta = operating_point(problem, scenario)
    idx = [problem.index[n] for n in names]
    signals = list(problem.signals)
    if not signals:
        raise SymcalError("design: the problem has no instance outputs for a term")
    y = ca.vertcat(*(q.sx for q in signals))            # internal units
    jac = ca.jacobian(y, problem.theta[idx])
    fn = mapped(problem.theta, problem.u, [jac], "term_shapes")
    u = data.matrix(problem.columns)
    total = np.zeros((len(signals), len(names)))
    for part in chunks(data.n):
        block = fn(theta, u[:, part])[0].reshape(-1, len(names), len(signals))
        total += np.sum(block**2, axis=0).T
    rms = np.sqrt(total / data.n)            # internal output per internal coefficient
    sizes = np.array([size(problem.parameters[i].unit) for i in idx])
    rms = rms / sizes[None, :]
    best = rms.max(axis=0)
    for name, value in zip(names, best, strict=True):
        if not value > 0:
            raise SymcalError(f"design: no output of the problem depends on '{name}' on "
                              f"run '{run}': it is not the coefficient of a term")
    output = signals[int(np.argmax(rms.sum(axis=1)))]
    return tuple(float(TERM / v) for v in best), output.unit
