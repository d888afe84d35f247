"""Both cores: chunk passes on threads equal the serial passes (issue 16, item 3).

The reduction is in the order of the chunks whoever evaluates them, so the thread path
gives the serial result bit for bit; the tests ask for that, and for agreement with an
independent numpy computation from the residuals."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from conftest import ROOT

import symcal
from symcal.base.errors import SymcalError
from symcal.data.dataset import make_dataset
from symcal.data.loading import needed_columns
from symcal.simulation import load_scenario, simulate_run
from symcal.solvers import executor as ex
from symcal.solvers.nlp import solve_ipopt
from symcal.solvers.objective import Objective

N = 12_000          # two chunks of at most 8192


@pytest.fixture(scope="module")
def dual():
    problem = symcal.load_problem(ROOT / "problems/dual_sensor_calibration.yaml")
    cols = simulate_run(load_scenario(ROOT / "problems/scenarios/courier_dual.yaml"),
                        "calibration", seed=3, n=N)
    data = make_dataset("calibration", "test", cols, needed_columns(problem))
    free = np.array([True] * len(problem.parameters))
    constraints = tuple(c.name for c in problem.constraints)
    theta = np.array([p.value + 0.01 * p.scale for p in problem.parameters])
    return problem, data, free, constraints, theta


def _pair(dual):
    problem, data, free, constraints, _ = dual
    return (Objective(problem, constraints, free, executor=ex.SerialExecutor()),
            Objective(problem, constraints, free, executor=ex.ThreadExecutor(2)))


def test_every_pass_on_threads_equals_the_serial_pass(dual) -> None:
    _, data, _, _, theta = dual
    serial, threaded = _pair(dual)
    assert serial.cost(data, theta) == threaded.cost(data, theta)
    assert serial.cost_terms(data, theta) == threaded.cost_terms(data, theta)
    for a, b in zip(serial.normal_equations(data, theta),
                    threaded.normal_equations(data, theta), strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(serial.accumulate_r(data, theta), threaded.accumulate_r(data, theta),
                    strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(serial.residuals(data, theta),
                                  threaded.residuals(data, theta))
    np.testing.assert_array_equal(serial.residual_covariance(data, theta, 10),
                                  threaded.residual_covariance(data, theta, 10))


def test_the_residual_covariance_from_kept_residuals_is_the_gram_pass(dual) -> None:
    """In memory the residual covariance reads the residuals the stage keeps (its
    outliers and serial correlation read them too): the same bits as the gram pass it
    replaced, on one thread and on two."""
    _, data, _, _, theta = dual
    for objective in _pair(dual):
        gram, count = objective._pass("gram", "residual", data, theta)
        rows = count * objective.g.shape[0]
        np.testing.assert_array_equal(objective.residual_covariance(data, theta, 10),
                                      gram / count * rows / max(rows - 10, 1))


def test_passes_agree_with_numpy_from_the_residuals(dual) -> None:
    _, data, _, constraints, theta = dual
    _, threaded = _pair(dual)
    g = threaded.residuals(data, theta)
    assert g.shape == (N, len(constraints))
    assert threaded.cost(data, theta) == pytest.approx(float(np.sum(g**2)), rel=1e-12)
    terms = threaded.cost_terms(data, theta)
    for k, name in enumerate(constraints):
        assert terms[name] == pytest.approx(float(np.sum(g[:, k] ** 2)), rel=1e-12)
    cov = threaded.residual_covariance(data, theta, 10)
    rows = g.size
    np.testing.assert_allclose(cov, g.T @ g / N * rows / (rows - 10), rtol=1e-12)
    # the TSQR factor and the normal equations describe the same least-squares problem
    cost, jtg, jtj = threaded.normal_equations(data, theta)
    r, c, tail, n_rows = threaded.accumulate_r(data, theta)
    assert n_rows == rows
    scale = np.sqrt(np.diag(jtj))
    np.testing.assert_allclose((r.T @ r) / np.outer(scale, scale),
                               jtj / np.outer(scale, scale), atol=1e-10)
    np.testing.assert_allclose(r.T @ c / scale, jtg / scale, atol=1e-8 * np.abs(jtg / scale).max())
    assert float(c @ c) + tail == pytest.approx(cost, rel=1e-10)


@pytest.mark.slow
def test_an_ipopt_solve_on_threads_equals_the_serial_solve(dual) -> None:
    problem, data, free, constraints, theta = dual
    serial, threaded = _pair(dual)
    a = solve_ipopt(serial, data, theta, max_iter=30)
    b = solve_ipopt(threaded, data, theta, max_iter=30)
    assert a.success and b.success
    np.testing.assert_allclose(b.theta, a.theta, rtol=1e-10, atol=1e-12)
    assert b.rss == pytest.approx(a.rss, rel=1e-10)


def test_the_default_is_threads_for_large_n_only(monkeypatch) -> None:
    monkeypatch.setenv("SYMCAL_THREADS", "2")
    assert isinstance(ex.default_executor(ex.THREAD_MIN - 1), ex.SerialExecutor)
    big = ex.default_executor(ex.THREAD_MIN)
    assert isinstance(big, ex.ThreadExecutor) and big.workers == 2
    monkeypatch.setenv("SYMCAL_THREADS", "1")
    assert isinstance(ex.default_executor(10**8), ex.SerialExecutor)
    monkeypatch.setenv("SYMCAL_THREADS", "two")
    with pytest.raises(SymcalError, match="SYMCAL_THREADS must be a whole number of "
                                          "threads, not 'two'"):
        ex.default_executor(10**6)


def test_a_mapped_function_is_safe_to_share_between_threads(dual) -> None:
    """Each thread has its own buffers: concurrent evaluations at different θ give what
    each gives alone."""
    _, data, _, _, theta = dual
    serial, _ = _pair(dual)
    fn = serial._mapped("residual", [serial.g])
    u = data.matrix(serial.problem.columns)[:, :3000]
    thetas = [theta * (1 + 1e-3 * k) for k in range(4)]
    alone = [fn(t, u)[0] for t in thetas]
    got: dict[int, np.ndarray] = {}

    def work(k: int) -> None:
        for _ in range(5):
            got[k] = fn(thetas[k], u)[0]

    workers = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    for k in range(4):
        np.testing.assert_array_equal(got[k], alone[k])


def test_a_chunk_split_over_the_cores_equals_the_serial_chunk(dual, monkeypatch) -> None:
    """Outside the pass threads a chunk's rows are split over the cores by CasADi's
    threaded map; every row is the same code, so the result is the serial one bit for
    bit.  Inside a pass thread nothing is split again (threads never multiply)."""
    from symcal.base import numeric
    from symcal.base.cores import inner_threads

    _, data, _, _, theta = dual
    serial, _ = _pair(dual)
    fn = serial._mapped("linearised", [serial.g, serial.jac.T])
    assert fn.fn.n_instructions() * 4096 >= numeric.SPLIT_WORK
    u = data.matrix(serial.problem.columns)[:, :4000]
    monkeypatch.setenv("SYMCAL_THREADS", "1")
    alone = [x.copy() for x in fn(theta, u)]
    monkeypatch.setenv("SYMCAL_THREADS", "2")
    assert inner_threads() == 2
    split = fn(theta, u)
    assert (4096, 2) in fn._maps       # the threaded form was the one evaluated
    assert fn._maps[(4096, 2)].class_name() == "ThreadMap"
    for a, b in zip(alone, split, strict=True):
        np.testing.assert_array_equal(a, b)
    seen = ex.threads(2).map(lambda _: inner_threads(), range(4))
    assert list(seen) == [1, 1, 1, 1]


def test_a_pass_started_inside_a_pass_thread_runs_in_that_thread(monkeypatch) -> None:
    """A pass over a shard inside a pass over the shards: the inner pass runs in the
    outer pass's thread (waiting on the same busy pool deadlocked: `symcal solve --data
    calibration=DIR` hung on shards of 1e5 rows)."""
    monkeypatch.setenv("SYMCAL_THREADS", "2")
    monkeypatch.setattr(ex, "THREAD_MIN", 1)
    pool = ex.ThreadExecutor(2)
    done: list[list[tuple[int, str]]] = []

    def shard(i: int) -> list[tuple[int, str]]:
        inner = ex.default_executor(10**6)
        assert inner is ex.default_executor(1) and isinstance(inner, ex.SerialExecutor)
        return list(pool.map(lambda k: (k * i, threading.current_thread().name), range(6)))

    worker = threading.Thread(target=lambda: done.append(list(pool.map(shard, range(4)))),
                              daemon=True)
    worker.start()
    worker.join(timeout=60)
    assert not worker.is_alive(), "a pass inside a pass thread waited on its own pool"
    for i, rows in enumerate(done[0]):
        assert [k for k, _ in rows] == [k * i for k in range(6)]
        assert len({name for _, name in rows}) == 1          # all in the shard's thread

