"""Which motion next: optimise a calibration run's motion within the scenario's limits.

A scenario's ``design`` section names a scatter or dwells run and what may change, with
limits: the range ``[lo, hi]`` of some of its states, the share of a scatter's draws that
``dwell`` at the ends of their ranges, and ``n``.  :func:`design` chooses them with IPOPT
on exact sensitivities: the Fisher information of the motion is a CasADi graph from the
motion's parameters through the states (uniform draws within the ranges), the
scenario's readings (:meth:`symcal.simulation.graph.Graph.explicit_columns`, noiseless, at
the truth) and the problem's symbolic Jacobian, so its derivatives by the motion are
exact.  The expectation over the random draws is a fixed sample of ``SAMPLES`` uniform
draws (common random numbers), with the draws that dwell at the ends of their ranges as
further sets (every combination of ends).  Two goals:

- a criterion on the covariance of the identifiable parameters, measured in their scales:
  ``D`` (log det), ``A`` (trace) or ``E`` (largest eigenvalue, through a smooth
  ``trace(C^16)^(1/16)``), with the most observations the limits allow;
- standard-error targets (``l_x=5um``) with the fewest observations: the motion that
  minimises ``max_j n_j``, ``n_j`` the observations target ``j`` needs; when even the
  limit on ``n`` does not suffice, the best reachable errors and the limits that bind;
- with them or alone, a term to make detectable (``mde(TERM)=1um``,
  :mod:`symcal.experiment.detectable`): its minimal detectable effect, which shrinks as
  1/√n like a standard error, at most the amplitude, from the covariance of the term's
  coefficients in the problem with the term added (its own model in the optimiser, on
  the same motion; the largest eigenvalue through the smooth ``trace(M^16)^(1/16)``).

Every design is then predicted exactly by :func:`symcal.experiment.predict.predict` (the
scenario's readings, noise and misfit, the solve's weighting), which is what is reported;
``n`` is raised to meet the targets on that prediction when the limits allow.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import SolveError, SymcalError
from symcal.base.linalg import sqrt_psd, whitening
from symcal.base.progress import Bars, Progress, Report, reporting
from symcal.base.units import internal_unit, size
from symcal.experiment.detectable import Detectable
from symcal.experiment.predict import Prediction, last_stage, operating_point, predict
from symcal.problem.symbolic import Problem
from symcal.simulation import Scenario, run_states
from symcal.simulation.graph import graph
from symcal.simulation.scenario import Dwells, Scatter
from symcal.solvers.objective import Objective

#: The design criteria (``--criterion``).
CRITERIA: tuple[str, ...] = ("D", "A", "E")
#: Uniform draws standing for a scatter's expectation in the optimiser.
SAMPLES = 256
#: Power of the smooth largest-eigenvalue criterion ``E``.
E_POWER = 16

#: A limit binds when the design ends within this fraction of its range from it (and
#: its multiplier is not zero).
BOUND_TOL = 1e-3
#: A parameter is reported less precise on the designed motion when its predicted
#: standard error grows by more than this factor.
WORSE = 1.1
#: A state whose designed range is below this share of its given range is reported as
#: narrowed: a term in it can hardly be seen on the designed motion.
NARROWED = 0.05
#: A scatter whose share of draws at the ends of their ranges is at least this holds
#: the dwelling states at two values: no term curved in them can be seen.
TWO_LEVELS = 0.999
#: IPOPT statuses that count as a solved design.
SOLVED = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
#: ``hold`` without a target.
HOLD_NEEDS_TARGET = ("--hold keeps the other parameters while meeting targets: it needs "
                     "--target")


@dataclass(frozen=True)
class Target:
    """A standard-error target: ``name``'s SE at most ``value`` (in the parameter's unit)."""

    name: str
    value: float
    text: str


@dataclass(frozen=True, eq=False)
class Design:
    """An optimised motion and the predictions before and after.

    Attributes
    ----------
    baseline
        The prediction for the scenario as given.
    designed
        The prediction for the optimised motion (None when nothing was optimised).
    scenario
        The optimised scenario (the given one when nothing was optimised).
    criterion
        ``D``, ``A`` or ``E``; None with targets.
    targets
        The standard-error targets.
    before, after
        The run's motion as given and as designed (:func:`motion_values`: ``n``, each
        ranged state's ``(lo, hi)`` in its unit, a scatter's ``dwell``).
    binding
        The limits that bind at the optimum (``theta <= 1.5 deg``); with targets that
        cannot be met, the limits that stop them.
    met
        Whether each target is met by the designed motion's prediction (a term to
        detect: by its label).
    message
        What the optimiser reported.
    detect
        A term to make detectable (None without one).
    mde_before, mde_after
        Its minimal detectable effect on the given and the designed motion (internal
        units; None where its coefficients are determined only in a combination).
    held
        With ``hold``: the other parameters the given motion determines, as targets at
        their standard errors there.
    """

    baseline: Prediction
    designed: Prediction | None
    scenario: Scenario
    criterion: str | None
    targets: tuple[Target, ...]
    before: dict[str, object]
    after: dict[str, object]
    binding: tuple[str, ...]
    met: dict[str, bool]
    message: str
    detect: Detectable | None = None
    mde_before: float | None = None
    mde_after: float | None = None
    held: tuple[Target, ...] = ()

    @property
    def worse(self) -> dict[str, float | None]:
        """The parameters less precise on the designed motion than on the given one: the
        factor by which their predicted standard error grows (more than :data:`WORSE`;
        None: the designed motion determines them only in a combination).  Empty when
        nothing was optimised."""
        if self.designed is None or self.designed is self.baseline:
            return {}
        out: dict[str, float | None] = {}
        for name, se in self.baseline.se.items():
            new = self.designed.se.get(name)
            if se is None or se <= 0:
                continue
            factor = None if new is None else float(new) / float(se)
            if factor is None or factor > WORSE:
                out[name] = factor
        return out

    @property
    def holds_met(self) -> bool:
        """Whether every held parameter is at most its given standard error on the
        design's exact prediction (True without ``hold``)."""
        return all(_met(self.final, self.held).values())

    @property
    def all_met(self) -> bool:
        """With targets: whether the design meets every one, and every hold, on its exact
        prediction (False without targets)."""
        return bool(self.met) and all(self.met.values()) and self.holds_met

    @property
    def converged(self) -> bool:
        """Whether IPOPT solved the design (or nothing was left to optimise)."""
        return not self.message.startswith("IPOPT") or self.message.endswith(SOLVED)

    @property
    def blind(self) -> dict[str, float]:
        """What the designed motion can no longer show, by state: 0 for a state held at
        the two ends of its range (every draw dwelling: a term curved in it, a
        quadratic, cannot be told from an offset and a gain), else the share of its
        given range it still spans (below :data:`NARROWED`: hardly any term in it can be
        seen).  Empty when nothing was optimised or nothing was lost."""
        if self.designed is None or self.designed is self.baseline:
            return {}
        out: dict[str, float] = {}
        motion = motion_of(self.scenario, self.baseline.run)
        if isinstance(motion, Scatter) and motion.dwell >= TWO_LEVELS:
            out.update({name: 0.0 for name in motion.dwell_at})
        for key, before in self.before.items():
            after = self.after.get(key)
            if not isinstance(before, tuple) or not isinstance(after, tuple) or key in out:
                continue
            given = float(before[1]) - float(before[0])
            kept = (float(after[1]) - float(after[0])) / given if given > 0 else 1.0
            if kept < NARROWED:
                out[key] = kept
        return out

    @property
    def repeats(self) -> dict[str, float]:
        """The quantized readings whose rounding the designed motion repeats, by column:
        its step (the column's unit).  A column read at a repeated pose (every draw of a
        scatter dwelling at the ends of the states it depends on, or a dwells run's
        samples) rounds the same value each time, so its rounding does not average over
        the draws, whereas the predicted standard errors (and a solve's on such data)
        take it for independent noise: a new user's joint, designed at ±180° for its gear
        ratio with its motor count rounded to 1 count, ended quiet at the floor with the
        ratio 6-8 SE off.  Only where the rounding dominates the column's noise (a
        Gaussian noise of half a step or more dithers it) and the column does not depend
        on time.  Empty when nothing was optimised."""
        if self.designed is None or self.designed is self.baseline:
            return {}
        motion = motion_of(self.scenario, self.baseline.run)
        if isinstance(motion, Scatter):
            if motion.dwell < TWO_LEVELS:
                return {}
            held = set(motion.dwell_at)
        elif motion.samples > 1:
            held = {s.name for s in self.scenario.states}
        else:
            return {}
        found = graph(self.scenario)
        columns = found.explicit_columns()
        out: dict[str, float] = {}
        for column in self.scenario.columns:
            if column.quantization <= 0 or column.noise >= 0.5 * column.quantization \
                    or column.name not in columns:
                continue
            sx = columns[column.name]
            if ca.depends_on(sx, found.t):
                continue
            reads = {s.name for j, s in enumerate(self.scenario.states)
                     if ca.depends_on(sx, found.states[j])}
            if reads and reads <= held:
                out[column.name] = column.quantization
        return out

    @property
    def final(self) -> Prediction:
        """The prediction of the design (the baseline when nothing was optimised)."""
        return self.designed if self.designed is not None else self.baseline

    @property
    def needed_n(self) -> int | None:
        """With targets, the observations the designed motion would need to meet them
        all (the prediction scaled as 1/n); None without targets."""
        if not self.targets and self.detect is None:
            return None
        ratios = _ratios(self.final, self.targets + self.held)
        if self.detect is not None:
            mde = self.mde_after if self.designed is not None else self.mde_before
            ratios.append(math.inf if mde is None else mde / self.detect.value)
        worst = max(ratios)
        return None if math.isinf(worst) else math.ceil(self.final.n * worst**2)

    @property
    def units(self) -> dict[str, str]:
        """The unit of each state of the scenario."""
        return {s.name: s.unit for s in self.baseline.scenario.states}

    def poses(self, designed: bool, seed: int = 0) -> dict[str, np.ndarray]:
        """The true states of the run (given or designed motion), each in its unit."""
        scenario = self.scenario if designed else self.baseline.scenario
        index = scenario.run_index(self.baseline.run)
        _, states = run_states(scenario, scenario.runs[index], seed)
        return {s.name: states[i] / s.size for i, s in enumerate(scenario.states)}

    def scenario_yaml(self, base: str | Path, out_dir: str | Path) -> str:
        """The designed scenario as a file that ``extends`` ``base`` (the given scenario
        file), for ``out_dir``: it replaces only the designed run's motion.  Written by
        the YAML emitter, so any path reads back as it was."""
        from symcal.language.yamlio import dump_yaml

        space = self.baseline.scenario.design
        run = self.baseline.run if space is None else space.run
        rel = os.path.relpath(Path(base).resolve(), Path(out_dir).resolve())
        after = self.after
        motion = motion_of(self.baseline.scenario, run)
        entry: dict[str, object] = {}
        if isinstance(motion, Dwells):
            entry["count"] = math.ceil(int(after["n"]) / motion.samples)  # type: ignore[call-overload]
        else:
            entry["n"] = int(after["n"])  # type: ignore[call-overload]
        for key, _ in motion.ranges:
            ends: Any = after[key]
            entry[key] = [_round(float(ends[0])), _round(float(ends[1]))]
        if isinstance(motion, Scatter):
            entry["dwell"] = _round(float(after["dwell"]))  # type: ignore[arg-type]
        goal = (f"criterion {self.criterion}" if self.criterion else
                "targets " + ", ".join(t.text for t in self.targets) if self.detect is None
                else "targets " + ", ".join([t.text for t in self.targets]
                                            + [self.detect.text]))
        if self.held:
            goal += ", every other parameter held at its given standard error"
        doc = {
            "scenario": f"{self.baseline.scenario.name}_designed",
            "extends": rel,
            "doc": f"run '{run}' of {self.baseline.scenario.name} designed by symcal design "
                   f"({goal}); everything else as in {Path(base).name}",
            "runs": {run: {motion.kind: entry}},
        }
        return dump_yaml(doc)


def _round(value: float) -> float:
    return float(f"{value:.10g}")


# --------------------------------------------------------------------------- targets


_TARGET = re.compile(r"^\s*([A-Za-z_][\w.]*)\s*=\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)"
                     r"\s*(.*?)\s*$")


def parse_target(text: str, problem: Problem) -> Target:
    """A ``NAME=VALUE[unit]`` target (``l_x=5um``), converted to the parameter's unit.

    Raises
    ------
    SymcalError
        For text of another form, an unknown parameter (did-you-mean), one not free in
        the last stage, a unit of another kind than the parameter's, or a value that is
        not positive.
    """
    match = _TARGET.match(text)
    if match is None:
        raise SymcalError(f"--target {text}: expected NAME=VALUE with an optional unit, "
                          "e.g. l_x=5um")
    name, number, unit = match.group(1), float(match.group(2)), match.group(3)
    if name not in problem.index:
        raise SymcalError(f"--target {text}: the problem has no parameter '{name}'"
                          f"{did_you_mean(name, problem.parameter_names)}")
    stage, free = last_stage(problem)
    param = problem.parameters[problem.index[name]]
    if not free[problem.index[name]]:
        raise SymcalError(f"--target {text}: '{name}' is not free in the last stage "
                          f"'{stage.name}', so the calibration reports no standard error "
                          "for it")
    if number <= 0:
        raise SymcalError(f"--target {text}: a standard error must be positive")
    if unit and internal_unit(unit) != internal_unit(param.unit):
        raise SymcalError(f"--target {text}: '{unit}' is not a unit of {name}, which is in "
                          f"'{param.unit or '1'}'")
    value = number * size(unit or param.unit) / size(param.unit)
    return Target(name, value, text.strip())


# --------------------------------------------------------------------------- motions


def _at_start(fn: ca.Function, x0: list[float]) -> Any:
    """``fn(x0)``, the design's prediction on the given motion, or a clear error where
    CasADi cannot evaluate it (a new user's scenario with ``atan(1/tan(pi*t/P))``: the
    evaluation failed inside, reported as an internal error)."""
    try:
        return fn(x0)
    except RuntimeError as exc:
        raise SolveError(
            "design: the optimisation cannot evaluate its prediction on the given motion "
            "(CasADi: " + str(exc).splitlines()[-1].strip()[:160] + "); an expression of "
            "the problem or the scenario that is not finite there (a division by zero, a "
            "tan at its pole) does this, and so may a fault of symcal's: if none is, "
            "please report it with the output of 'symcal --debug ...'. symcal design "
            "without --optimize predicts the given motion") from None


def motion_of(scenario: Scenario, run: str) -> Scatter | Dwells:
    """The scatter or dwells motion of ``run`` (a line or series cannot be designed)."""
    motion = scenario.runs[scenario.run_index(run)].motion
    if not isinstance(motion, (Scatter, Dwells)):
        raise SymcalError(f"design: run '{run}' of scenario '{scenario.name}' is a "
                          f"{motion.kind}; only a scatter or dwells run can be designed")
    return motion


def motion_values(scenario: Scenario, motion: Scatter | Dwells) -> dict[str, object]:
    """A motion as a design's limits state it: ``n``, each ranged state's ``(lo, hi)`` in
    the state's unit, and a scatter's ``dwell``."""
    out: dict[str, object] = {"n": motion.n}
    for name, (lo, hi) in motion.ranges:
        factor = scenario.state(name).size
        out[name] = (lo / factor, hi / factor)
    if isinstance(motion, Scatter):
        out["dwell"] = motion.dwell
    return out


def with_motion(scenario: Scenario, run: str, values: dict[str, object]) -> Scenario:
    """``scenario`` with ``run``'s motion set to ``values`` (see :func:`motion_values`;
    a dwells run gets the whole number of dwells that holds ``n``)."""
    index = scenario.run_index(run)
    old = scenario.runs[index]
    motion = motion_of(scenario, run)
    ranges = []
    for name, (lo, hi) in motion.ranges:
        factor = scenario.state(name).size
        ends: Any = values.get(name, (lo / factor, hi / factor))
        ranges.append((name, (float(ends[0]) * factor, float(ends[1]) * factor)))
    n = int(values["n"])  # type: ignore[call-overload]
    new: Scatter | Dwells
    if isinstance(motion, Scatter):
        new = dataclasses.replace(motion, ranges=tuple(ranges), n=n,
                                  dwell=float(values.get("dwell", motion.dwell)))  # type: ignore[arg-type]
    else:
        new = dataclasses.replace(motion, ranges=tuple(ranges),
                                  count=math.ceil(n / motion.samples))
    runs = list(scenario.runs)
    runs[index] = dataclasses.replace(old, motion=new)
    return dataclasses.replace(scenario, runs=tuple(runs))


# --------------------------------------------------------------------------- the optimiser


@dataclass(frozen=True)
class _Var:
    """One scalar of the design: a key of the motion (and which end of a range)."""

    key: str
    end: int | None
    lower: float
    upper: float
    start: float
    unit: str = ""

    @property
    def label(self) -> str:
        return self.key if self.end is None else f"{self.key}[{self.end}]"

    def bound_text(self, at_upper: bool) -> str:
        bound = self.upper if at_upper else self.lower
        unit = f" {self.unit}" if self.unit else ""
        return f"{self.key} {'<=' if at_upper else '>='} {bound:g}{unit}"


def _variables(scenario: Scenario, limits: tuple[tuple[str, tuple[float, float]], ...],
               start: dict[str, object]) -> list[_Var]:
    out: list[_Var] = []
    for key, (lo, hi) in limits:
        if key == "n":
            continue
        value = start[key]
        if key == "dwell":
            out.append(_Var(key, None, lo, hi, float(value)))  # type: ignore[arg-type]
        else:
            unit = scenario.state(key).unit
            out.append(_Var(key, 0, lo, hi, float(value[0]), unit))  # type: ignore[index]
            out.append(_Var(key, 1, lo, hi, float(value[1]), unit))  # type: ignore[index]
    return out


def _identifiable_basis(prediction: Prediction, names: tuple[str, ...],
                        scales: np.ndarray) -> np.ndarray:
    """Orthonormal columns spanning the identifiable directions, in scaled coordinates."""
    null = [np.array([c.coefficients.get(n, 0.0) for n in names]) / scales
            for c in prediction.identifiability.null_space]
    if not null:
        return np.eye(len(names))
    q, _ = np.linalg.qr(np.array(null).T, mode="complete")
    return q[:, len(null):]


class _Model:
    """The per-observation Fisher information of a scatter or dwells motion as a CasADi
    graph of its ranges and dwell share."""

    def __init__(self, problem: Problem, scenario: Scenario, run: str,
                 prediction: Prediction) -> None:
        stage, free = last_stage(problem)
        theta = operating_point(problem, scenario)
        cov = prediction.covariance
        ng = cov.shape[0]
        estimated = problem.weighting in ("estimated", "propagated") and ng > 1
        transform = whitening(cov)[0] if estimated else np.eye(ng)
        objective = Objective(problem, stage.constraints, free, transform)
        self.names = objective.names
        self.scales = objective.scales
        self.basis = _identifiable_basis(prediction, self.names, self.scales)
        seen = transform @ cov @ transform.T
        self.single = ng == 1
        self.variance = float(seen[0, 0]) if self.single else 1.0
        self.meat_root = None if (estimated or self.single) else sqrt_psd(seen).T
        motion = motion_of(scenario, run)
        run_spec = scenario.runs[scenario.run_index(run)]
        g = graph(scenario)
        t_mid = run_spec.t0 + run_spec.dt * (motion.n - 1) / 2.0
        readings = {name: ca.substitute(sx, g.t, ca.SX(t_mid)) / size(scenario.column(
            name).unit) for name, sx in g.explicit_columns().items()}
        missing = [c for c in problem.columns_of(objective.g) if c not in readings]
        if missing:
            raise SymcalError(f"design: the problem reads column(s) {', '.join(missing)} "
                              f"that scenario '{scenario.name}' does not simulate")
        u = ca.vertcat(*(readings.get(c, 0.0) for c in problem.columns))
        jac = ca.substitute(objective.jac, ca.vertcat(problem.theta, problem.u),
                            ca.vertcat(ca.DM(theta), u))
        b = ca.mtimes(ca.mtimes(jac, ca.DM(np.diag(self.scales))), ca.DM(self.basis))
        outs = [ca.vec(b.T)]
        if self.meat_root is not None:
            outs.append(ca.vec(ca.mtimes(ca.DM(self.meat_root), b).T))
        self.ng, self.rank = ng, self.basis.shape[1]
        self.per_pose = ca.Function("info", [g.states], outs).map(SAMPLES, "serial")
        self.states = scenario.states
        self.ranged = [name for name, _ in motion.ranges]
        self.held = dict(motion.held)
        self.dwell_at = list(motion.dwell_at)
        self.sizes = {s.name: s.size for s in scenario.states}
        rng = np.random.default_rng(20240517)
        self.draws = rng.uniform(size=(len(self.ranged), SAMPLES))

    def _gram(self, poses: Any) -> tuple[Any, Any]:
        outs: Any = self.per_pose(poses)
        outs = outs if isinstance(outs, (list, tuple)) else [outs]
        mats = [ca.reshape(o, self.rank, self.ng * SAMPLES) for o in outs]
        bread = ca.mtimes(mats[0], mats[0].T) / SAMPLES
        meat = ca.mtimes(mats[1], mats[1].T) / SAMPLES if len(mats) > 1 else None
        return bread, meat

    def _poses(self, values: dict[str, Any], ends: dict[str, int]) -> Any:
        """The states of the sample (``k × SAMPLES``, internal units); states in ``ends``
        sit at that end (0: lo, 1: hi) of their range."""
        rows = []
        for state in self.states:
            name = state.name
            if name in self.held:
                rows.append(ca.DM.ones(1, SAMPLES) * self.held[name])
                continue
            lo, hi = values[name]
            factor = self.sizes[name]
            if name in ends:
                rows.append(ca.repmat((hi if ends[name] else lo) * factor, 1, SAMPLES))
                continue
            u = ca.DM(self.draws[self.ranged.index(name)]).T
            rows.append((lo + (hi - lo) * u) * factor)
        return ca.vertcat(*rows)

    def covariance(self, values: dict[str, Any]) -> Any:
        """Scaled covariance (identifiable coordinates) of ONE observation's worth of
        information (divide by n)."""
        w = values.get("dwell", 0.0)
        parts = [(1 - w, self._gram(self._poses(values, {})))]
        if self.dwell_at and not (isinstance(w, float) and w == 0.0):
            combos = list(itertools.product((0, 1), repeat=len(self.dwell_at)))
            for combo in combos:
                ends = dict(zip(self.dwell_at, combo, strict=True))
                parts.append((w / len(combos), self._gram(self._poses(values, ends))))
        bread: Any = sum(share * g[0] for share, g in parts)
        inverse = _inverse(bread, self.rank)
        if self.meat_root is None:
            return self.variance * inverse
        meat: Any = sum(share * g[1] for share, g in parts)
        return ca.mtimes(ca.mtimes(inverse, meat), inverse)

    def se2(self, cov: Any, name: str) -> Any:
        """Variance of parameter ``name`` (its unit squared) from a scaled covariance."""
        i = self.names.index(name)
        z = ca.DM(self.basis[i, :])
        return self.scales[i] ** 2 * ca.mtimes(ca.mtimes(z.T, cov), z)

    def mde2(self, cov: Any, detect: Detectable) -> Any:
        """The squared minimal detectable effect of ``detect``'s term (internal units)
        from a scaled covariance: ``term² λ* λ_max(D⁻¹ C D⁻¹)``, the largest eigenvalue
        by the smooth upper bound ``trace(M^16)^(1/16)`` (at most 4.4 % above it for two
        columns; the design is predicted exactly afterwards)."""
        idx = [self.names.index(n) for n in detect.names]
        factor = (np.asarray(self.scales)[idx] * detect.to_internal()
                  / np.asarray(detect.scales))
        z = ca.mtimes(ca.DM(np.diag(factor)), ca.DM(self.basis[idx, :]))
        m = ca.mtimes(ca.mtimes(z, cov), z.T)
        if len(idx) == 1:
            top = m
        else:
            size_ = ca.trace(m)
            power = m / size_
            for _ in range(int(math.log2(E_POWER))):
                power = ca.mtimes(power, power)
            top = size_ * ca.trace(power) ** (1.0 / E_POWER)
        return detect.term**2 * detect.noncentrality * top


def _criterion(kind: str, cov: Any, rank: int, reference: float) -> Any:
    if kind == "D":
        return ca.log(ca.det(cov))
    if kind == "A":
        return ca.trace(cov) / reference
    power = cov / reference
    for _ in range(int(math.log2(E_POWER))):
        power = ca.mtimes(power, power)
    return ca.trace(power) ** (1.0 / E_POWER)


def _inverse(gram: Any, rank: int) -> Any:
    """The inverse of an information matrix, scaled to unit diagonal first (Jacobi) and
    back: CasADi's default QR refuses a matrix whose pivots are small in absolute terms,
    which the per-observation information of a nearly aliased revision has (eigenvalues
    from 2e-14 to 8e-4, a magnetometer's scale factor and a term linear in its reading:
    'Evaluation failed'); scaled, the same matrix has eigenvalues 2e-6 to 2.4."""
    scale = ca.diag(1.0 / ca.sqrt(ca.diag(gram)))
    unit = ca.mtimes(ca.mtimes(scale, gram), scale)
    return ca.mtimes(ca.mtimes(scale, ca.solve(unit, ca.DM.eye(rank))), scale)


def _optimise(model: _Model, variables: list[_Var], fixed: dict[str, object],
              criterion: str | None, targets: tuple[Target, ...], n_scale: float,
              detect: tuple[_Model, Detectable] | None = None
              ) -> tuple[dict[str, float], list[str], float, str]:
    """IPOPT over the motion; returns the values, the active bounds, the optimum and
    IPOPT's status.  ``detect``: a term to make detectable, with the model of the problem
    that has its coefficients."""
    d = ca.MX.sym("d", len(variables))
    values: dict[str, Any] = {}
    for key in model.ranged:
        ends = [next((d[i] for i, v in enumerate(variables) if v.key == key and v.end == e),
                     fixed[key][e]) for e in (0, 1)]  # type: ignore[index]
        values[key] = tuple(ends)
    if "dwell" in fixed:
        values["dwell"] = next((d[i] for i, v in enumerate(variables) if v.key == "dwell"),
                               fixed["dwell"])
    cov = model.covariance(values)
    g: list[ca.MX] = []
    glb: list[float] = []
    for key in model.ranged:
        lo, hi = values[key]
        if isinstance(lo, ca.MX) or isinstance(hi, ca.MX):
            g.append(hi - lo)
            glb.append(0.0)
    x = d
    lbx = [v.lower for v in variables]
    ubx = [v.upper for v in variables]
    x0 = [v.start for v in variables]
    if targets or detect is not None:
        t = ca.MX.sym("t")
        x = ca.vertcat(d, t)
        ratios = [model.se2(cov, tg.name) / tg.value**2 / n_scale for tg in targets]
        if detect is not None:
            term_model, term = detect
            ratios.append(term_model.mde2(term_model.covariance(values), term)
                          / term.value**2 / n_scale)
        start: Any = _at_start(ca.Function("r", [d], ratios), x0)
        start = start if isinstance(start, (list, tuple)) else [start]
        g += [r - t for r in ratios]
        glb += [-ca.inf] * len(ratios)
        t0 = max(float(s) for s in start)
        objective = t
        lbx, ubx = lbx + [0.0], ubx + [ca.inf]
        x0 = x0 + [t0]
    else:
        assert criterion is not None
        reference = float(_at_start(ca.Function("c", [d], [ca.trace(cov)]), x0))
        objective = _criterion(criterion, cov, model.rank, reference)
    gub = [0.0 if b == -ca.inf else -b if b < 0 else ca.inf for b in glb]
    glb = [-ca.inf if b < 0 else b for b in glb]
    xs, lam, best, status = _ipopt(x, objective, g, x0, lbx, ubx, glb, gub)
    if targets or detect is not None:
        best = float(xs[-1])
    active = []
    for i, v in enumerate(variables):
        # an interior point stops just inside an active bound (measured: 2e-5 of the
        # width): a bound is binding when its multiplier is non-zero and the design is
        # within BOUND_TOL of it; the design is then put on the bound itself
        width = max(v.upper - v.lower, 1e-12)
        near_hi = v.upper - xs[i] <= BOUND_TOL * width
        near_lo = xs[i] - v.lower <= BOUND_TOL * width
        if (near_hi or near_lo) and abs(lam[i]) > 1e-9:
            active.append(v.bound_text(near_hi))
            xs[i] = v.upper if near_hi else v.lower
    out = {v.label: float(xs[i]) for i, v in enumerate(variables)}
    return out, active, best, status


def _ipopt(x: ca.MX, f: ca.MX, g: list[ca.MX], x0: list[float], lbx: list[float],
           ubx: list[float], lbg: list[float], ubg: list[float]
           ) -> tuple[np.ndarray, np.ndarray, float, str]:
    """One IPOPT solve (limited-memory Hessian): x, bound multipliers, f, status."""
    nlp = {"x": x, "f": f, "g": ca.vertcat(*g) if g else ca.MX(0, 1)}
    solver = ca.nlpsol("design", "ipopt", nlp, {
        "ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
        "ipopt.max_iter": 1000, "ipopt.tol": 1e-9,
        "ipopt.hessian_approximation": "limited-memory"})
    sol = solver(x0=x0, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
    status = str(solver.stats().get("return_status", ""))
    return (np.array(sol["x"]).ravel(), np.array(sol["lam_x"]).ravel(), float(sol["f"]),
            status)


# --------------------------------------------------------------------------- the design


def _apply(start: dict[str, object], variables: list[_Var], solution: dict[str, float],
           n: int) -> dict[str, object]:
    out = dict(start)
    for key in {v.key for v in variables if v.end is not None}:
        ends = list(start[key])  # type: ignore[call-overload]
        for v in variables:
            if v.key == key and v.end is not None:
                ends[v.end] = min(max(solution[v.label], v.lower), v.upper)
        if ends[0] > ends[1]:
            ends = [ends[1], ends[0]]
        out[key] = tuple(ends)
    for v in variables:
        if v.key == "dwell":
            out["dwell"] = min(max(solution[v.label], v.lower), v.upper)
    out["n"] = n
    return out


def _whole(motion: Scatter | Dwells, n: int, n_hi: int) -> int:
    """``n`` as observations the motion can have: whole dwells for a dwells run (rounded
    up, or down to stay within ``n_hi``)."""
    if not isinstance(motion, Dwells):
        return n
    whole = math.ceil(n / motion.samples) * motion.samples
    return whole if whole <= n_hi else max(motion.samples,
                                           (n_hi // motion.samples) * motion.samples)


def _ratios(prediction: Prediction, targets: tuple[Target, ...]) -> list[float]:
    """How many times its target each target's predicted standard error is (inf where
    the motion determines the parameter only in a combination)."""
    se = prediction.se
    return [math.inf if se.get(t.name) is None else float(se[t.name]) / t.value  # type: ignore[arg-type]
            for t in targets]


def _met(prediction: Prediction, targets: tuple[Target, ...]) -> dict[str, bool]:
    se = prediction.se
    return {t.name: se.get(t.name) is not None and float(se[t.name]) <= t.value  # type: ignore[arg-type]
            for t in targets}


@dataclass(frozen=True)
class _Plan:
    """One motion's predictions: the problem's, and the term's (its MDE) if any."""

    prediction: Prediction
    mde: float | None

    def ratio(self, targets: tuple[Target, ...], detect: Detectable | None) -> float:
        """How many times its target the worst target is (1: just met)."""
        ratios = _ratios(self.prediction, targets)
        if detect is not None:
            ratios.append(math.inf if self.mde is None else self.mde / detect.value)
        return max(ratios, default=0.0)

    def met(self, targets: tuple[Target, ...], detect: Detectable | None) -> dict[str, bool]:
        out = _met(self.prediction, targets)
        if detect is not None:
            out[detect.label] = self.mde is not None and self.mde <= detect.value
        return out


def _plan(problem: Problem, scenario: Scenario, run: str, seed: int,
          detect: Detectable | None) -> _Plan:
    prediction = predict(problem, scenario, run, seed)
    if detect is None:
        return _Plan(prediction, None)
    term = prediction if detect.problem is problem else predict(detect.problem, scenario,
                                                                 run, seed)
    return _Plan(prediction, detect.mde(term))


def design(problem: Problem, scenario: Scenario, *, criterion: str | None = None,
           targets: tuple[Target, ...] = (), seed: int = 0,
           detect: Detectable | None = None, hold: bool = False,
           progress: Progress | None = None, bars: Bars | None = None) -> Design:
    """Optimise the motion of the scenario's ``design`` run within its limits.

    Parameters
    ----------
    problem
        The calibration problem (its last stage is what the calibration reports).
    scenario
        A scenario with a ``design`` section.
    criterion
        ``D``, ``A`` or ``E`` (default ``D`` without targets).
    targets
        Standard-error targets (:func:`parse_target`): met with the fewest observations
        the limits allow, or the best reachable errors with the limits that bind.
    seed
        Seed of the poses the predictions are evaluated on.
    detect
        A term to make detectable at an amplitude
        (:class:`~symcal.experiment.detectable.Detectable`), with the standard-error
        targets or alone: its minimal detectable effect at most that amplitude.
    hold
        With targets: hold every other parameter the given motion determines at its
        standard error there (further targets, :attr:`Design.held`), so that the design
        meets the targets without making another parameter less precise.
    progress
        Called with each line of progress (:mod:`symcal.base.progress`): the baseline's
        prediction, each optimisation round's outcome (None: no lines).
    bars
        Progress bars (:func:`symcal.base.progress.terminal_bars`): one meter counting
        the optimisation rounds (at most 2), the latest round's line beside it (then not
        passed to ``progress``).  None: no bars.

    Returns
    -------
    Design
        The designed motion, the predictions before and after, the binding limits.

    Raises
    ------
    SymcalError
        Without a ``design`` section, for an unknown criterion, or for a target that the
        baseline cannot determine on its own (a term to detect: whose coefficients it
        determines only in a combination).
    """
    space = scenario.design
    if space is None and scenario.inherited_design:
        raise SymcalError(f"scenario '{scenario.name}' ({scenario.source}) inherits a "
                          "'design' section that does not apply to it: "
                          f"{scenario.inherited_design}; declare its own 'design:' section "
                          "for the run that may change")
    if space is None:
        raise SymcalError(f"scenario '{scenario.name}' ({scenario.source}) has no 'design' "
                          "section: declare which run may change and its limits (design: "
                          "{run: NAME, limits: {KEY: [lo, hi], ...}}, KEY a ranged state of "
                          "the run, dwell or n)")
    goal = bool(targets) or detect is not None
    if hold and not goal:
        raise SymcalError(HOLD_NEEDS_TARGET)
    if goal and criterion is not None:
        raise SymcalError("--criterion and --target: give one goal, a criterion or targets")
    criterion = None if goal else (criterion or "D")
    if criterion is not None and criterion not in CRITERIA:
        raise SymcalError(f"--criterion {criterion}: expected one of {', '.join(CRITERIA)}"
                          f"{did_you_mean(criterion, CRITERIA)}")
    with reporting(progress, bars, "design", total=2, unit="round") as report:
        return _design(problem, scenario, criterion, targets, seed, report, detect, hold)


def _design(problem: Problem, scenario: Scenario, criterion: str | None,
            targets: tuple[Target, ...], seed: int, report: Report,
            detect: Detectable | None, hold: bool) -> Design:
    space = scenario.design
    assert space is not None
    run = space.run
    goal = bool(targets) or detect is not None
    first = _plan(problem, scenario, run, seed, detect)
    baseline = first.prediction
    report.line(f"design: the baseline run '{run}' predicted ({baseline.n} observations)")
    for tg in targets:
        if baseline.se.get(tg.name) is None:
            raise SymcalError(f"--target {tg.text}: '{tg.name}' is determined only in a "
                              "combination with other parameters, on any motion of this "
                              "problem; target an identifiable parameter")
    if detect is not None and first.mde is None:
        raise SymcalError(f"--target {detect.text}: on the given motion the calibration "
                          f"cannot tell {detect.label} from the parameters it has (its "
                          f"coefficients {', '.join(detect.names)} are determined only in a "
                          "combination); widen the motion in the scenario first")
    aimed = {t.name for t in targets}
    held = tuple(Target(name, float(se), f"{name}<={se:.4g}")
                 for name, se in baseline.se.items()
                 if hold and se is not None and se > 0 and name not in aimed)
    given, targets = targets, targets + held
    motion = motion_of(scenario, run)
    start = motion_values(scenario, motion)
    limits = space.bounds
    n_lo, n_hi = (int(limits["n"][0]), int(limits["n"][1])) if "n" in limits else (
        int(start["n"]), int(start["n"]))  # type: ignore[call-overload]
    variables = _variables(scenario, space.limits, start)
    current, current_term = baseline, None
    values: dict[str, object] = dict(start)
    active: list[str] = []
    message = "only n may change: no motion to optimise"
    plan = first
    for round_ in range(2):  # a second round with the design's own noise model, if needed
        if variables:
            model = _Model(problem, scenario, run, current)
            term = None
            if detect is not None:
                term_prediction = current if detect.problem is problem else (
                    current_term or predict(detect.problem, scenario, run, seed))
                term = (_Model(detect.problem, scenario, run, term_prediction), detect)
            solution, active, best, status = _optimise(model, variables, start, criterion,
                                                       targets, float(baseline.n), term)
            message = f"IPOPT: {status}"
        else:
            solution, best = {}, first.ratio(targets, detect) ** 2
        n = n_hi if not goal else min(max(math.ceil(best * baseline.n * 1.02), n_lo), n_hi)
        n = _whole(motion, n, n_hi)
        values = _apply(start, variables, solution, n)
        plan = _plan(problem, with_motion(scenario, run, values), run, seed, detect)
        if goal:
            worst = plan.ratio(targets, detect)
            fitted = _whole(motion, min(max(math.ceil(n * worst**2 * 1.02), n_lo), n_hi),
                            n_hi) if math.isfinite(worst) else n_hi
            if fitted != n:  # the exact prediction needs more, or fewer, observations
                values_n = _apply(start, variables, solution, fitted)
                again = _plan(problem, with_motion(scenario, run, values_n), run, seed,
                              detect)
                if fitted > n or all(again.met(targets, detect).values()):
                    n, values, plan = fitted, values_n, again
        report.step(f"design: round {round_ + 1}: {message}; {n} observations")
        if not goal or all(plan.met(targets, detect).values()):
            break
        current = plan.prediction
        if detect is not None and detect.problem is not problem:
            current_term = predict(detect.problem, with_motion(scenario, run, values), run,
                                   seed)
    met = plan.met(targets, detect)
    binding = list(active)
    if "n" in limits and int(values["n"]) == _whole(motion, n_hi, n_hi) and (  # type: ignore[call-overload]
            criterion is not None or not all(met.values())):
        binding.append(f"n <= {n_hi}")
    return Design(baseline, plan.prediction, with_motion(scenario, run, values), criterion,
                  given, start, values, tuple(dict.fromkeys(binding)),
                  {k: v for k, v in met.items() if k not in {t.name for t in held}}, message,
                  detect, first.mde, plan.mde, held)
