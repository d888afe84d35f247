"""One huge log: passes over shards (Parquet, NPZ, CSV), on Dask, equal the in-memory
passes to 1e-10 (issue 16, item 2)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from conftest import ROOT

import symcal
from symcal.base.errors import DataError
from symcal.calibrate.partitioned import solve_partitioned
from symcal.data.dataset import make_dataset, read_table, write_table
from symcal.data.loading import needed_columns
from symcal.data.shards import open_shards
from symcal.simulation import load_scenario, simulate_run
from symcal.solvers.executor import SerialExecutor, ThreadExecutor
from symcal.solvers.objective import Objective

SIZES = (1100, 2600, 1300)      # uneven shards (each one chunk: chunks are 8192 rows)
N = sum(SIZES)


def _columns(problem_file: str, scenario: str, n: int, seed: int) -> dict[str, np.ndarray]:
    return simulate_run(load_scenario(ROOT / scenario), "calibration", seed=seed, n=n)


def write_shards(folder: Path, cols: dict[str, np.ndarray], kind: str,
                 sizes: tuple[int, ...] = SIZES) -> Path:
    """Split ``cols`` into shards of ``sizes`` rows, written as ``kind`` files."""
    folder.mkdir(parents=True, exist_ok=True)
    start = 0
    for i, size in enumerate(sizes):
        part = {k: v[start:start + size] for k, v in cols.items()}
        path = folder / f"part-{i:03d}.{kind}"
        if kind == "parquet":
            pq.write_table(pa.table(part), path)
        else:
            write_table(path, part)
        start += size
    return folder


@pytest.fixture(scope="module")
def dual():
    problem = symcal.load_problem(ROOT / "problems/dual_sensor_calibration.yaml")
    cols = _columns("", "problems/scenarios/courier_dual.yaml", N, seed=5)
    free = np.ones(len(problem.parameters), dtype=bool)
    constraints = tuple(c.name for c in problem.constraints)
    theta = np.array([p.value + 0.01 * p.scale for p in problem.parameters])
    return problem, cols, free, constraints, theta


def _same_passes(objective: Objective, sharded, memory, theta: np.ndarray) -> None:
    """Every pass over the shards equals the pass over the same data in memory."""
    assert objective.cost(sharded, theta) == pytest.approx(objective.cost(memory, theta),
                                                           rel=1e-10)
    a, b = objective.cost_terms(sharded, theta), objective.cost_terms(memory, theta)
    assert a == pytest.approx(b, rel=1e-10)
    for x, y in zip(objective.normal_equations(sharded, theta),
                    objective.normal_equations(memory, theta), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-10, atol=1e-10 * np.max(np.abs(y)))
    r1, c1, t1, rows1 = objective.accumulate_r(sharded, theta)
    r2, c2, t2, rows2 = objective.accumulate_r(memory, theta)
    assert rows1 == rows2 == N * len(objective.constraints)
    # R is unique up to the signs of its rows: compare RᵀR, Rᵀc and the tail
    np.testing.assert_allclose(r1.T @ r1, r2.T @ r2, rtol=1e-10,
                               atol=1e-10 * np.max(np.abs(r2.T @ r2)))
    np.testing.assert_allclose(r1.T @ c1, r2.T @ c2, rtol=1e-10,
                               atol=1e-10 * np.max(np.abs(r2.T @ c2)))
    assert float(c1 @ c1) + t1 == pytest.approx(float(c2 @ c2) + t2, rel=1e-10)
    np.testing.assert_allclose(objective.residual_covariance(sharded, theta, 7),
                               objective.residual_covariance(memory, theta, 7), rtol=1e-10)


@pytest.mark.parametrize("kind", ["parquet", "npz", "csv"])
def test_passes_over_shards_equal_the_passes_in_memory(dual, tmp_path, kind) -> None:
    problem, cols, free, constraints, theta = dual
    folder = write_shards(tmp_path / kind, cols, kind)
    sharded = open_shards("calibration", folder, needed_columns(problem))
    assert [s.rows for s in sharded.shards] == list(SIZES) and sharded.n == N
    if kind == "csv":               # CSV keeps 15 digits: compare with the same numbers
        write_table(tmp_path / "whole.csv", cols)
        cols = read_table(tmp_path / "whole.csv")
    memory = make_dataset("calibration", "memory", cols, needed_columns(problem))
    _same_passes(Objective(problem, constraints, free, executor=ThreadExecutor(2)),
                 sharded, memory, theta)


def test_a_partitioned_solve_equals_the_in_memory_solve(tmp_path) -> None:
    """solve_partitioned returns a Result like solve's (issue 21 item 3): the same
    estimate, standard errors, gauges and statistics (moments of the shards combined)."""
    problem = symcal.load_problem(ROOT / "problems/platen_self_calibration.yaml")
    problem = problem.with_weighting("equal")      # per-row weights need every row at once
    cols = _columns("", "problems/scenarios/courier_platen.yaml", 6000, seed=2)
    folder = write_shards(tmp_path / "log", cols, "npz", (2000, 2500, 1500))
    memory = make_dataset("calibration", "memory", cols, needed_columns(problem))
    sharded = solve_partitioned(problem, folder, executor=SerialExecutor())
    local = solve_partitioned(problem, memory)
    full = symcal.solve(problem, {"calibration": memory})
    assert isinstance(sharded, symcal.Result) and sharded.success
    assert sharded.provenance[0].n == 6000
    scales = np.array([p.scale for p in problem.parameters])
    for other in (local, full):
        np.testing.assert_allclose(sharded.theta / scales, other.theta / scales, rtol=0,
                                   atol=1e-10)
    # the standard errors of the partitioned path (in memory too; solve's own allow for
    # the serial correlation it finds on time-ordered rows, which shards do not examine)
    for other in (local,):
        for name, p in other.params.items():
            q = sharded.params[name]
            assert (q.se is None) == (p.se is None), name
            if p.se is not None:
                assert q.se == pytest.approx(p.se, rel=1e-8), name
    assert [g.text for g in sharded.stages[0].gauges.gauges] == \
        [g.text for g in full.stages[0].gauges.gauges]
    for s in full.statistics:
        got = next(x for x in sharded.statistics if (x.name, x.dataset) == (s.name, s.dataset))
        assert got.n == s.n
        for which in ("before", "after"):
            a, b = getattr(got, which), getattr(s, which)
            assert (a.rms, a.mean) == pytest.approx((b.rms, b.mean), rel=1e-9, abs=1e-15)
            assert a.std == pytest.approx(b.std, rel=1e-7)
    np.testing.assert_allclose(sharded.value("g_p", unit="mm"), full.value("g_p", unit="mm"),
                               rtol=0, atol=1e-12)
    assert any("are not looked for on the partitioned log" in n for n in sharded.stages[0].notes)
    # saved and loaded: the log is found again by its manifest, and refused once it changed
    sharded.save(tmp_path / "r.json")
    loaded = symcal.Result.load(tmp_path / "r.json")
    np.testing.assert_allclose(loaded.value("g_p", unit="mm"), full.value("g_p", unit="mm"),
                               rtol=0, atol=1e-12)
    first = sorted(folder.iterdir())[0]
    first.write_bytes(first.read_bytes())            # the same bytes, a new modification
    os.utime(first, ns=(0, 0))
    with pytest.raises(symcal.SymcalError, match="changed since the result was computed"):
        symcal.Result.load(tmp_path / "r.json").check_data()


def test_a_folder_of_shards_from_the_command_line(tmp_path, capsys) -> None:
    """symcal solve PROBLEM --data calibration=FOLDER solves the log kept as shards and
    prints the same report as for the data in one file (issue 26 item 7)."""
    from symcal.cli import main

    prob = ROOT / "problems/platen_self_calibration.yaml"
    cols = _columns("", "problems/scenarios/courier_platen.yaml", 3000, seed=4)
    folder = write_shards(tmp_path / "log", cols, "npz", (1000, 1000, 1000))
    write_table(tmp_path / "whole.npz", cols)
    args = ["solve", str(prob), "--weighting", "equal", "--json"]
    assert main([*args, "--data", f"calibration={folder}"]) == 0
    sharded = json.loads(capsys.readouterr().out)
    assert main([*args, "--data", f"calibration={tmp_path / 'whole.npz'}"]) == 0
    whole = json.loads(capsys.readouterr().out)
    for a, b in zip(sharded["parameters"], whole["parameters"], strict=True):
        assert a["value"] == pytest.approx(b["value"], rel=1e-9, abs=1e-12)
    assert [s["after"]["rms"] for s in sharded["statistics"]] == pytest.approx(
        [s["after"]["rms"] for s in whole["statistics"]], rel=1e-9)


def test_shards_are_checked_and_named(dual, tmp_path) -> None:
    problem, cols, *_ = dual
    needed = needed_columns(problem)
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no shard files"):
        open_shards("calibration", tmp_path / "empty", needed)
    mixed = write_shards(tmp_path / "mixed", cols, "npz")
    pq.write_table(pa.table({k: v[:10] for k, v in cols.items()}), mixed / "extra.parquet")
    with pytest.raises(DataError, match=r"shards of more than one kind \(npz, parquet\)"):
        open_shards("calibration", mixed, needed)
    missing = write_shards(tmp_path / "missing", {k: v for k, v in cols.items()
                                                  if k != needed[0]}, "parquet")
    sharded = open_shards("calibration", missing, needed)
    objective = Objective(problem, tuple(c.name for c in problem.constraints),
                          np.ones(len(problem.parameters), dtype=bool))
    with pytest.raises(DataError, match=rf"part-000\.parquet: missing column '{needed[0]}'"):
        objective.cost(sharded, np.array([p.value for p in problem.parameters]))


def test_each_shard_done_advances_the_progress_meter(tmp_path) -> None:
    problem = symcal.load_problem(ROOT / "problems/platen_self_calibration.yaml")
    cols = _columns("", "problems/scenarios/courier_platen.yaml", 3000, seed=4)
    folder = write_shards(tmp_path / "log", cols, "parquet", (1000, 1000, 1000))
    counted: list[tuple[str, int]] = []

    class Meter:
        def __init__(self, label: str) -> None:
            self.label = label

        def advance(self, n: int = 1) -> None:
            counted.append((self.label, n))

        def note(self, text: str) -> None:
            pass

        def close(self) -> None:
            pass

    def bars(label: str, total: int | None, unit: str) -> Meter:
        assert unit == "shard"
        return Meter(label)

    from symcal.solvers.instrument import counting

    with counting() as counts:
        solve_partitioned(problem, folder, bars=bars)
    assert len(counted) == 3 * counts.passes and counts.passes >= 1


@pytest.fixture(scope="module")
def cluster():
    from symcal.solvers.dask_executor import dask_executor

    with dask_executor(workers=2) as executor:
        yield executor


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["parquet", "npz"])
def test_passes_on_a_local_dask_cluster_equal_the_passes_in_memory(dual, cluster, tmp_path,
                                                                    kind) -> None:
    problem, cols, free, constraints, theta = dual
    sharded = open_shards("calibration", write_shards(tmp_path / kind, cols, kind),
                          needed_columns(problem))
    memory = make_dataset("calibration", "memory", cols, needed_columns(problem))
    _same_passes(Objective(problem, constraints, free, executor=cluster), sharded, memory,
                 theta)


@pytest.mark.slow
def test_a_partitioned_solve_on_dask_equals_the_in_memory_solve(cluster, tmp_path) -> None:
    problem = symcal.load_problem(ROOT / "problems/platen_self_calibration.yaml")
    cols = _columns("", "problems/scenarios/courier_platen.yaml", 6000, seed=2)
    folder = write_shards(tmp_path / "log", cols, "parquet", (2000, 2500, 1500))
    memory = make_dataset("calibration", "memory", cols, needed_columns(problem))
    on_dask = solve_partitioned(problem, folder, executor=cluster)
    local = solve_partitioned(problem, memory)
    scales = np.array([p.scale for p in problem.parameters])
    np.testing.assert_allclose(on_dask.theta / scales, local.theta / scales, rtol=0,
                               atol=1e-10)
    assert on_dask.rss == pytest.approx(local.rss, rel=1e-10)


@pytest.mark.slow
def test_a_nonlinear_partitioned_solve_equals_the_in_memory_solve(tmp_path) -> None:
    """The dual problem (closed form, closed form, then lm, weighting estimated) on NPZ
    shards: the estimate equals symcal.solve's on the data in memory to 1e-10 of each
    parameter's scale, although the passes reduce in another order (lm's last
    Gauss-Newton step settles what the cost's rounding cannot)."""
    problem = symcal.load_problem(ROOT / "problems/dual_sensor_calibration.yaml")
    problem = problem.with_weighting("estimated")   # 'propagated' weights every row
    cols = _columns("", "problems/scenarios/courier_dual.yaml", 6000, seed=2)
    folder = write_shards(tmp_path / "log", cols, "npz", (2000, 2500, 1500))
    memory = make_dataset("calibration", "memory", cols, needed_columns(problem))
    sharded = solve_partitioned(problem, folder, executor=SerialExecutor())
    full = symcal.solve(problem, {"calibration": memory})
    assert sharded.success and full.success
    assert [s.method for s in sharded.stages] == ["linear", "linear", "lm"]
    scales = np.array([p.scale for p in problem.parameters])
    np.testing.assert_allclose(sharded.theta / scales, full.theta / scales, rtol=0,
                               atol=1e-10)
