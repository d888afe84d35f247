"""Globalised least squares: symcal's own trust-region Levenberg–Marquardt solver.

Minimises Σ g² (the weighted residuals of an :class:`Objective`) over the free parameters,
on the exact Jacobian from CasADi's AD.

* **Linearisation.** Each accepted iterate is linearised with ``Objective.accumulate_r``:
  the R factor of ``[J | g]`` reduced chunk by chunk (TSQR), so no N × n Jacobian is stored
  and the step is computed from R (condition number κ), not from JᵀJ (κ²).  Trial points
  evaluate residuals only (``Objective.cost``).
* **Variables.** x = θ_free / scale, each parameter in units of its nominal scale.  The
  trust region is the ellipsoid ‖D p‖ ≤ Δ, D the largest Jacobian column norms seen so far
  (in x), which makes steps independent of how the model is parametrised.
* **Step.** With the SVD B = R_x D⁻¹ = U S Vᵀ computed once per iterate, the step for a
  multiplier λ is z(λ) = D p = −V S (S² + λ)⁻¹ Uᵀc.  The Gauss–Newton step (λ = 0, singular
  values below :func:`symcal.base.linalg.rank_tolerance` dropped: minimum norm) is taken when
  it lies inside the region; otherwise λ solves ‖z(λ)‖ = Δ (to 10 %) by safeguarded Newton
  iterations on 1/‖z(λ)‖, which is nearly linear in λ.
* **Bounds.** Parameters at a bound whose gradient points out of the box are held for the
  step (active set); the step of the others is then cut back into the box.  The model's
  predicted decrease is that of the step actually taken.
* **Acceptance.** A step is taken when the actual decrease is at least 10⁻⁴ of the
  predicted one; the radius shrinks after poor steps (and non-finite trial costs) and grows
  after good ones.  Only decreasing steps are accepted, so the iterate kept is always the
  best one seen.
* **Status.** Success only when a first-order test holds at the final iterate: a
  Gauss–Newton step would lower the cost by less than ``GN_DECREMENT`` of itself (with the
  held bounds: the projected problem), or, once no step lowers the cost, that decrease is
  within the cost's rounding noise or the step is below ``XTOL`` of the parameters, or
  the fit is exact.  The rounding noise is measured by rejected trial steps too small for
  the model's curvature to matter: as soon as two in a row show it (:class:`_Steps`), and
  from then on at every linearisation, a Gauss–Newton promise within it stops the solve,
  without the train of rejected trials that shrinking the region to nothing would take.
  Converged to rounding, the last Gauss–Newton step (from R, finer than the cost) is
  taken when the cost stays within its noise (a step of at most ``KEEP_R`` of the
  parameters checked by a pass of residuals alone, R the last linearisation's), so the
  estimate does not depend on the order the passes reduce in (the residual vanished,
  or fell below ``EXACT_FIT`` of the starting residual, where rounding dominates).
  Divergence,
  NaN/inf in the Jacobian, the iteration limit and a stall (the region shrank to nothing
  without the test holding) are failures that say so.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from symcal.base.linalg import rank_tolerance
from symcal.data.dataset import Dataset
from symcal.solvers import instrument
from symcal.solvers.base import SolverOutput
from symcal.solvers.objective import Objective

#: Converged when a Gauss–Newton step would lower the cost by less than this fraction
#: (far tighter than the IPOPT path's 1e-14: NIST's certified values need it).
GN_DECREMENT = 1e-20
#: Rejected steps shorter than this fraction of ‖D x‖ measure the cost's rounding noise.
NOISE_STEP = 1e-6
#: Converged to rounding when a Gauss–Newton step promises at most this many times the
#: largest rounding noise seen.
NOISE_FACTOR = 4.0
#: The cost is a sum of rounded squares: its relative rounding is at least this many
#: machine epsilons, measured or not (a step's predicted decrease below it is lost in it).
ROUNDING_FLOOR = 16.0
#: Converged when no step lowers the cost and the Gauss–Newton step is shorter than this
#: fraction of the parameters (‖D x‖): they are determined to rounding.
XTOL = 1e-12
#: An exact fit: the residual norm fell below this fraction of the starting one.
EXACT_FIT = 1e-12
#: Stalled when the trust radius falls below this fraction of ‖D x‖ (or of 1).
STALL = 1e-15
#: Diverged when a parameter exceeds this many nominal scales.
DIVERGED = 1e15
#: The last Gauss–Newton step is taken when the cost stays within this fraction of
#: itself (far above the rounding of a sum of squares, far below a real increase).
POLISH = 1e-12
#: The last Gauss–Newton step keeps the R factor it was computed from (its cost checked
#: by a pass of residuals alone) when it moves the parameters by at most this share of
#: ‖D x‖; a longer one is linearised again (see :func:`_polish`).
KEEP_R = 1e-9
#: Machine epsilon of the floats the cost is summed in.
EPS = float(np.finfo(float).eps)
#: A step is accepted when it achieves this fraction of its predicted decrease.
ACCEPT = 1e-4


@dataclass
class _Linearisation:
    """The linear model of the residual at one iterate, in scaled variables x."""

    cost: float
    r_x: np.ndarray  # R·diag(scale): ‖J_x p + g‖² = ‖r_x p + c‖² + tail
    c: np.ndarray
    r_theta: np.ndarray
    rows: int

    @property
    def finite(self) -> bool:
        """Whether the cost, R and c are all finite."""
        return bool(math.isfinite(self.cost) and np.all(np.isfinite(self.r_x))
                    and np.all(np.isfinite(self.c)))

    @property
    def gradient(self) -> np.ndarray:
        """∇ Σ g² in x (2 J_xᵀ g)."""
        return np.asarray(2.0 * (self.r_x.T @ self.c))


def _held(x: np.ndarray, lower: np.ndarray, upper: np.ndarray,
          gradient: np.ndarray) -> np.ndarray:
    """Parameters at a bound whose descent direction leaves the box."""
    tol = 1e-12 * np.maximum(1.0, np.abs(x))
    at_lower = (x - lower <= tol) & (gradient > 0)
    at_upper = (upper - x <= tol) & (gradient < 0)
    return np.asarray(at_lower | at_upper)


def _step_norm(s: np.ndarray, a: np.ndarray, lam: float) -> float:
    return float(np.linalg.norm(s * a / (s**2 + lam)))


def _multiplier(s: np.ndarray, a: np.ndarray, radius: float) -> float:
    """λ > 0 with ‖S (S² + λ)⁻¹ a‖ = radius to 10 %, by safeguarded Newton on 1/‖z(λ)‖."""
    lo, hi = 0.0, float(np.linalg.norm(s * a)) / radius
    lam = 0.0
    for _ in range(60):
        w = s * a / (s**2 + lam)
        norm = float(np.linalg.norm(w))
        if abs(norm - radius) <= 0.1 * radius:
            return lam
        if norm > radius:
            lo = lam
        else:
            hi = lam
        slope = float(np.sum(w**2 / (s**2 + lam)))  # −‖z‖·d‖z‖/dλ
        newton = lam + (norm / radius - 1.0) * norm**2 / slope if slope > 0 else hi
        lam = newton if lo < newton < hi else 0.5 * (lo + hi) if hi > 0 else 2 * lo + 1e-300
        if hi - lo <= 1e-15 * hi:
            break
    return lam


class _Steps:
    """Trial steps from one linearisation, and what the rejected ones say about rounding.

    A rejected trial step of at most :data:`NOISE_STEP` of ‖D x‖ differs from its predicted
    decrease by curvature the model leaves out, which falls like the square of the step,
    or by the rounding of the cost, which does not.  Two such trials in a row whose
    discrepancies do not fall like the square of their steps measure the rounding:
    ``rounding`` is then the part of the smaller step's discrepancy that curvature cannot
    explain.  Once the decrease a Gauss–Newton step promises is within
    :data:`NOISE_FACTOR` times that, no step can lower the cost beyond rounding, and the
    solve stops (:meth:`settled`) instead of shrinking the region trial after trial.
    """

    def __init__(self, lin: _Linearisation, x: np.ndarray, lower: np.ndarray,
                 upper: np.ndarray, free: np.ndarray, d: np.ndarray, s: np.ndarray,
                 a: np.ndarray, vt: np.ndarray, decrement: float,
                 rounding: float = 0.0) -> None:
        self.lin, self.x, self.lower, self.upper = lin, x, lower, upper
        self.free, self.d, self.s, self.a, self.vt = free, d, s, a, vt
        self.decrement = decrement
        self.accepted = False
        self.noise = 0.0
        self.rounding = rounding
        self.samples: list[tuple[float, float]] = []   # (size, discrepancy) of small ones
        self.small = NOISE_STEP * max(float(np.linalg.norm(d * x)), 1.0)

    def settled(self) -> bool:
        """Whether the decrease a Gauss–Newton step promises is within the measured
        rounding of the cost (see the class)."""
        return self.rounding > 0 and (self.decrement * self.lin.cost
                                      <= NOISE_FACTOR * self.rounding)

    def settled_words(self) -> str:
        """Why :meth:`settled` stopped the solve."""
        return (f"converged to rounding: a Gauss-Newton step would lower the cost by "
                f"{self.decrement:.2g} of itself, within the rounding noise of the cost "
                f"measured by rejected trial steps ({self.rounding / self.lin.cost:.2g} of "
                "it)")

    def trial(self, radius: float) -> tuple[np.ndarray, float, float]:
        """The point of the step within ``radius``, its predicted decrease and its size."""
        s, a = self.s, self.a
        lam = 0.0
        if float(np.linalg.norm(a / s)) > radius:
            lam = _multiplier(s, a, radius)
        z = -(self.vt.T @ (s * a / (s**2 + lam)))
        step = np.zeros(len(self.x))
        step[self.free] = z / self.d[self.free]
        trial = np.clip(self.x + step, self.lower, self.upper)
        taken = trial - self.x
        change = self.lin.r_x @ taken   # ‖c‖² - ‖c + change‖², without cancellation
        predicted = float(-2.0 * (self.lin.c @ change) - change @ change)
        return trial, predicted, float(np.linalg.norm(self.d * taken))

    def rejected(self, cost: float, predicted: float, size: float) -> None:
        """Record a rejected trial: tiny ones measure the rounding noise of the cost."""
        if math.isfinite(cost) and size <= self.small:
            error = abs(self.lin.cost - cost - predicted)
            self.noise = max(self.noise, error)
            if self.samples:
                before, error_before = self.samples[-1]
                curvature = (size / before) ** 2 * error_before if size < before else math.inf
                if error > 2.0 * curvature:
                    self.rounding = max(self.rounding, error - curvature)
            self.samples.append((size, error))

    def verdict(self) -> tuple[bool, str, str]:
        """Success, status and words once no step lowers the cost any more."""
        promised = self.decrement * self.lin.cost
        step = float(np.linalg.norm(self.a / self.s))
        size = float(np.linalg.norm(self.d * self.x))
        if size > 0 and step <= XTOL * size:
            return True, "converged_to_rounding", (
                f"converged to rounding: no step lowers the cost and a Gauss-Newton step "
                f"would move the parameters by {step / size:.2g} of themselves, below "
                f"{XTOL:g}")
        noise = max(self.noise, ROUNDING_FLOOR * np.finfo(float).eps * self.lin.cost)
        if promised <= NOISE_FACTOR * noise:
            self.noise = noise
            return True, "converged_to_rounding", (
                f"converged to rounding: no step lowers the cost; the decrease a "
                f"Gauss-Newton step predicts ({self.decrement:.2g} of the cost) is within "
                f"the rounding noise of the cost ({self.noise / self.lin.cost:.2g} of it)")
        return False, "stalled", (
            f"failed: stalled, no step lowers the cost although a Gauss-Newton step predicts "
            f"a decrease of {self.decrement:.2g} of it, above the rounding noise of the cost "
            f"({self.noise / self.lin.cost:.2g} of it): the point is not stationary")


def _polish(steps: _Steps, x: np.ndarray, lin: _Linearisation,
            linearise: Callable[[np.ndarray], _Linearisation],
            cost_at: Callable[[np.ndarray], float]) -> tuple[np.ndarray, _Linearisation]:
    """Converged to rounding: take the last Gauss–Newton step, which the cost can no longer
    judge, when the cost stays within its rounding noise.  The step comes from the
    accumulated R factor, which resolves the minimum more finely than the cost does, so
    the estimate no longer depends on where rounding stopped the search (the same data in
    shards or in memory give the same estimate).

    A step of at most :data:`KEEP_R` of the parameters is checked by its cost alone (a
    pass of residuals, no derivatives, no R): the linearisation kept is the last one's R
    with the residual moved along it, R moving by about ten times the step's share of
    the parameters (the standard errors to about 8 digits).  A longer step is linearised
    again (NIST's Nelson, Lanczos3 and MGH17 polish by 3e-8 to 8e-8 of the parameters:
    the R kept there gave their certified standard errors to 6.4-6.5 digits, not 8)."""
    z = -(steps.vt.T @ (steps.a / steps.s))
    step = np.zeros(len(x))
    step[steps.free] = z / steps.d[steps.free]
    trial = np.clip(x + step, steps.lower, steps.upper)
    if not np.any(trial != x):
        return x, lin
    allowed = lin.cost + max(NOISE_FACTOR * steps.noise, POLISH * lin.cost)
    size = float(np.linalg.norm(steps.d * x))
    if float(np.linalg.norm(steps.d * (trial - x))) > KEEP_R * size:
        polished = linearise(trial)
        if polished.finite and polished.cost <= allowed:
            return trial, polished
        return x, lin
    cost = cost_at(trial)
    if math.isfinite(cost) and cost <= allowed:
        c = lin.c + lin.r_x @ (trial - x)
        return trial, _Linearisation(cost, lin.r_x, c, lin.r_theta, lin.rows)
    return x, lin


def solve_trust_region(
    objective: Objective,
    dataset: Dataset,
    theta0: np.ndarray,
    progress: Callable[[str], None] | None = None,
    max_iter: int = 200,
    label: str = "lm",
) -> SolverOutput:
    """Minimise the objective with a trust-region Levenberg–Marquardt method from ``theta0``.

    Parameters
    ----------
    objective
        Constraints and free parameters.
    dataset
        Observations to solve on.
    theta0
        Initial values of all parameters (fixed ones stay); free ones outside their bounds
        are moved onto them.
    progress
        Called with one line per iteration (None: silent).
    max_iter
        Largest number of trial steps (each one evaluation of the residuals).
    label
        Name shown in progress lines.

    Returns
    -------
    SolverOutput
        ``method == "lm"``.  ``success`` only when a first-order test holds (see the module
        docstring); otherwise the best iterate seen, with the reason it stopped.
    """
    start = time.perf_counter()
    problem = objective.problem
    idx, scales = objective.index, objective.scales
    params = [problem.parameters[i] for i in idx]
    lower = np.array([q.lower / s for q, s in zip(params, scales, strict=True)])
    upper = np.array([q.upper / s for q, s in zip(params, scales, strict=True)])
    base = np.array(theta0, dtype=float)
    x = np.clip(base[idx] / scales, lower, upper)
    # the start itself, bit for bit, where clipping left it finite: ``scales * (θ/scales)`` can
    # differ from θ in its last bit, and then the stage's analysis at the start (its R
    # kept by the objective) is not found and the first linearisation is a pass again
    x_start = x.copy() if np.all(np.isfinite(x)) and np.array_equal(
        x, base[idx] / scales) else None

    def theta_of(x: np.ndarray) -> np.ndarray:
        theta = base.copy()
        if x_start is None or not np.array_equal(x, x_start):
            theta[idx] = scales * x
        return theta

    def linearise(x: np.ndarray) -> _Linearisation:
        r, c, tail, rows = objective.accumulate_r(dataset, theta_of(x))
        return _Linearisation(float(c @ c + tail), r * scales[None, :], c, r, rows)

    def cost_at(x: np.ndarray) -> float:     # the polished point: the analysis's next
        return objective.cost(dataset, theta_of(x), keep=True)

    lin = linearise(x)
    cost0 = lin.cost
    ok, status, words = False, "", ""
    iterations = 0
    d = np.zeros(len(x))
    radius = 0.0
    rounding = 0.0          # the rounding of the cost measured so far, relative to it
    while True:
        if not lin.finite:
            status, words = "invalid_number", ("failed: a residual or derivative is NaN or "
                                               "inf at the start")
            break
        if lin.cost == 0.0 or (iterations > 0 and lin.cost <= EXACT_FIT**2 * cost0):
            ok, status = True, "exact_fit"
            words = ("converged: exact fit (the residual vanished)" if lin.cost == 0.0 else
                     f"converged: exact fit (the residual norm fell below {EXACT_FIT:g} of "
                     "its starting value, to rounding)")
            break
        free = ~_held(x, lower, upper, lin.gradient)
        d = np.maximum(d, np.linalg.norm(lin.r_x, axis=0))
        d = np.where(d > 0, d, 1.0)
        u, s, vt = np.linalg.svd(lin.r_x[:, free] / d[free][None, :], full_matrices=False)
        a = u.T @ lin.c
        rank = int(np.sum(s > rank_tolerance(s, lin.rows)))
        s, a, vt = s[:rank], a[:rank], vt[:rank]
        decrement = float(a @ a) / lin.cost
        instrument.record_decrement(decrement)
        if decrement < GN_DECREMENT:
            ok, status = True, "converged"
            words = (f"converged: a Gauss-Newton step would lower the cost by less than "
                     f"{GN_DECREMENT:g} of itself")
            break
        if iterations == 0:
            size = float(np.linalg.norm(d * x))
            radius = size if size > 0 else 1.0
        step_out = _Steps(lin, x, lower, upper, free, d, s, a, vt, decrement,
                          rounding * lin.cost)
        if iterations > 0 and step_out.settled():
            ok, status, words = True, "converged_to_rounding", step_out.settled_words()
            x, lin = _polish(step_out, x, lin, linearise, cost_at)
            break
        if iterations > 0 and decrement <= NOISE_FACTOR * ROUNDING_FLOOR * EPS:
            ok, status = True, "converged_to_rounding"
            words = (f"converged to rounding: a Gauss-Newton step would lower the cost by "
                     f"{decrement:.2g} of itself, within the rounding of a sum of squares "
                     f"({NOISE_FACTOR * ROUNDING_FLOOR:g} machine epsilons)")
            x, lin = _polish(step_out, x, lin, linearise, cost_at)
            break
        fresh = True   # the first trial of a linearisation is evaluated with derivatives
        while not step_out.accepted:
            if iterations >= max_iter:
                status, words = "iteration_limit", (
                    f"stopped: iteration limit ({max_iter}) reached before convergence (a "
                    f"Gauss-Newton step would still lower the cost by {decrement:.2g} of "
                    "itself)")
                break
            if radius <= STALL * max(float(np.linalg.norm(d * x)), 1.0):
                ok, status, words = step_out.verdict()
                if ok:
                    x, lin = _polish(step_out, x, lin, linearise, cost_at)
                break
            trial, predicted, size = step_out.trial(radius)
            iterations += 1
            ahead: _Linearisation | None = None
            with np.errstate(over="ignore", invalid="ignore"):  # inf/NaN: a rejected trial
                if predicted <= 0:
                    cost = math.nan
                elif fresh:   # most first trials are taken: one pass instead of two
                    ahead = linearise(trial)
                    cost = ahead.cost if ahead.finite else math.nan
                else:
                    cost = objective.cost(dataset, theta_of(trial))
            fresh = False
            ratio = (lin.cost - cost) / predicted if math.isfinite(cost) else -math.inf
            if ratio < 0.25:
                radius = 0.25 * min(radius, size) if size > 0 else 0.25 * radius
            elif ratio > 0.75:
                radius = max(radius, 2.0 * size)
            if progress is not None:
                progress(f"  {label}: iteration {iterations:3d}  cost {lin.cost:.6e}  "
                         f"trial {cost:.6e}  step {size:.3e} (scaled)  ratio {ratio:.3g}")
            if ratio > ACCEPT:
                candidate = ahead if ahead is not None else linearise(trial)
                if candidate.finite:
                    step_out.accepted = True
                    x, lin = trial, candidate
                    instrument.record_iteration(label, iterations, cost, x)
                    continue
                radius = 0.25 * min(radius, size)  # J is not finite there: a smaller step
            step_out.rejected(cost, predicted, size)
            if step_out.settled():
                ok, status, words = True, "converged_to_rounding", step_out.settled_words()
                step_out.noise = max(step_out.noise, step_out.rounding)
                x, lin = _polish(step_out, x, lin, linearise, cost_at)
                break
        rounding = max(rounding, step_out.rounding / step_out.lin.cost
                       if step_out.lin.cost > 0 else 0.0)
        if not step_out.accepted:
            break
        if float(np.max(np.abs(x))) > DIVERGED:
            status, words = "diverged", (
                f"failed: the iterates diverged (a parameter passed {DIVERGED:g} times its "
                "nominal scale)")
            break
    return SolverOutput(theta_of(x), objective.free.copy(), "lm", ok, status,
                        f"trust-region Levenberg-Marquardt: {words}; {iterations} "
                        f"iterations", lin.r_theta, lin.rows, lin.cost, iterations,
                        time.perf_counter() - start)
