"""The least-squares objective of one solve: chosen constraints, chosen free parameters.

J(θ) = Σ_obs Σ_k (g_k(θ, u)/σ_k)².  Everything is built symbolically for ONE observation
and evaluated over all of them with CasADi ``map`` (serial), in chunks, so the graph never
grows with N and memory is bounded.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np
import scipy.linalg

from symcal.data import Dataset
from symcal.numeric import Mapped, chunks, mapped
from symcal.problem import Problem
from symcal.solvers import instrument


@dataclass(frozen=True, eq=False)
class Objective:
    """Σ (g/σ)² over ``constraints``, as a function of the parameters in ``free``.

    Parameters
    ----------
    problem
        The symbolic problem.
    constraints
        Names of the constraints in the cost.
    free
        Boolean mask over ``problem.parameters``.
    whiten
        Optional ``n_g × n_g`` matrix T: the cost becomes Σ ‖T g‖², e.g. T = S^-½ for an
        estimated covariance S between the constraints of one observation.
    """

    problem: Problem
    constraints: tuple[str, ...]
    free: np.ndarray
    whiten: np.ndarray | None = None
    g: ca.SX = field(init=False, repr=False)
    jac: ca.SX = field(init=False, repr=False)
    _cache: dict[str, Mapped] = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        free = np.asarray(self.free, dtype=bool)
        object.__setattr__(self, "free", free)
        quantities = [self.problem.constraint(n) for n in self.constraints]
        g = ca.vertcat(*(q.sx / q.sigma for q in quantities))
        if self.whiten is not None:
            g = ca.mtimes(ca.DM(self.whiten), g)
        object.__setattr__(self, "g", g)
        object.__setattr__(self, "jac", ca.jacobian(g, self.theta_free))

    @property
    def theta_free(self) -> ca.SX:
        """SX symbols of the free parameters."""
        return self.problem.theta[np.flatnonzero(self.free).tolist()]

    @property
    def index(self) -> np.ndarray:
        """Positions of the free parameters in θ."""
        return np.flatnonzero(self.free)

    @property
    def scales(self) -> np.ndarray:
        """Nominal magnitudes of the free parameters."""
        return np.array([self.problem.parameters[i].scale for i in self.index])

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the free parameters."""
        return tuple(self.problem.parameters[i].name for i in self.index)

    def nonlinear(self) -> list[str]:
        """Constraints of the cost that are not linear in the free parameters."""
        theta_free = self.theta_free
        return [n for n in self.constraints
                if not ca.is_linear(self.problem.constraint(n).sx, theta_free)]

    def accumulate_r(
        self, dataset: Dataset, theta: np.ndarray, transform: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, float, int]:
        """R factor of the weighted Jacobian and the reduced residual at ``theta``.

        Parameters
        ----------
        transform
            Optional ``n_g × n_g`` matrix T applied to each observation's block of
            residuals and Jacobian rows (T g_i, T J_i) before reduction.

        Returns
        -------
        (R, c, tail, rows)
            ``‖J δ + g‖² = ‖R δ + c‖² + tail`` for every step δ of the free parameters,
            J and g the weighted Jacobian and residual at ``theta``; ``rows`` counts the
            residual rows.  Accumulated chunk by chunk (TSQR).
        """
        instrument.record_pass("r", "accumulate_r", dataset.n)
        fn = self._mapped("linearised", [self.g, self.jac.T])
        n, ng = int(self.free.sum()), self.g.shape[0]
        u = dataset.matrix(self.problem.columns)
        r_aug = np.zeros((0, n + 1))
        rows = 0
        for part in chunks(dataset.n):
            g0, jt = fn.chunk(theta, u[:, part])
            m = g0.shape[0]
            jac = jt.reshape(m, ng, n)
            if transform is not None:
                g0 = g0 @ transform.T
                jac = np.einsum("ab,mbn->man", transform, jac)
            block = np.column_stack([jac.reshape(m * ng, n), g0.reshape(m * ng)])
            r_aug = scipy.linalg.qr(np.vstack([r_aug, block]), mode="r",
                                    check_finite=False)[0][: n + 1]
            rows += m * ng
        if r_aug.shape[0] < n + 1:
            r_aug = np.vstack([r_aug, np.zeros((n + 1 - r_aug.shape[0], n + 1))])
        return r_aug[:n, :n], r_aug[:n, n], float(r_aug[n, n] ** 2), rows

    def residual_covariance(self, dataset: Dataset, theta: np.ndarray, rank: int) -> np.ndarray:
        """Covariance between the weighted constraints of one observation (``n_g × n_g``),
        estimated from the residuals at ``theta`` with ``rank`` degrees of freedom used."""
        instrument.record_pass("residual", "residual_covariance", dataset.n)
        fn = self._mapped("residual", [self.g])
        g = fn(theta, dataset.matrix(self.problem.columns))[0]
        rows = g.size
        return (g.T @ g) / dataset.n * rows / max(rows - rank, 1)

    def residuals(self, dataset: Dataset, theta: np.ndarray) -> np.ndarray:
        """Weighted residuals at ``theta``, ``N × n_g``."""
        instrument.record_pass("residual", "residuals", dataset.n)
        fn = self._mapped("residual", [self.g])
        return fn(theta, dataset.matrix(self.problem.columns))[0]

    def cost_terms(self, dataset: Dataset, theta: np.ndarray) -> dict[str, float]:
        """Σ (g_k/σ_k)² of each constraint of the cost at ``theta``."""
        g = self.residuals(dataset, theta)
        return {name: float(np.sum(g[:, k] ** 2)) for k, name in enumerate(self.constraints)}

    def normal_equations(
        self, dataset: Dataset, theta: np.ndarray
    ) -> tuple[float, np.ndarray, np.ndarray]:
        """``(Σ g², Jᵀg, JᵀJ)`` of the weighted residual at ``theta``, by chunks.

        J is evaluated by CasADi (exact AD) for one chunk of observations at a time and
        reduced with BLAS, so memory stays bounded whatever N is.
        """
        instrument.record_pass("linearised", "normal_equations", dataset.n)
        fn = self._mapped("linearised", [self.g, self.jac.T])
        n, ng = int(self.free.sum()), self.g.shape[0]
        u = dataset.matrix(self.problem.columns)
        cost, jtg, jtj = 0.0, np.zeros(n), np.zeros((n, n))
        for part in chunks(dataset.n):
            g0, jt = fn.chunk(theta, u[:, part])
            m = g0.shape[0]
            jac, res = jt.reshape(m * ng, n), g0.reshape(m * ng)
            cost += float(res @ res)
            jtg += jac.T @ res
            jtj += jac.T @ jac
        return cost, jtg, jtj

    def cost(self, dataset: Dataset, theta: np.ndarray) -> float:
        """Σ (g/σ)² at ``theta`` (residuals only, no derivatives)."""
        instrument.record_pass("residual", "cost", dataset.n)
        fn = self._mapped("residual", [self.g])
        u = dataset.matrix(self.problem.columns)
        return float(sum(np.sum(fn.chunk(theta, u[:, part])[0] ** 2)
                         for part in chunks(dataset.n)))

    def _mapped(self, name: str, outputs: list[ca.SX]) -> Mapped:
        if name not in self._cache:
            self._cache[name] = mapped(self.problem.theta, self.problem.u, outputs, name)
        return self._cache[name]
