"""Predicted uncertainty of a planned motion: the Fisher information before any data.

For the motion a scenario describes, :func:`predict` states what the calibration's last
stage would report on data simulated from it, with nothing recorded:

1. the run is simulated *without noise* (the scenario's readings, with its sensor errors
   and hidden effects), at the scenario's true parameters (:func:`operating_point`);
2. the noise model is the scenario's (:func:`symcal.simulation.input_noise`): each
   observation's constraints get the covariance ``S_i = G_i Σ G_iᵀ``, ``G_i = ∂g/∂u`` (exact,
   symbolic) and ``Σ`` the columns' noise variances;
3. the weights are the solve's: ``weighting: estimated`` whitens by the covariance the
   solve estimates from the residuals of its *equal-weight* fit, so ``S`` is the mean
   noise covariance plus that of what an equal-weight refit of the noiseless data leaves
   (the model's misfit to the simulated system); equal weights keep ``g/σ``;
   ``weighting: propagated`` (each observation whitened by its own propagated noise
   covariance) is predicted as that pooled whitening: the per-observation weights are
   not modelled (on the courier's motions the constraints' noise covariance varies
   little with the pose);
4. the estimate lands at the weighted refit ``θ*`` of the noiseless data, and its spread
   over data sets is the sandwich ``(J̃ᵀJ̃)⁺ (Σ_i J̃_iᵀ S̃_i J̃_i) (J̃ᵀJ̃)⁺`` at ``θ*``
   (``J̃ = T J``, ``T`` the weights), each observation with its own noise and misfit,
   ``S̃_i = T (G_i Σ G_iᵀ + m_i m_iᵀ) Tᵀ``, through
   :func:`symcal.analysis.identifiability.analyse` with the solve's rank rule.

Weighting by the misfit matters when the misfit is not small beside the noise: on the
dual problem's motion with every pose at ±1.5° (issue 17), predicting with the misfit of
a noise-weighted refit and the Jacobian at the true θ gave an l_y standard error 10 %
below the Monte-Carlo spread (400 seeds); with the solve's own weights, 5 % (within the
spread's confidence interval).  The randomness of the estimated weights themselves
(first order in the misfit) was measured and is negligible there (< 0.5 %), so it is
not modelled.  The solve uses no errors-in-variables model (the inputs' noise reaches it
only through the residual covariance), so neither does the prediction.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from symcal.analysis.identifiability import Identifiability, Uncertainty, analyse
from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import SymcalError
from symcal.base.linalg import numerical_rank, whitening
from symcal.base.numeric import chunks, mapped
from symcal.base.units import size
from symcal.data.dataset import Dataset, make_dataset
from symcal.data.derived import sources, with_derived
from symcal.data.loading import column_noise, needed_columns
from symcal.problem.symbolic import Problem, Stage
from symcal.simulation import Scenario, input_noise, quiet, simulate_run, true_values
from symcal.solvers.objective import Objective


@dataclass(frozen=True, eq=False)
class Prediction:
    """What a calibration on a planned motion would report, before any data.

    Attributes
    ----------
    scenario
        The scenario the motion comes from.
    run
        The run whose motion is the calibration data.
    n
        Its number of observations.
    stage
        The calibration stage predicted (the last; its free parameters and constraints).
    identifiability, uncertainty
        Rank, condition number, null space, identifiable combinations; standard errors
        and correlations, as the calibration's
        :class:`~symcal.calibrate.result.StageResult` has them.
    residual_std
        Predicted standard deviation of each constraint of the stage, noise and misfit
        (display unit, with ``units``).
    residual_noise
        Its part from the noise alone (display unit).
    units
        Display unit of each constraint and free parameter.
    covariance
        ``S``: covariance of one observation's weighted constraints (``g/σ``).
    """

    scenario: Scenario
    run: str
    n: int
    stage: Stage
    identifiability: Identifiability
    uncertainty: Uncertainty
    residual_std: dict[str, float]
    residual_noise: dict[str, float]
    units: dict[str, str]
    covariance: np.ndarray

    @property
    def se(self) -> dict[str, float | None]:
        """Predicted standard error of each free parameter (its unit; None: only in a
        combination)."""
        return dict(self.uncertainty.se)


def operating_point(problem: Problem, scenario: Scenario) -> np.ndarray:
    """θ at which a plan is evaluated: the scenario's true parameters.

    A true value (the scenario's ``truth`` and its active effects' values) is matched by
    its name (``l_x``) or, when that is not a parameter of the problem, by the one
    parameter whose last part it is (``h`` → ``cs.h``), and converted to the parameter's
    unit; the other parameters keep their initial values.
    """
    theta = np.array([p.value for p in problem.parameters])
    names = problem.parameter_names
    for name, (value, unit) in true_values(scenario).items():
        if name in problem.index:
            target = name
        else:
            matches = [n for n in names if n.rsplit(".", 1)[-1] == name]
            if len(matches) != 1:
                continue
            target = matches[0]
        param = problem.parameters[problem.index[target]]
        factor = size(unit) / size(param.unit)
        theta[problem.index[target]] = value if factor == 1.0 else value * factor
    return theta


def design_run(problem: Problem, scenario: Scenario) -> str:
    """The run whose motion is the fitted data: the one the scenario's ``design`` section
    names, else the one the problem's fitted dataset simulates, else the run of that
    dataset's name."""
    if scenario.design is not None:
        return scenario.design.run
    spec = problem.datasets.get(problem.fit_dataset)
    if spec is not None and getattr(spec, "run", None):
        return str(spec.run)
    return problem.fit_dataset


def last_stage(problem: Problem) -> tuple[Stage, np.ndarray]:
    """The stage whose uncertainty the calibration reports, and its free-parameter mask."""
    stage = problem.stages[-1]
    for name in stage.constraints:
        if getattr(problem.constraint(name), "loss", None) is not None:
            raise SymcalError(f"design: constraint '{name}' of stage '{stage.name}' has a "
                              "robust loss; predicted uncertainties assume least squares")
    return stage, np.array([p.name in stage.free for p in problem.parameters])


def noise_matrix(problem: Problem, scenario: Scenario) -> np.ndarray:
    """Diagonal covariance of the columns ``problem.columns`` (a column the simulator does
    not write is taken as exact)."""
    sigma = input_noise(scenario)
    return np.diag([sigma.get(c, 0.0) ** 2 for c in problem.columns])


def per_observation(objective: Objective) -> Any:
    """``g/σ``, ``∂(g/σ)/∂u`` and ``∂(g/σ)/∂θ_free`` of one observation, mapped over
    observations (column-major vecs of ``n_g``, ``n_g × n_u`` and ``n_g × n_free``)."""
    problem = objective.problem
    return mapped(problem.theta, problem.u,
                  [objective.g, ca.jacobian(objective.g, problem.u), objective.jac],
                  "plan_per_observation")


def _blocks(objective: Objective, data: Dataset,
            theta: np.ndarray) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per chunk of observations: residuals ``g`` (``m × n_g``), ``G = ∂g/∂u``
    (``m × n_g × n_u``) and ``J = ∂g/∂θ_free`` (``m × n_g × n_free``), all of ``g/σ``."""
    fn = per_observation(objective)
    ng, nu, nf = objective.g.shape[0], len(objective.problem.columns), len(objective.index)
    u = data.matrix(objective.problem.columns)
    for part in chunks(data.n):
        g, g_u, jac = (np.asarray(x) for x in fn(theta, u[:, part]))
        yield (g.reshape(-1, ng), g_u.reshape(-1, nu, ng).transpose(0, 2, 1),
               jac.reshape(-1, nf, ng).transpose(0, 2, 1))


def noise_covariance(objective: Objective, data: Dataset, theta: np.ndarray,
                     columns_cov: np.ndarray) -> np.ndarray:
    """Mean over observations of ``G_i Σ G_iᵀ`` (the weighted constraints' noise)."""
    total = np.zeros((objective.g.shape[0],) * 2)
    for _, g_u, _ in _blocks(objective, data, theta):
        total += np.einsum("mau,uv,mbv->ab", g_u, columns_cov, g_u)
    return total / data.n


def refit(objective: Objective, data: Dataset, theta: np.ndarray,
          transform: np.ndarray | None, steps: int = 3) -> np.ndarray:
    """θ after Gauss-Newton steps on (noiseless) data, weighted by ``transform``: where
    the calibration's fit of the model to the simulated courier lands."""
    weighted = objective if transform is None else Objective(
        objective.problem, objective.constraints, objective.free, transform)
    refitted = theta.copy()
    for _ in range(steps):
        r, c, _, _ = weighted.accumulate_r(data, refitted)
        refitted[objective.index] -= np.linalg.lstsq(r, c, rcond=None)[0]
    return refitted


def misfit_covariance(objective: Objective, data: Dataset, theta: np.ndarray,
                      transform: np.ndarray | None) -> np.ndarray:
    """Covariance of what a refit of noiseless data leaves (weighted by ``transform``):
    the model's own misfit to the simulated courier, which the calibration's residuals
    carry too."""
    g = objective.residuals(data, refit(objective, data, theta, transform))
    return (g.T @ g) / data.n


def sandwich_meat(objective: Objective, data: Dataset, theta: np.ndarray,
                  columns_cov: np.ndarray, transform: np.ndarray | None,
                  misfit: bool = True) -> np.ndarray:
    """``M`` (``n_free × n_free``, upper triangular) with
    ``MᵀM = Σ_i J̃_iᵀ (T (G_i Σ G_iᵀ + m_i m_iᵀ) Tᵀ) J̃_i`` at the refit ``theta``: the
    spread of the calibration's estimating equations over data sets, each observation
    with its own noise covariance (it changes with the pose, e.g. with the sign of θ) and
    its own misfit ``m_i`` (it changes with the pose drawn; False: left out);
    ``J̃_i = T J_i``.

    ``M`` is the R factor of the rows ``a_kᵀ J̃_i`` (``a_k`` the columns of
    ``T G_i Σ^½`` and ``T m_i``), reduced chunk by chunk as the solve reduces its own
    meat (:meth:`Objective.accumulate_r`): the sum ``Σ J̃ᵀ S̃ J̃`` is never formed, so
    its condition number is the Jacobian's, not its square, and no direction of it is
    dropped as numerically zero (its eigenvalues span the square of the parameters'
    scales and of the Jacobian's conditioning: 1e12 and more on a linear axis with a
    product and an Abbe term, where a relative PSD cut of the sum dropped half of it)."""
    nf = len(objective.index)
    w, v = np.linalg.eigh((columns_cov + columns_cov.T) / 2)
    root = v * np.sqrt(np.clip(w, 0.0, None))[None, :]     # Σ^½, no relative cut
    meat = np.zeros((0, nf))
    for g, g_u, jac in _blocks(objective, data, theta):
        t = np.eye(g.shape[1]) if transform is None else transform
        tj = np.einsum("ab,mbp->map", t, jac)
        a = np.einsum("ab,mbu,ur->mar", t, g_u, root)
        if misfit:
            a = np.concatenate([a, (g @ t.T)[:, :, None]], axis=2)
        rows = np.einsum("mar,map->mrp", a, tj).reshape(-1, nf)
        stacked = np.vstack([meat, rows])
        meat = np.linalg.qr(stacked, mode="r")  # type: ignore[assignment]
    return meat


def covariance_of(objective: Objective, data: Dataset, theta: np.ndarray, cov: np.ndarray,
                  columns_cov: np.ndarray, weighting: str,
                  misfit: bool = True) -> tuple[Identifiability, Uncertainty]:
    """Identifiability and uncertainty of the calibration's estimate when the constraints
    of one observation have (pooled) covariance ``cov`` — what the solve estimates from
    its residuals and weights by — and the columns' noise is ``columns_cov``.

    The estimate lands at the weighted refit of the model to the courier (θ at which the
    Jacobian and misfit are taken; ``misfit`` False: at ``theta``, noise alone); its
    covariance is the sandwich
    ``(J̃ᵀJ̃)⁺ (Σ_i J̃_iᵀ S̃_i J̃_i) (J̃ᵀJ̃)⁺`` with the same rank rule as the solve's."""
    ng = cov.shape[0]
    pooled = weighting in ("estimated", "propagated") and ng > 1
    transform = whitening(cov)[0] if pooled else None
    solved = objective if transform is None else Objective(
        objective.problem, objective.constraints, objective.free, transform)
    at = refit(objective, data, theta, transform) if misfit else theta
    r, _, _, rows = solved.accumulate_r(data, at)
    rank = numerical_rank(r, rows, solved.scales)
    dof = max(rows - rank, 1)
    seen = cov if transform is None else transform @ cov @ transform.T
    meat = sandwich_meat(objective, data, at, columns_cov, transform, misfit)
    return analyse(r, rows, float(np.trace(seen)) / seen.shape[0] * dof, solved.names,
                   solved.scales, at[solved.index], meat)


def noiseless_data(problem: Problem, scenario: Scenario, run: str, seed: int) -> Dataset:
    """The run simulated without noise, as the calibration dataset, with the columns the
    problem derives from it (``rate_of``) computed as a solve computes them."""
    columns = simulate_run(quiet(scenario), run, seed=seed)
    needed = needed_columns(problem)
    data = make_dataset(problem.fit_dataset, f"{scenario.name} run '{run}' without noise",
                        columns, sources(problem.column_specs, needed))
    return with_derived(problem.column_specs, data, needed, column_noise(problem))


def predict(problem: Problem, scenario: Scenario, run: str | None = None, seed: int = 0,
            misfit: bool = True) -> Prediction:
    """Predicted uncertainty of the calibration on a scenario's planned motion.

    Parameters
    ----------
    problem
        The calibration problem (its last stage is predicted).
    scenario
        The courier, its noise and its motions.
    run
        The run used as calibration data (default: :func:`design_run`).
    seed
        Seed of the run's poses (its noise is not drawn).
    misfit
        Add the covariance of the model's misfit to the simulated courier to the noise's
        (what the calibration's residuals carry); False: noise alone.

    Returns
    -------
    Prediction
        Standard errors, identifiability and condition number, predicted residuals.

    Raises
    ------
    SymcalError
        If the run does not exist (did-you-mean), the problem's columns are not all
        simulated, or a constraint of the stage has a robust loss.
    """
    run = design_run(problem, scenario) if run is None else run
    if run not in scenario.run_names:
        raise SymcalError(f"scenario '{scenario.name}' has no run '{run}'"
                          f"{did_you_mean(run, scenario.run_names)}; runs: "
                          f"{', '.join(scenario.run_names)}")
    stage, free = last_stage(problem)
    data = noiseless_data(problem, scenario, run, seed)
    theta = operating_point(problem, scenario)
    objective = Objective(problem, stage.constraints, free)
    columns_cov = noise_matrix(problem, scenario)
    noise = noise_covariance(objective, data, theta, columns_cov)
    cov = noise
    if misfit:      # the solve estimates S at its equal-weight fit, misfit included
        cov = noise + misfit_covariance(objective, data, theta, None)
    ident, unc = covariance_of(objective, data, theta, cov, columns_cov, problem.weighting,
                               misfit)
    units: dict[str, str] = {}
    std: dict[str, float] = {}
    floor: dict[str, float] = {}
    for k, name in enumerate(stage.constraints):
        q = problem.constraint(name)
        shown = q.sigma / size(q.unit)
        units[name] = q.unit
        std[name] = float(np.sqrt(cov[k, k]) * shown)
        floor[name] = float(np.sqrt(noise[k, k]) * shown)
    for p in problem.parameters:
        units[p.name] = p.unit
    return Prediction(scenario, run, data.n, stage, ident, unc, std, floor, units, cov)


def noise_floors(problem: Problem, scenario: Scenario, run: str | None = None,
                 seed: int = 0) -> dict[str, float]:
    """The spread that noise alone leaves in each constraint of ``problem`` on data
    simulated from ``scenario``, by propagation: the RMS over the run's (noiseless)
    observations of ``sqrt(G_i Σ G_iᵀ)``, ``G_i = ∂g/∂u`` at the true parameters and ``Σ``
    the columns' noise variances (first order; exact for a constraint linear in the
    readings).

    Parameters
    ----------
    problem
        The problem whose constraints are measured.
    scenario
        The simulated system and its declared noise.
    run
        The run the floor is taken on (default: :func:`design_run`).
    seed
        Seed of the run's states.

    Returns
    -------
    dict
        ``NAME_std`` → the floor of constraint ``NAME`` in internal units, for every
        constraint whose columns the scenario writes.
    """
    run = design_run(problem, scenario) if run is None else run
    simulated = set(scenario.column_names)
    constraints = [c for c in problem.constraints
                   if set(problem.columns_of(c.sx)) <= simulated]
    if not constraints or run not in scenario.run_names:
        return {}
    columns = simulate_run(quiet(scenario), run, seed=seed)
    data = make_dataset("floor", f"{scenario.name} run '{run}' without noise", columns,
                        needed_columns(problem))
    g = ca.vertcat(*(c.sx for c in constraints))
    fn = mapped(problem.theta, problem.u, [ca.jacobian(g, problem.u)], "noise_floor")
    sigma = np.array([input_noise(scenario).get(c, 0.0) for c in problem.columns])
    total = np.zeros(len(constraints))
    theta = operating_point(problem, scenario)
    u = data.matrix(problem.columns)
    for part in chunks(data.n):
        jac = fn(theta, u[:, part])[0].reshape(-1, len(problem.columns), len(constraints))
        total += np.einsum("mua,u->a", jac**2, sigma**2)
    return {f"{c.name}_std": float(np.sqrt(total[k] / data.n))
            for k, c in enumerate(constraints)}
