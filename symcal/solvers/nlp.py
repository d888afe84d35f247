"""Nonlinear path: minimise Σ (g/σ)² with IPOPT through ``casadi.nlpsol``.

* Derivatives are exact: the Jacobian of the one-observation residual comes from CasADi's
  AD, evaluated over all observations with a serial ``map``, chunk by chunk.
* IPOPT receives the Gauss-Newton Hessian 2·JᵀJ, what a least-squares problem needs to
  converge in few iterations.  Jᵀg and JᵀJ are accumulated with BLAS per chunk, so no
  N × n Jacobian is stored and the expression graph never grows with N.
* Cost, gradient and Hessian reach IPOPT through CasADi callbacks that share one
  evaluation per iterate.  A trial point is evaluated with its derivatives (one pass per
  accepted iteration); after a rejected trial, trials evaluate residuals only until one
  is accepted.
* IPOPT works on x = θ_free / scale (each parameter's nominal magnitude), with bounds.
* A failed solve returns its last iterate, marked failed; it is never a silent success.
* Ctrl-C (KeyboardInterrupt, or the command line's SIGTERM, a subclass of it) inside a
  callback would be swallowed by CasADi and reported as a failed evaluation: the callbacks
  catch it, answer with zeros so that IPOPT ends its iteration at once, stop IPOPT through
  the iteration callback, and the interrupt is raised again when IPOPT returns.
"""

from __future__ import annotations

import contextlib
import math
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from types import FrameType
from typing import Any

import casadi as ca
import numpy as np

from symcal.solvers import instrument
from symcal.solvers.base import SolverOutput
from symcal.solvers.objective import Objective, Source

#: IPOPT's return statuses in words; the boolean says whether the estimate can be used.
PRINT_LEVEL = 0
#: Converged when a Gauss-Newton step would lower the cost by less than this fraction.
GN_DECREMENT = 1e-14
STATUS_WORDS: dict[str, tuple[bool, str]] = {
    "Gauss_Newton_Converged": (True, "converged: a Gauss-Newton step would lower the cost "
                                     f"by less than {GN_DECREMENT:g} of itself"),
    "Solve_Succeeded": (True, "converged to the requested tolerance"),
    "Solved_To_Acceptable_Level": (True, "converged to the acceptable (looser) tolerance"),
    "Search_Direction_Becomes_Too_Small": (
        True, "stopped: the steps became too small to change the estimate"),
    "Maximum_Iterations_Exceeded": (False, "stopped: iteration limit reached before "
                                           "convergence"),
    "Maximum_CpuTime_Exceeded": (False, "stopped: time limit reached before convergence"),
    "Maximum_WallTime_Exceeded": (False, "stopped: time limit reached before convergence"),
    "Diverging_Iterates": (False, "failed: the iterates diverged"),
    "Invalid_Number_Detected": (False, "failed: a residual or derivative became NaN or inf"),
    "Restoration_Failed": (False, "failed: no acceptable step could be found"),
    "Error_In_Step_Computation": (False, "failed: the step could not be computed"),
    "Infeasible_Problem_Detected": (False, "failed: the bounds cannot be satisfied"),
    "User_Requested_Stop": (False, "stopped by the user"),
    "NonIpopt_Exception_Thrown": (False, "failed: an evaluation raised an error"),
}


class _Stop:
    """Ctrl-C and SIGTERM while IPOPT runs: raised only inside symcal's own evaluations
    (where they are caught), recorded anywhere else (in IPOPT or CasADi's glue code, which
    would swallow them), and raised again once IPOPT has stopped."""

    def __init__(self) -> None:
        self.interrupt: KeyboardInterrupt | None = None
        self.inside = False

    def call(self, fn: Callable[[Any], Any], arg: Any, default: Any) -> Any:
        """``fn(arg)``, or ``default`` once interrupted (zeros: IPOPT sees a stationary
        point and ends its iteration at once)."""
        if self.interrupt is None:
            try:
                self.inside = True
                value = fn(arg)
                self.inside = False
                return value
            except KeyboardInterrupt as exc:
                self.inside = False
                self.interrupt = self.interrupt or exc
        return default

    @contextlib.contextmanager
    def deferred(self) -> Iterator[None]:
        """While IPOPT runs, record SIGINT and SIGTERM (when Python handles them) and
        raise them only inside an evaluation; main thread only."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        previous: dict[int, Any] = {}

        def handler(signum: int, frame: FrameType | None) -> None:
            try:
                previous[signum](signum, frame)
            except KeyboardInterrupt as exc:
                self.interrupt = self.interrupt or exc
                if self.inside:
                    self.inside = False
                    raise

        for sig in (int(signal.SIGINT), int(signal.SIGTERM)):
            handler_before = signal.getsignal(sig)
            if callable(handler_before):
                previous[sig] = handler_before
                signal.signal(sig, handler)
        try:
            yield
        finally:
            for sig, handler_before in previous.items():
                signal.signal(sig, handler_before)

    def reraise(self) -> None:
        """Raise the recorded interrupt, if any."""
        if self.interrupt is not None:
            raise self.interrupt


class _Oracle:
    """Cost, gradient and Gauss-Newton Hessian of the scaled problem, cached per iterate."""

    def __init__(self, objective: Objective, dataset: Source, theta0: np.ndarray) -> None:
        self.objective = objective
        self.dataset = dataset
        self.base = np.array(theta0, dtype=float)
        self.index = objective.index
        self.scales = objective.scales
        self.key: bytes | None = None
        self.terms: tuple[float, np.ndarray, np.ndarray] | None = None
        self.costs: dict[bytes, float] = {}
        self.cost_scale = 1.0
        self.evaluations = 0
        self.best: tuple[float, np.ndarray] | None = None   # lowest cost seen, at x
        self.nonfinite = 0                                  # evaluations giving NaN/inf
        self.trial_linearised = True    # evaluate trial points with their derivatives
        self.trials: set[bytes] = set()  # trial points evaluated since the last accepted

    def _seen(self, x: np.ndarray, cost: float) -> None:
        if not math.isfinite(cost):
            self.nonfinite += 1
        elif self.best is None or cost < self.best[0]:
            self.best = (cost, x.copy())
        self.stop = _Stop()

    def theta(self, x: np.ndarray) -> np.ndarray:
        theta = self.base.copy()
        theta[self.index] = self.scales * x
        return theta

    def cost(self, x: np.ndarray) -> float:
        """The scaled cost at ``x``.  A trial point is evaluated with its derivatives (one
        linearised pass, not a residual pass and then a linearised one): a Gauss-Newton
        step is nearly always accepted, and IPOPT then asks for the gradient and Hessian
        at that point.  After a rejected trial the next one is evaluated by a residual
        pass only, until a trial is accepted again."""
        key = x.tobytes()
        if key == self.key and self.terms is not None:
            return self.terms[0] / self.cost_scale
        if key not in self.costs:
            if len(self.costs) > 64:
                self.costs.clear()
            if self.trials:             # the previous trial was not accepted
                self.trial_linearised = False
            if self.trial_linearised:
                self.costs[key] = self._terms(x)[0]
            else:
                self.costs[key] = self.objective.cost(self.dataset, self.theta(x))
                self._seen(x, self.costs[key])
            self.trials.add(key)
        return self.costs[key] / self.cost_scale

    def _terms(self, x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        key = x.tobytes()
        if key in self.trials:          # derivatives asked at a trial point: accepted
            self.trials.clear()
            self.trial_linearised = True
        if key != self.key:
            self.evaluations += 1
            cost, jtg, jtj = self.objective.normal_equations(self.dataset, self.theta(x))
            self._seen(x, cost)
            self.key, self.terms = key, (cost, jtg, jtj)
        assert self.terms is not None
        return self.terms

    def gradient(self, x: np.ndarray) -> np.ndarray:
        _, jtg, _ = self._terms(x)
        return 2 * self.scales * jtg / self.cost_scale

    def hessian(self, x: np.ndarray) -> np.ndarray:
        _, _, jtj = self._terms(x)
        return 2 * self.scales[:, None] * jtj * self.scales[None, :] / self.cost_scale

    def decrement(self, x: np.ndarray) -> float:
        """Fraction of the cost a Gauss-Newton step from ``x`` would remove."""
        cost, jtg, jtj = self._terms(x)
        d = self.scales
        step = np.linalg.lstsq(d[:, None] * jtj * d[None, :], d * jtg, rcond=1e-13)[0]
        value = float((d * jtg) @ step / cost) if cost > 0 else 0.0
        instrument.record_decrement(value)
        return value


class _Call(ca.Callback):
    """A CasADi function of x (n) evaluated by a Python method of the oracle."""

    def __init__(self, name: str, n: int, shape: tuple[int, int],
                 fn: Callable[[np.ndarray], float | np.ndarray], stop: _Stop,
                 gradient: _Call | None = None) -> None:
        ca.Callback.__init__(self)
        self.n, self.shape, self.fn, self.gradient = n, shape, fn, gradient
        self.stop = stop
        self.construct(name, {"enable_fd": False})

    def has_jacobian(self) -> bool:
        return self.gradient is not None

    def get_jacobian(self, name: str, inames: Sequence[str], onames: Sequence[str],
                     opts: Mapping[str, Any]) -> ca.Function:
        x, out = ca.MX.sym("x", self.n), ca.MX.sym("out", *self.shape)
        assert self.gradient is not None
        return ca.Function(name, [x, out], [self.gradient(x).T], list(inames), list(onames),
                           dict(opts))

    def get_n_in(self) -> int:
        return 1

    def get_n_out(self) -> int:
        return 1

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(self.n)

    def get_sparsity_out(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(*self.shape)

    def eval(self, arg: Sequence[Any]) -> list:
        value = self.stop.call(self.fn, np.array(arg[0]).ravel(), np.zeros(self.shape))
        return [ca.DM(np.reshape(value, self.shape))]


class _Progress(ca.Callback):
    """IPOPT iteration callback: reports progress and keeps the last iterate."""

    def __init__(self, n: int, report: Callable[[str], None] | None, cost_scale: float,
                 label: str, converged: Callable[[np.ndarray], bool], stop: _Stop) -> None:
        ca.Callback.__init__(self)
        self.converged = converged
        self.stop = stop
        self.stopped = False
        self.n = n
        self.report = report
        self.cost_scale = cost_scale
        self.label = label
        self.iteration = 0
        self.last_x: np.ndarray | None = None
        self.construct("progress", {})

    def get_n_in(self) -> int:
        return ca.nlpsol_n_out()

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ca.nlpsol_out(i)

    def get_name_out(self, i: int) -> str:
        return "ret"

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        name = ca.nlpsol_out(i)
        if name == "f":
            return ca.Sparsity.scalar()
        if name in ("x", "lam_x"):
            return ca.Sparsity.dense(self.n)
        return ca.Sparsity(0, 0)

    def eval(self, arg: Sequence[Any]) -> list:
        return [1 if self.stop.call(self._iteration, arg, True) else 0]

    def _iteration(self, arg: Sequence[Any]) -> bool:
        """Report one iteration; whether the solve has converged."""
        x = np.array(arg[0]).ravel()
        step = float("nan") if self.last_x is None else float(np.linalg.norm(x - self.last_x))
        if self.report is not None:
            cost = float(arg[1]) * self.cost_scale
            self.report(f"  {self.label}: iteration {self.iteration:3d}  cost {cost:.6e}  "
                        f"step {step:.3e} (scaled)")
        instrument.record_iteration(self.label, self.iteration,
                                    float(arg[1]) * self.cost_scale, x)
        self.last_x = x
        self.iteration += 1
        self.stopped = self.converged(x)
        return self.stopped


def _ipopt_round(
    oracle: _Oracle, x0: np.ndarray, lower: np.ndarray, upper: np.ndarray,
    progress: Callable[[str], None] | None, max_iter: int, tol: float, label: str,
    extra: Mapping[str, Any],
) -> tuple[np.ndarray, dict, _Progress]:
    """One IPOPT run on the cost normalised by its value at ``x0``."""
    n = len(x0)
    cost0 = oracle.cost(x0) * oracle.cost_scale
    oracle.cost_scale = cost0 if cost0 > 0 and math.isfinite(cost0) else 1.0
    stop = oracle.stop
    gradient = _Call("ls_gradient", n, (n, 1), oracle.gradient, stop)
    calls = [_Call("ls_cost", n, (1, 1), oracle.cost, stop, gradient), gradient,
             _Call("ls_gauss_newton", n, (n, n), oracle.hessian, stop)]
    x = ca.MX.sym("x", n)
    lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", 0, 1)
    empty = ca.MX.sym("p", 0, 1)
    callback = _Progress(n, progress, oracle.cost_scale, label,
                         lambda z: oracle.decrement(z) < GN_DECREMENT, stop)
    opts: dict[str, Any] = {
        "grad_f": ca.Function("grad_f", [x, empty], [calls[0](x), calls[1](x)]),
        "hess_lag": ca.Function("hess_lag", [x, empty, lam_f, lam_g],
                                [ca.triu(lam_f * calls[2](x))]),
        "iteration_callback": callback,
        "error_on_fail": False,
        "show_eval_warnings": False,   # counted by the oracle, summarised in one line
        "print_time": False,
        "ipopt": {"print_level": PRINT_LEVEL, "sb": "yes", "max_iter": max_iter, "tol": tol,
                  "acceptable_tol": 1e-6, "acceptable_iter": 5, **extra},
    }
    nlp: dict[str, Any] = {"x": x, "p": empty, "f": calls[0](x)}
    solver = ca.nlpsol("symcal", "ipopt", nlp, opts)
    with stop.deferred():
        sol = solver(x0=x0, lbx=lower, ubx=upper)
    stop.reraise()
    x_opt = np.array(sol["x"]).ravel()
    if not np.all(np.isfinite(x_opt)) and callback.last_x is not None:
        x_opt = callback.last_x
    return x_opt, solver.stats(), callback


def solve_ipopt(
    objective: Objective,
    dataset: Source,
    theta0: np.ndarray,
    progress: Callable[[str], None] | None = None,
    max_iter: int = 200,
    tol: float = 1e-8,
    label: str = "ipopt",
    max_rounds: int = 4,
    extra: Mapping[str, Any] | None = None,
) -> SolverOutput:
    """Minimise the objective with IPOPT (Gauss-Newton Hessian), from ``theta0``.

    Convergence is tested after every iteration as a least-squares solver should: stop
    when a Gauss-Newton step would lower the cost by less than ``GN_DECREMENT`` of itself
    (scale-free; IPOPT's own optimality tolerance cannot be met on costs that are flat to
    machine precision along near-null directions).  If IPOPT stops on its own tolerance,
    which is relative to the cost at the start of the run, after lowering the cost more
    than twofold, it is run again from its result, renormalised (at most ``max_rounds``
    runs; every iteration counts against ``max_iter``).

    Parameters
    ----------
    objective
        Constraints and free parameters.
    dataset
        Observations to solve on.
    theta0
        Initial values of all parameters (fixed ones stay).
    progress
        Called with one line per iteration (None: silent).
    max_iter, tol
        Iteration limit over all runs, and IPOPT's tolerance.
    label
        Name shown in progress lines.
    extra
        Further IPOPT options by name (a problem's ``solver: {ipopt: ...}``).

    Returns
    -------
    SolverOutput
        ``method == "ipopt"``; ``success`` False with the last iterate when IPOPT failed.
    """
    start = time.perf_counter()
    problem = objective.problem
    idx, scales = objective.index, objective.scales
    oracle = _Oracle(objective, dataset, theta0)
    params = [problem.parameters[i] for i in idx]
    lower = np.array([q.lower / s for q, s in zip(params, scales, strict=True)])
    upper = np.array([q.upper / s for q, s in zip(params, scales, strict=True)])
    x = np.asarray(theta0, dtype=float)[idx] / scales
    iterations, rounds = 0, 0
    while True:
        before = oracle.cost(x) * oracle.cost_scale
        x, stats, callback = _ipopt_round(oracle, x, lower, upper, progress,
                                          max_iter - iterations, tol, label, extra or {})
        iterations += int(stats.get("iter_count", callback.iteration))
        rounds += 1
        status = str(stats.get("return_status", "unknown"))
        if callback.stopped and status == "User_Requested_Stop":
            status = "Gauss_Newton_Converged"
        ok, words = STATUS_WORDS.get(status, (bool(stats.get("success")), status))
        after = oracle.cost(x) * oracle.cost_scale
        if (not ok or status == "Gauss_Newton_Converged" or rounds >= max_rounds
                or iterations >= max_iter or not after < 0.5 * before):
            break
    if not ok and oracle.best is not None and not oracle.best[0] >= oracle.cost(x) * \
            oracle.cost_scale:
        x = oracle.best[1]              # a failed solve keeps the best iterate it saw
        words += "; the estimate is the best iterate seen"
    if oracle.nonfinite:
        words += (f"; {oracle.nonfinite} trial point(s) gave a NaN or infinite cost (IPOPT "
                  "stepped back from them)")
    theta = oracle.theta(x)
    r, c, tail, rows = objective.accumulate_r(dataset, theta)
    rss = float(np.sum(c**2) + tail)
    if not math.isfinite(rss):
        ok, words = False, "failed: the cost is not finite at the last iterate"
    runs = f" ({rounds} runs)" if rounds > 1 else ""
    return SolverOutput(theta, objective.free.copy(), "ipopt", ok, status,
                        f"IPOPT with a Gauss-Newton Hessian{runs}: {words}", r, rows, rss,
                        iterations, time.perf_counter() - start)
