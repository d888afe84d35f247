"""What a user would write instead of symcal: the residuals in numpy, solved with scipy.

Everything here is written by hand from the equations in ``models/*.yaml`` and
``problems/*.yaml`` (Quaid & Rizzi eq. 3, 5, 9, 10, 11); nothing comes from symcal's
symbolic machinery.  The harness (``bench.problems.check_residuals``) checks that these
residuals agree with symcal's to 1e-12 at a test point before it times anything.

Parameter vectors are in symcal's order:

* linear problem (``platen_self_calibration.yaml``, 36 parameters):
  ``s1.k0..k8, s2.k0..k8, s3.k0..k8, s4.k0..k8``;
* dual problem (``dual_sensor_calibration.yaml``, 49 parameters):
  ``s1.k0..k10, s2.k0..k10, s3.k0..k10, s4.k0..k10, cs.h, l_x, l_y, o_x, o_y``.

The cost of both is J(θ) = Σ_obs Σ_constraints g² (equal weights, σ = 1, mm²).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np
import scipy.optimize

RHO = 1.016            # platen tooth pitch (mm), models/platen_segment.yaml
F = 2 * np.pi / RHO    # tooth frequency (rad/mm)
L_S = 9.7              # distance between the segments of a pair (mm)
L_O = 4.85             # lateral offset of each segment from the centre (mm)
HARMONICS = (1, 2, 4, 6)   # eq. (3): k1..k8 are sin/cos of these harmonics
T = TypeVar("T")


@dataclass(frozen=True)
class PeerResult:
    """Outcome of one peer solve."""

    theta: np.ndarray
    cost: float
    iterations: int | None
    evaluations: int
    seconds: float
    message: str


# --------------------------------------------------------------------------- the models


def fourier_basis(p: np.ndarray) -> np.ndarray:
    """φ(p) = [1, sin fp, cos fp, sin 2fp, cos 2fp, sin 4fp, cos 4fp, sin 6fp, cos 6fp]
    (N × 9): eq. (3) is e = φ(p)·k."""
    out = np.empty((len(p), 9))
    out[:, 0] = 1.0
    for j, m in enumerate(HARMONICS):
        phase = (m * F) * p
        out[:, 1 + 2 * j] = np.sin(phase)
        out[:, 2 + 2 * j] = np.cos(phase)
    return out


def segment_error(k: np.ndarray, p: np.ndarray, q: np.ndarray | None = None) -> np.ndarray:
    """e of one segment: eq. (3) (k0..k8), plus eq. (9)'s lateral k9, k10 when ``q``."""
    e = k[0] + np.zeros_like(p)
    for j, m in enumerate(HARMONICS):
        phase = (m * F) * p
        e += k[1 + 2 * j] * np.sin(phase) + k[2 + 2 * j] * np.cos(phase)
    if q is not None:
        e += k[9] * np.sin(F * q) + k[10] * np.cos(F * q)
    return e


# --------------------------------------------------------------------------- §3.1 linear


def platen_residual(theta: np.ndarray, cols: Mapping[str, np.ndarray]) -> np.ndarray:
    """g_p of eq. (5) for every observation (N), θ the 36 platen parameters."""
    k = np.asarray(theta).reshape(4, 9)
    ph = [cols[f"p{i + 1}"] + segment_error(k[i], cols[f"p{i + 1}"]) for i in range(4)]
    return (ph[0] - ph[2]) - (ph[1] - ph[3])


def platen_gamma(cols: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Γ and b of eq. (7): g_p = Γ k + b, Γ = [φ(p1), −φ(p2), −φ(p3), φ(p4)] (N × 36)."""
    p1, p2, p3, p4 = (cols[f"p{i}"] for i in range(1, 5))
    gamma = np.hstack([fourier_basis(p1), -fourier_basis(p2), -fourier_basis(p3),
                       fourier_basis(p4)])
    return gamma, (p1 - p3) - (p2 - p4)


def numpy_floor(theta0: np.ndarray, cols: Mapping[str, np.ndarray]) -> PeerResult:
    """The floor of the linear problem: assemble Γ with numpy, one ``lstsq`` (min-norm,
    as eq. 8's pseudo-inverse; θ0 is zero for the platen so no offset is needed)."""
    start = time.perf_counter()
    gamma, b = platen_gamma(cols)
    step, _, rank, _ = np.linalg.lstsq(gamma, -(gamma @ theta0 + b), rcond=None)
    theta = theta0 + step
    r = gamma @ theta + b
    cost = float(r @ r)
    return PeerResult(theta, cost, 0, 1, time.perf_counter() - start,
                      f"numpy lstsq (SVD), rank {rank}")


# --------------------------------------------------------------------------- §3.2 dual


def dual_residual(theta: np.ndarray, cols: Mapping[str, np.ndarray]) -> np.ndarray:
    """(g_x, g_y, g_p) of eq. (11) and (5) for every observation, stacked (3N)."""
    theta = np.asarray(theta)
    k = theta[:44].reshape(4, 11)
    h, l_x, l_y, o_x, o_y = theta[44:49]
    p = [cols[f"p{i + 1}"] for i in range(4)]
    px_raw, py_raw = (p[0] + p[2]) / 2, (p[1] + p[3]) / 2
    theta_raw = ((p[0] - p[2]) + (p[1] - p[3])) / (2 * L_S)
    q = [py_raw - L_O * theta_raw, px_raw + L_O * theta_raw,
         py_raw + L_O * theta_raw, px_raw - L_O * theta_raw]
    ph = [p[i] + segment_error(k[i], p[i], q[i]) for i in range(4)]
    angle = ((ph[0] - ph[2]) / L_S + (ph[1] - ph[3]) / L_S) / 2
    pos_x, pos_y = (ph[0] + ph[2]) / 2, (ph[1] + ph[3]) / 2
    c_x, c_y = h * np.tan(cols["psi_x"]), h * np.tan(cols["psi_y"])
    cos, sin = np.cos(angle), np.sin(angle)
    g_x = -pos_x + cos * c_x - sin * c_y - l_y * sin + l_x * cos + o_x
    g_y = -pos_y + sin * c_x + cos * c_y + l_y * cos + l_x * sin + o_y
    g_p = (ph[0] - ph[2]) - (ph[1] - ph[3])
    return np.concatenate([g_x, g_y, g_p])


# --------------------------------------------------------------------------- solvers


class _Counted(Generic[T]):
    """A residual (or cost) function that counts its calls."""

    def __init__(self, fn: Callable[[np.ndarray], T]) -> None:
        self.fn, self.calls = fn, 0

    def __call__(self, x: np.ndarray) -> T:
        self.calls += 1
        return self.fn(x)


class _CapReachedError(Exception):
    """Raised inside the residual when a peer runs past its time cap."""


def least_squares(residual: Callable[[np.ndarray, Mapping[str, np.ndarray]], np.ndarray],
                  theta0: np.ndarray, cols: Mapping[str, np.ndarray],
                  max_seconds: float | None = None) -> PeerResult:
    """``scipy.optimize.least_squares`` (TRF, the default) with its default 2-point
    finite-difference Jacobian, tolerances tightened so that it reaches the minimum.

    ``max_seconds`` stops it (marked in the message) if it runs past a time cap; it then
    returns the best point it evaluated.
    """
    start = time.perf_counter()
    best: list = [np.inf, np.asarray(theta0, dtype=float)]

    def fun(x: np.ndarray) -> np.ndarray:
        if max_seconds is not None and time.perf_counter() - start > max_seconds:
            raise _CapReachedError
        r = residual(x, cols)
        cost = float(r @ r)
        if cost < best[0]:
            best[:] = [cost, x.copy()]
        return r

    counted = _Counted(fun)
    try:
        sol = scipy.optimize.least_squares(counted, theta0, method="trf", jac="2-point",
                                           ftol=1e-15, xtol=1e-15, gtol=1e-15, max_nfev=2000)
        theta, iterations = sol.x, int(sol.nfev)
        message = f"status {sol.status}: {sol.message}"
    except _CapReachedError:
        theta, iterations = best[1], None
        message = (f"stopped at the {max_seconds:g} s cap before converging "
                   "(best point evaluated)")
    seconds = time.perf_counter() - start
    r = residual(theta, cols)
    return PeerResult(theta, float(r @ r), iterations, counted.calls, seconds, message)


def bfgs(residual: Callable[[np.ndarray, Mapping[str, np.ndarray]], np.ndarray],
         theta0: np.ndarray, cols: Mapping[str, np.ndarray],
         max_seconds: float | None = None) -> PeerResult:
    """``scipy.optimize.minimize(method="BFGS")`` of J = Σ g² with its default
    finite-difference gradient (the paper's method), ``gtol`` tightened.

    ``max_seconds`` stops it (marked in the message) if it runs past a time cap.
    """
    start = time.perf_counter()

    def cost(x: np.ndarray) -> float:
        r = residual(x, cols)
        return float(r @ r)

    fun = _Counted(cost)
    iterations = [0]

    def callback(intermediate_result: scipy.optimize.OptimizeResult) -> None:
        iterations[0] += 1
        if max_seconds is not None and time.perf_counter() - start > max_seconds:
            raise StopIteration

    sol = scipy.optimize.minimize(fun, theta0, method="BFGS", callback=callback,
                                  options={"gtol": 1e-12, "maxiter": 100_000})
    seconds = time.perf_counter() - start
    message = str(sol.message)
    if max_seconds is not None and seconds > max_seconds and not sol.success:
        message = f"stopped at the {max_seconds:g} s cap: {message}"
    return PeerResult(sol.x, cost(sol.x), int(sol.nit), fun.calls, seconds, message)
