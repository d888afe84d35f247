"""Strong peers: what a competent user writes with an exact Jacobian (issue 26).

The residuals of ``bench.peers`` written again for an exact Jacobian, two ways:

* in JAX (float64), the Jacobian by ``jax.jacfwd`` (forward-mode AD compiled by XLA);
* in CasADi, for ONE observation, its Jacobian by CasADi's AD, both mapped over the N
  observations with ``Function.map`` (what a CasADi user writes; far cheaper than jacfwd
  here, whose 49 tangents each pass through the whole residual).

and these solvers on them:

* ``scipy.optimize.least_squares`` trust-region reflective (``trf``, ``tr_solver="exact"``)
  with the JAX Jacobian and with the CasADi one, and MINPACK's Levenberg–Marquardt (``lm``)
  with the CasADi one;
* Ceres (``pyceres``), Levenberg–Marquardt with dense QR, one residual block of all the
  residuals with the CasADi Jacobian as its analytic Jacobian;
* optimistix's ``LevenbergMarquardt``, the whole solve one ``jax.jit`` program.

All four form the 3N × 49 (dual) or N × 36 (linear) Jacobian in memory, which symcal never
does.  These packages are optional (``pip install -e ".[bench]"``): a peer whose package is
missing is reported as not installed.  Every peer's first call in a process includes its
compilation (XLA); the harness reports that first call as the cold time.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from .peers import HARMONICS, L_O, L_S, F, PeerResult

#: The peers of this module: method name -> (package to import, label).
PEERS = {
    "ls_trf_jax": ("jax", "scipy least_squares trf, JAX Jacobian"),
    "ls_trf_casadi": ("casadi", "scipy least_squares trf, CasADi Jacobian"),
    "ls_lm_casadi": ("casadi", "scipy least_squares lm (MINPACK), CasADi Jacobian"),
    "ceres": ("pyceres", "Ceres (pyceres) LM, dense QR, CasADi Jacobian"),
    "optimistix": ("optimistix", "optimistix LevenbergMarquardt (jax.jit)"),
}
#: Tolerances (ftol, xtol, gtol and their kin): scipy's defaults, what a user leaves.
#: Every peer reaches the lowest J to 1e-11 with them here (1e-15 only adds iterations:
#: 4 -> 30 for trf at the dual problem's N = 1e3); the harness checks it (1e-10).
TOL = 1e-8
MAX_STEPS = 200


def available(method: str) -> str | None:
    """None when the peer's packages import, else why not."""
    import importlib

    main = PEERS[method][0]
    for package in {main, "jax"} if main in ("jax", "optimistix") else {main}:
        try:
            importlib.import_module(package)
        except ImportError as exc:
            return (f"not installed ({exc.name}): pip install -e \".[bench]\"")
    return None


def _jax() -> Any:
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_platforms", "cpu")
    return jax


def _segment_error(jnp: Any, k: Any, p: Any, q: Any = None) -> Any:
    e = k[0] + 0 * p
    for j, m in enumerate(HARMONICS):
        phase = (m * F) * p
        e = e + k[1 + 2 * j] * jnp.sin(phase) + k[2 + 2 * j] * jnp.cos(phase)
    if q is not None:
        e = e + k[9] * jnp.sin(F * q) + k[10] * jnp.cos(F * q)
    return e


def platen_residual(theta: Any, cols: Mapping[str, Any]) -> Any:
    """g_p of eq. (5) in JAX (``bench.peers.platen_residual``)."""
    import jax.numpy as jnp

    k = theta.reshape(4, 9)
    ph = [cols[f"p{i + 1}"] + _segment_error(jnp, k[i], cols[f"p{i + 1}"])
          for i in range(4)]
    return (ph[0] - ph[2]) - (ph[1] - ph[3])


def dual_residual(theta: Any, cols: Mapping[str, Any]) -> Any:
    """(g_x, g_y, g_p) of eq. (11) and (5) in JAX (``bench.peers.dual_residual``)."""
    import jax.numpy as jnp

    k = theta[:44].reshape(4, 11)
    h, l_x, l_y, o_x, o_y = (theta[44 + i] for i in range(5))
    p = [cols[f"p{i + 1}"] for i in range(4)]
    px_raw, py_raw = (p[0] + p[2]) / 2, (p[1] + p[3]) / 2
    theta_raw = ((p[0] - p[2]) + (p[1] - p[3])) / (2 * L_S)
    q = [py_raw - L_O * theta_raw, px_raw + L_O * theta_raw,
         py_raw + L_O * theta_raw, px_raw - L_O * theta_raw]
    ph = [p[i] + _segment_error(jnp, k[i], p[i], q[i]) for i in range(4)]
    angle = ((ph[0] - ph[2]) / L_S + (ph[1] - ph[3]) / L_S) / 2
    pos_x, pos_y = (ph[0] + ph[2]) / 2, (ph[1] + ph[3]) / 2
    c_x, c_y = h * jnp.tan(cols["psi_x"]), h * jnp.tan(cols["psi_y"])
    cos, sin = jnp.cos(angle), jnp.sin(angle)
    g_x = -pos_x + cos * c_x - sin * c_y - l_y * sin + l_x * cos + o_x
    g_y = -pos_y + sin * c_x + cos * c_y + l_y * cos + l_x * sin + o_y
    g_p = (ph[0] - ph[2]) - (ph[1] - ph[3])
    return jnp.concatenate([g_x, g_y, g_p])


COLUMNS = {"linear": ("p1", "p2", "p3", "p4"),
           "dual": ("p1", "p2", "p3", "p4", "psi_x", "psi_y")}


def _casadi_residual(problem: str) -> tuple[Any, Any, Any]:
    """The residual of ONE observation in CasADi SX: (θ, u, g), u the columns of
    :data:`COLUMNS` and g the problem's constraints (1 for linear, 3 for dual)."""
    import casadi as ca

    class _Ops:
        sin, cos, tan = ca.sin, ca.cos, ca.tan

        @staticmethod
        def concatenate(parts: list[Any]) -> Any:
            return ca.vertcat(*parts)

    n = 36 if problem == "linear" else 49
    theta = ca.SX.sym("theta", n)
    u = ca.SX.sym("u", len(COLUMNS[problem]))
    cols = {c: u[i] for i, c in enumerate(COLUMNS[problem])}
    if problem == "linear":
        k = [theta[9 * i:9 * i + 9] for i in range(4)]
        ph = [cols[f"p{i + 1}"] + _segment_error(_Ops, k[i], cols[f"p{i + 1}"])
              for i in range(4)]
        return theta, u, (ph[0] - ph[2]) - (ph[1] - ph[3])
    k = [theta[11 * i:11 * i + 11] for i in range(4)]
    h, l_x, l_y, o_x, o_y = (theta[44 + i] for i in range(5))
    p = [cols[f"p{i + 1}"] for i in range(4)]
    px_raw, py_raw = (p[0] + p[2]) / 2, (p[1] + p[3]) / 2
    theta_raw = ((p[0] - p[2]) + (p[1] - p[3])) / (2 * L_S)
    q = [py_raw - L_O * theta_raw, px_raw + L_O * theta_raw,
         py_raw + L_O * theta_raw, px_raw - L_O * theta_raw]
    ph = [p[i] + _segment_error(_Ops, k[i], p[i], q[i]) for i in range(4)]
    angle = ((ph[0] - ph[2]) / L_S + (ph[1] - ph[3]) / L_S) / 2
    pos_x, pos_y = (ph[0] + ph[2]) / 2, (ph[1] + ph[3]) / 2
    c_x, c_y = h * ca.tan(cols["psi_x"]), h * ca.tan(cols["psi_y"])
    cos, sin = ca.cos(angle), ca.sin(angle)
    g_x = -pos_x + cos * c_x - sin * c_y - l_y * sin + l_x * cos + o_x
    g_y = -pos_y + sin * c_x + cos * c_y + l_y * cos + l_x * sin + o_y
    g_p = (ph[0] - ph[2]) - (ph[1] - ph[3])
    return theta, u, ca.vertcat(g_x, g_y, g_p)


class CasadiCompiled:
    """The residual and its Jacobian by CasADi: one observation's functions mapped over
    the N observations (serial map, CasADi's interpreter), residuals stacked constraint
    by constraint as ``bench.peers`` stacks them."""

    def __init__(self, problem: str, cols: Mapping[str, np.ndarray]) -> None:
        import casadi as ca

        theta, u, g = _casadi_residual(problem)
        self.u = np.vstack([np.asarray(cols[c], dtype=float) for c in COLUMNS[problem]])
        n_obs = self.u.shape[1]
        self.ng, self.n = int(g.shape[0]), int(theta.shape[0])
        self.f = ca.Function("g", [theta, u], [g]).map(n_obs, "serial")
        self.j = ca.Function("J", [theta, u], [ca.jacobian(g, theta)]).map(n_obs, "serial")
        self.residuals = 0
        self.jacobians = 0

    def fun(self, x: np.ndarray) -> np.ndarray:
        """Residuals at ``x`` (``ng·N``)."""
        self.residuals += 1
        return np.asarray(self.f(x, self.u)).ravel()

    def jac(self, x: np.ndarray) -> np.ndarray:
        """The Jacobian at ``x`` (``ng·N × n``)."""
        self.jacobians += 1
        blocks = np.asarray(self.j(x, self.u))                # ng × (N·n)
        n_obs = blocks.shape[1] // self.n
        return blocks.reshape(self.ng, n_obs, self.n).reshape(self.ng * n_obs, self.n)


class Compiled:
    """The residual and its Jacobian of one problem's data, compiled by XLA on first
    call (the data are arguments, not constants baked into the program)."""

    def __init__(self, problem: str, cols: Mapping[str, np.ndarray]) -> None:
        jax = _jax()
        import jax.numpy as jnp

        self.residual_fn = platen_residual if problem == "linear" else dual_residual
        self.cols = {c: jnp.asarray(cols[c], dtype=jnp.float64) for c in COLUMNS[problem]}
        self.f = jax.jit(self.residual_fn)
        self.j = jax.jit(jax.jacfwd(self.residual_fn))
        self.residuals = 0
        self.jacobians = 0

    def fun(self, x: np.ndarray) -> np.ndarray:
        """Residuals at ``x`` as numpy."""
        self.residuals += 1
        return np.asarray(self.f(x, self.cols))

    def jac(self, x: np.ndarray) -> np.ndarray:
        """The Jacobian at ``x`` as numpy (``m × n``)."""
        self.jacobians += 1
        return np.asarray(self.j(x, self.cols))


def least_squares(compiled: Compiled | CasadiCompiled, theta0: np.ndarray,
                  method: str) -> PeerResult:
    """``scipy.optimize.least_squares`` with the exact Jacobian."""
    import scipy.optimize

    start = time.perf_counter()
    compiled.residuals = compiled.jacobians = 0
    kwargs: dict[str, Any] = {"tr_solver": "exact"} if method == "trf" else {}
    sol = scipy.optimize.least_squares(compiled.fun, theta0, jac=compiled.jac, method=method,
                                       x_scale="jac", ftol=TOL, xtol=TOL, gtol=TOL,
                                       max_nfev=MAX_STEPS, **kwargs)
    seconds = time.perf_counter() - start
    r = compiled.fun(sol.x)
    return PeerResult(sol.x, float(r @ r), int(sol.nfev), compiled.residuals + compiled.jacobians,
                      seconds, f"status {sol.status}: {sol.message} ({int(sol.njev or 0)} "
                      "Jacobians)")


def ceres(compiled: Compiled | CasadiCompiled, theta0: np.ndarray) -> PeerResult:
    """Ceres through pyceres: Levenberg–Marquardt, dense QR, the exact Jacobian."""
    import pyceres

    m = int(compiled.fun(np.asarray(theta0, dtype=float)).size)
    n = int(theta0.size)

    class Cost(pyceres.CostFunction):  # type: ignore[misc,unused-ignore]
        def __init__(self) -> None:
            super().__init__()
            self.set_num_residuals(m)
            self.set_parameter_block_sizes([n])

        def Evaluate(self, parameters: Any, residuals: Any, jacobians: Any) -> bool:  # noqa: N802
            x = np.asarray(parameters[0])
            residuals[:] = compiled.fun(x)
            if jacobians is not None and jacobians[0] is not None:
                jacobians[0][:] = compiled.jac(x).ravel()
            return True

    start = time.perf_counter()
    compiled.residuals = compiled.jacobians = 0
    x = np.array(theta0, dtype=float)
    problem = pyceres.Problem()
    cost = Cost()
    problem.add_residual_block(cost, None, [x])
    options = pyceres.SolverOptions()
    options.linear_solver_type = pyceres.LinearSolverType.DENSE_QR
    options.trust_region_strategy_type = pyceres.TrustRegionStrategyType.LEVENBERG_MARQUARDT
    options.function_tolerance = TOL
    options.parameter_tolerance = TOL
    options.gradient_tolerance = TOL
    options.max_num_iterations = MAX_STEPS
    options.num_threads = 1
    options.minimizer_progress_to_stdout = False
    summary = pyceres.SolverSummary()
    pyceres.solve(options, problem, summary)
    seconds = time.perf_counter() - start
    r = compiled.fun(x)
    steps = int(summary.num_successful_steps + summary.num_unsuccessful_steps)
    return PeerResult(x, float(r @ r), steps, compiled.residuals + compiled.jacobians, seconds,
                      f"{summary.termination_type}: {summary.message}")


def optimistix(compiled: Compiled, theta0: np.ndarray,
               cache: dict[str, Any]) -> PeerResult:
    """optimistix's Levenberg–Marquardt, the whole solve one compiled XLA program."""
    jax = _jax()
    import jax.numpy as jnp
    import optimistix as optx

    if "solve" not in cache:
        residual = compiled.residual_fn

        def run(y0: Any, cols: Any) -> Any:
            solver: Any = optx.LevenbergMarquardt(rtol=TOL, atol=TOL)
            sol: Any = optx.least_squares(lambda y, args: residual(y, args), solver, y0,
                                     args=cols, max_steps=MAX_STEPS, throw=False)
            return sol.value, sol.stats["num_steps"], sol.result._value

        cache["solve"] = jax.jit(run)
    start = time.perf_counter()
    value, steps, code = cache["solve"](jnp.asarray(theta0, dtype=jnp.float64), compiled.cols)
    x = np.asarray(value)
    seconds = time.perf_counter() - start
    r = compiled.fun(x)
    verdict = "successful" if int(code) == 0 else "not successful"
    return PeerResult(x, float(r @ r), int(steps), int(steps), seconds,
                      f"optimistix result {int(code)} ({verdict}), {int(steps)} steps")


def runner(problem: str, method: str, cols: Mapping[str, np.ndarray]
           ) -> Callable[[np.ndarray], PeerResult]:
    """``theta0 -> PeerResult`` for the peer ``method`` on ``problem``'s data."""
    if method == "ls_trf_casadi":
        by_casadi = CasadiCompiled(problem, cols)
        return lambda theta0: least_squares(by_casadi, theta0, "trf")
    if method == "ls_lm_casadi":
        by_casadi = CasadiCompiled(problem, cols)
        return lambda theta0: least_squares(by_casadi, theta0, "lm")
    if method == "ceres":
        by_casadi = CasadiCompiled(problem, cols)
        return lambda theta0: ceres(by_casadi, theta0)
    compiled = Compiled(problem, cols)
    if method == "ls_trf_jax":
        return lambda theta0: least_squares(compiled, theta0, "trf")
    cache: dict[str, Any] = {}
    return lambda theta0: optimistix(compiled, theta0, cache)
