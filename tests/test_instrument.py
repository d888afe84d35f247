"""symcal.solvers.instrument: counts of passes over the data and of solver iterations,
checked against what each solver path is known to do."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from conftest import ROOT

import symcal
from symcal.calibrate.solve import run_stage
from symcal.data.dataset import make_dataset
from symcal.simulation import load_scenario, simulate_run
from symcal.solvers import instrument
from symcal.solvers.instrument import Counters, counting
from symcal.solvers.linear import solve_linear
from symcal.solvers.nlp import solve_ipopt
from symcal.solvers.objective import Objective

PLATEN = ROOT / "problems" / "platen_self_calibration.yaml"
DUAL = ROOT / "problems" / "dual_sensor_calibration.yaml"
SCENARIOS = ROOT / "problems" / "scenarios"
N = 1_500  # not a power of two: the last chunk is padded


@pytest.fixture(scope="module")
def platen() -> tuple[symcal.Problem, symcal.Dataset]:
    problem = symcal.load_problem(PLATEN)
    cols = simulate_run(load_scenario(SCENARIOS / "courier_platen.yaml"), "calibration",
                        seed=3, n=N)
    return problem, make_dataset("calibration", "simulated", cols, [])


def _objective(problem: symcal.Problem) -> Objective:
    stage = problem.stages[0]
    free = np.array([p.name in stage.free for p in problem.parameters])
    return Objective(problem, stage.constraints, free)


def _theta0(problem: symcal.Problem) -> np.ndarray:
    return np.array([p.value for p in problem.parameters])


def test_nothing_is_counted_outside_a_block(platen) -> None:
    problem, data = platen
    objective = _objective(problem)
    assert not instrument.active()
    objective.cost(data, _theta0(problem))  # no block: nothing to record, no error
    with counting() as counts:
        assert instrument.active()
    objective.cost(data, _theta0(problem))
    assert counts == Counters()
    assert counts.to_dict()["passes"] == 0
    assert not instrument.active()


def test_closed_form_makes_exactly_one_r_pass(platen) -> None:
    problem, data = platen
    objective = _objective(problem)
    assert not objective.nonlinear()
    with counting() as counts:
        out = solve_linear(objective, data, _theta0(problem))
    assert out.iterations == 0
    assert (counts.r_passes, counts.linearised_passes, counts.residual_passes) == (1, 0, 0)
    assert counts.passes == 1
    assert counts.observations == N
    assert counts.iterations == 0
    assert counts.by_method == {"accumulate_r": 1}


def test_each_objective_method_is_one_pass_of_its_kind(platen) -> None:
    problem, data = platen
    objective = _objective(problem)
    theta = _theta0(problem) + 1e-3   # a point no earlier test reduced an R factor at
    with counting() as counts:
        objective.cost(data, theta)
        terms = objective.cost_terms(data, theta)  # a residual pass of its own (Σ g_k²)
        objective.residuals(data, theta)
        objective.residual_covariance(data, theta, rank=33)   # from the kept residuals
        objective.normal_equations(data, theta)
        objective.accumulate_r(data, theta)
    assert counts.by_method == {"cost": 1, "residuals": 1, "cost_terms": 1,
                                "normal_equations": 1, "accumulate_r": 1}
    assert (counts.residual_passes, counts.linearised_passes, counts.r_passes) == (3, 1, 1)
    assert counts.observations == 5 * N
    # at a new point, the covariance is one residuals pass, kept for what comes next
    with counting() as fresh:
        objective.residual_covariance(data, theta + 1e-3, rank=33)
        objective.residuals(data, theta + 1e-3)
    assert fresh.by_method == {"residuals": 1}
    # asked again at the point of the last residuals: from them, no pass, the same bits
    with counting() as again:
        assert objective.cost_terms(data, theta) == terms
        objective.residuals(data, theta)
    assert again.passes == 0


def test_the_cost_per_constraint_at_an_r_factors_point_needs_no_pass(platen) -> None:
    """A stage's cost per constraint at its start reads the sums of the R factor's pass
    there (the same evaluation): no pass of its own, the same bits as one; a transformed
    reduction, or one of another dataset, does not serve."""
    problem, data = platen
    objective = _objective(problem)
    theta = _theta0(problem) + 3.7e-3   # a point no other test evaluated
    twin = make_dataset("calibration", "the same rows", dict(data.columns), [])
    with counting() as own:
        expected = objective.cost_terms(twin, theta)
    assert own.by_method == {"cost_terms": 1}
    objective.accumulate_r(data, theta)
    with counting() as counts:
        assert objective.cost_terms(data, theta) == expected
    assert counts.passes == 0
    objective.accumulate_r(data, theta, np.eye(len(objective.constraints)))
    with counting() as transformed:
        assert objective.cost_terms(data, theta) == expected
    assert transformed.by_method == {"cost_terms": 1}


@pytest.mark.slow
def test_an_iterative_stage_takes_its_start_cost_from_its_first_pass() -> None:
    """The dual problem's lm stage: its cost per constraint at the start is read from the
    start's R-factor pass before the solver's passes replace it (no residual pass of its
    own), and equals Σ (g/σ)² of the residuals evaluated apart."""
    scenario = load_scenario(SCENARIOS / "courier_dual.yaml")
    data = make_dataset("calibration", "simulated",
                        simulate_run(scenario, "calibration", 5, N), [])
    problem = symcal.load_problem(DUAL).with_weighting("equal")
    stage = problem.stages[-1]
    theta = _theta0(problem)
    for earlier in problem.stages[:-1]:     # the start the lm stage has in a solve
        theta, _ = run_stage(problem, earlier, data, theta)
    with counting() as counts:
        _, result = run_stage(problem, stage, data, theta)
    assert result.method == "lm"
    assert "cost_terms" not in counts.by_method
    free = np.array([p.name in stage.free for p in problem.parameters])
    g = Objective(problem, stage.constraints, free).residuals(data, theta)
    for k, cost in enumerate(result.costs):
        expected = float(np.sum(g[:, k] ** 2))
        assert cost.cost_before == pytest.approx(expected, rel=1e-12)


def test_nested_blocks_both_count(platen) -> None:
    problem, data = platen
    objective = _objective(problem)
    theta = _theta0(problem)
    with counting() as outer:
        objective.cost(data, theta)
        with counting() as inner:
            objective.normal_equations(data, theta)
        objective.cost(data, theta)
    assert (outer.residual_passes, outer.linearised_passes) == (2, 1)
    assert (inner.residual_passes, inner.linearised_passes) == (0, 1)


def test_other_threads_are_not_counted(platen) -> None:
    """The active block is a context variable: a thread started without the context
    does not count into it."""
    problem, data = platen
    objective = _objective(problem)
    with counting() as counts:
        worker = threading.Thread(target=objective.cost, args=(data, _theta0(problem)))
        worker.start()
        worker.join()
    assert counts.passes == 0


def test_ipopt_iterations_and_hook_match_the_solver(platen) -> None:
    """The linear problem through IPOPT: the counted iterations are the solver's own,
    and the hook sees the start (iteration 0) and the cost of every iterate."""
    problem, data = platen
    objective = _objective(problem)
    theta0 = _theta0(problem)
    calls: list[tuple[str, int, float, np.ndarray]] = []
    with counting(on_iteration=lambda *args: calls.append(args)) as counts:
        out = solve_ipopt(objective, data, theta0, label="platen")
    assert out.success and out.iterations > 0
    assert counts.iterations == out.iterations
    assert sum(it > 0 for _, it, _, _ in calls) == out.iterations
    assert {label for label, _, _, _ in calls} == {"platen"}
    assert len(counts.decrements) == len(calls)  # the convergence test after each call
    label, iteration, cost, x = calls[0]
    assert iteration == 0
    assert cost == pytest.approx(objective.cost(data, theta0), rel=1e-12)
    *_, (label, iteration, cost, x) = calls
    np.testing.assert_allclose(x * objective.scales, out.theta[objective.index],
                               rtol=0, atol=1e-12 * objective.scales.max())
    assert cost == pytest.approx(objective.cost(data, out.theta), rel=1e-9)
    # one R pass for the R factor at the solution; residual and linearised passes drive
    # the iterations (at least one linearised pass per iteration's gradient)
    assert counts.r_passes == 1
    assert counts.linearised_passes >= out.iterations
    assert counts.observations == counts.passes * N


@pytest.mark.slow
def test_staged_solve_counts_every_ipopt_stage() -> None:
    """The dual problem's stages, all through IPOPT: the iterations counted are those the
    result reports, and every stage reaches the hook."""
    scenario = load_scenario(SCENARIOS / "courier_dual.yaml")
    data = {name: make_dataset(name, "simulated", simulate_run(scenario, name, 5, 1_000), [])
            for name in ("calibration", "flyby")}
    labels: set[str] = set()
    with counting(on_iteration=lambda label, *_: labels.add(label)) as counts:
        result = symcal.solve(symcal.load_problem(DUAL), data,
                              symcal.SolveOptions(method="ipopt"))
    assert result.success
    assert all(st.method == "ipopt" and st.iterations > 0 for st in result.stages)
    assert counts.iterations == sum(st.iterations for st in result.stages)
    assert labels == {st.name for st in result.stages}
    assert counts.r_passes >= len(result.stages)


@pytest.mark.slow
def test_default_staged_solve_counts_lm_steps() -> None:
    """By default: closed form, closed form, then lm.  The hook sees the accepted lm steps
    (no more than the trial steps the stage reports) and only the lm stage."""
    scenario = load_scenario(SCENARIOS / "courier_dual.yaml")
    data = {name: make_dataset(name, "simulated", simulate_run(scenario, name, 5, 1_000), [])
            for name in ("calibration", "flyby")}
    labels: set[str] = set()
    with counting(on_iteration=lambda label, *_: labels.add(label)) as counts:
        result = symcal.solve(symcal.load_problem(DUAL), data)
    assert result.success
    assert [st.method for st in result.stages] == ["linear", "linear", "lm"]
    assert 0 < counts.iterations <= result.stages[-1].iterations
    assert labels == {"full"}


def test_an_exception_in_the_hook_stops_the_solve(platen) -> None:
    """Raising in the hook is how a caller stops IPOPT: the solve ends, failed, with the
    last iterate."""
    problem, data = platen

    def hook(label: str, iteration: int, cost: float, x: np.ndarray) -> None:
        if iteration == 1:
            raise RuntimeError("stop here")

    with counting(on_iteration=hook) as counts:
        out = solve_ipopt(_objective(problem), data, _theta0(problem))
    assert not out.success
    assert out.status == "User_Requested_Stop"
    assert out.iterations == counts.iterations == 1
