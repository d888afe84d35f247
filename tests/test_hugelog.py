"""One huge log: passes over shards (Parquet, NPZ, CSV), on Dask, equal the in-memory
passes to 1e-10 (issue 16, item 2)."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import courier_scenarios
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from conftest import ROOT

import symcal
from symcal.analysis import order
from symcal.base.errors import DataError
from symcal.calibrate.partitioned import solve_partitioned
from symcal.data.dataset import make_dataset, read_table, write_table
from symcal.data.loading import needed_columns
from symcal.data.shards import open_shards
from symcal.simulation import load_scenario, simulate_run, slipped_rows
from symcal.solvers.executor import SerialExecutor, ThreadExecutor
from symcal.solvers.instrument import counting
from symcal.solvers.objective import Objective

PLATEN = "problems/platen_self_calibration.yaml"
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


@pytest.mark.parametrize("kind", ["parquet", *(pytest.param(k, marks=pytest.mark.slow)
                                              for k in ("npz", "csv"))])
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


def differences(a: Any, b: Any, rel: float = 1e-9, path: str = "", size: float = 0.0,
                skip: tuple[str, ...] = ()) -> list[tuple]:
    """Where two result documents differ: every string, integer and flag exactly, every
    number to ``rel`` of its size, or of the largest number of its list (the singular
    values of a null direction are rounding), or of its spread's RMS (a mean); 1e-7 for a
    spread found as √(rms² - mean²), which loses digits to cancellation; near-null
    directions whatever their sign; a correlation to ``rel`` of 1 (a correlation of 3e-5
    is the difference of products of 1's size); the times a solve took, where the data
    came from and the keys ``skip`` excepted."""
    last = path.rsplit("/", 1)[-1]
    if last in ("seconds", "datasets", *skip):
        return []
    if last == "near_null":         # a direction is a direction whatever its sign
        a, b = [[_signless(d) for d in x] for x in (a, b)]
    if isinstance(a, dict) and isinstance(b, dict):
        out = [(path, "keys", sorted(set(a) ^ set(b)))] if set(a) != set(b) else []
        rms = a.get("rms")              # a mean is measured against its spread's RMS
        size = abs(rms) if isinstance(rms, float) else 0.0
        return out + [d for k in a if k in b
                      for d in differences(a[k], b[k], rel, f"{path}/{k}", size, skip)]
    if isinstance(a, list) and isinstance(b, list):
        out = [(path, "length", len(a), len(b))] if len(a) != len(b) else []
        top = max((abs(x) for x in (*a, *b) if isinstance(x, float) and math.isfinite(x)),
                  default=0.0)
        return out + [d for i, (x, y) in enumerate(zip(a, b, strict=False))
                      for d in differences(x, y, rel, f"{path}/{i}", top, skip)]
    if isinstance(a, float) and isinstance(b, float):
        tol = 1e-7 if last == "std" else rel
        if "/correlations/" in path:     # a correlation's size is 1, not its own value
            size = max(size, 1.0)
        same = a == b or (math.isnan(a) and math.isnan(b)) or \
            abs(a - b) <= tol * max(abs(a), abs(b), size)
        return [] if same else [(path, a, b)]
    return [] if a == b and type(a) is type(b) else [(path, a, b)]


def _signless(entry: dict) -> dict:
    """A near-null direction with its first coefficient positive (its text dropped)."""
    first = next((v for v in entry["coefficients"].values() if v), 1.0)
    sign = 1.0 if first > 0 else -1.0
    return {**{k: v for k, v in entry.items() if k != "direction"},
            "coefficients": {k: sign * v for k, v in entry["coefficients"].items()}}


@pytest.mark.slow
def test_a_partitioned_solve_equals_the_in_memory_solve(tmp_path) -> None:
    """solve_partitioned returns a Result like solve's (issue 21 item 3), its document the
    same to 1e-9: the estimate, standard errors, the serial correlation of the
    time-ordered rows, gauges, statistics (moments of the shards combined), the
    outliers, the 'propagated' weighting's per-row weights (computed in the passes), the
    noise floors and the global tests (sums over the shards)."""
    problem = symcal.load_problem(ROOT / "problems/platen_self_calibration.yaml")
    assert problem.weighting == "propagated"
    cols = _columns("", "problems/scenarios/courier_platen.yaml", 3000, seed=2)
    folder = write_shards(tmp_path / "log", cols, "npz", (1000, 1250, 750))
    memory = make_dataset("calibration", "memory", cols, needed_columns(problem))
    sharded = solve_partitioned(problem, folder, executor=SerialExecutor())
    full = symcal.solve(problem, {"calibration": memory})
    assert isinstance(sharded, symcal.Result) and sharded.success
    assert sharded.provenance[0].n == 3000
    assert differences(sharded.to_dict(), full.to_dict()) == []
    stage = sharded.stages[0]
    assert stage.serial is not None            # examined: the rows are in time order
    assert stage.outliers is not None and stage.outliers.rows == 3000
    assert [t.dataset for t in sharded.floor_tests] == ["calibration", "flyby"]
    assert all(t.chi2_dof is not None for t in sharded.floor_tests)
    assert any(n.startswith("weighting: each observation's constraints whitened by their "
                            "covariance propagated") for n in stage.notes)
    assert [g.text for g in stage.gauges.gauges] == \
        [g.text for g in full.stages[0].gauges.gauges] != []
    local = solve_partitioned(problem, memory)       # the passes on the data in memory
    assert differences(local.to_dict(), full.to_dict()) == []
    np.testing.assert_allclose(sharded.value("g_p", unit="mm"), full.value("g_p", unit="mm"),
                               rtol=0, atol=1e-12)
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


@pytest.mark.slow
def test_a_folder_of_shards_from_the_command_line(tmp_path, capsys) -> None:
    """symcal solve PROBLEM --data calibration=FOLDER solves the log kept as shards and
    prints the same report as for the data in one file (issue 26 item 7)."""
    from symcal.cli import main

    prob = ROOT / "problems/platen_self_calibration.yaml"
    cols = _columns("", "problems/scenarios/courier_platen.yaml", 3000, seed=4)
    folder = write_shards(tmp_path / "log", cols, "npz", (1000, 1000, 1000))
    write_table(tmp_path / "whole.npz", cols)
    docs, texts = [], []
    for k, data in enumerate((folder, tmp_path / "whole.npz")):
        out = tmp_path / f"out{k}"
        assert main(["solve", str(prob), "--json", "--out", str(out), "--data",
                     f"calibration={data}"]) == 0
        docs.append(json.loads(capsys.readouterr().out))
        texts.append(re.sub(r"; [0-9.e+-]+ s\b", "; (seconds)",     # the time it took
                            (out / "report.txt").read_text().replace(str(data), "DATA")))
    assert differences(*docs) == []
    assert docs[0]["stages"][0]["outliers"] is not None
    assert docs[0]["floor_tests"][0]["dataset"] == "calibration"
    assert texts[0] == texts[1]


@pytest.mark.slow
def test_a_folder_of_large_shards_from_the_command_line_finishes(tmp_path) -> None:
    """Shards above the passes' thread threshold, from the command line, in a fresh
    process: it ends (with the default threads) and its estimate is the serial one."""
    from symcal.solvers import executor as ex

    problem = ROOT / "problems/platen_self_calibration.yaml"
    cols = _columns("", "problems/scenarios/courier_platen.yaml", 2 * ex.THREAD_MIN + 100,
                    seed=8)
    folder = write_shards(tmp_path / "log", cols, "npz",
                          (ex.THREAD_MIN + 50, ex.THREAD_MIN + 50))
    values = []
    for threads in ("2", "1"):
        out = subprocess.run(
            [sys.executable, "-m", "symcal", "solve", str(problem), "--json", "--data",
             f"calibration={folder}"], capture_output=True, text=True, timeout=600,
            env={**os.environ, "SYMCAL_THREADS": threads})
        assert out.returncode in (0, 1), out.stderr
        values.append({p["name"]: p["value"] for p in json.loads(out.stdout)["parameters"]})
    assert values[0] == values[1]


# ------------------------------------------------- robust losses, outliers, serial rows

ROBUST = """\
problem: platen_robust
extends: {base}
constraints:
  g_p:
    expr: (s1.p_hat - s3.p_hat) - (s2.p_hat - s4.p_hat)
    unit: um
    loss: {{type: huber, scale: 2}}
"""


@pytest.fixture(scope="module")
def slips(tmp_path_factory):
    """The platen's log with count slips of segment s1 on 1 % of the rows (as in
    test_robust), kept as three NPZ shards, and the fly-by in memory."""
    scenario = courier_scenarios.platen(courier_scenarios.count_slips(
        {1: 0.01, 2: 0.0, 3: 0.0, 4: 0.0}))
    folder = tmp_path_factory.mktemp("slips")
    cols = simulate_run(scenario, "calibration", seed=11)
    flyby = make_dataset("flyby", "simulated", simulate_run(scenario, "flyby", seed=11), [])
    (folder / "robust.yaml").write_text(ROBUST.format(base=ROOT / PLATEN))
    return (scenario, write_shards(folder / "log", cols, "npz", (300, 450, 250)),
            make_dataset("calibration", "simulated", cols, []), flyby, folder)


def test_a_robust_loss_on_shards_equals_the_in_memory_solve(slips) -> None:
    """Huber by IRLS in passes over the shards, its weights computed in each pass: the same
    rounds, estimate, sandwich standard errors and outliers (the slipped rows, their
    weights) as the robust solve in memory."""
    scenario, folder, memory, flyby, tmp = slips
    problem = symcal.load_problem(tmp / "robust.yaml")
    with counting() as counts:
        sharded = solve_partitioned(problem, folder, data={"flyby": flyby})
    full = symcal.solve(problem, {"calibration": memory, "flyby": flyby})
    assert sharded.success and "iteratively reweighted" in sharded.stages[-1].message
    assert differences(sharded.to_dict(), full.to_dict()) == []
    outliers = sharded.outliers
    assert outliers is not None and outliers.loss == "g_p: huber, scale 2 µm"
    assert sorted(o.row for o in outliers.listed) == \
        slipped_rows(scenario, "calibration", 11)["p1"]
    assert all(o.weight < 0.05 for o in outliers.listed)
    assert sharded.stages[-1].serial is None        # not examined under a robust loss
    # nothing of the log's size in the lead: no pass returned residual rows or scores
    assert "residuals" not in counts.by_method and "score_chunks" not in counts.by_method


def test_outliers_that_dominate_a_squared_fit_on_shards(slips, monkeypatch) -> None:
    """A squared fit that the slips dominate: the outliers, their share, the spread
    measured once the fit is solved again without them (the flagged residuals weighted 0
    in the passes) and the verdict that they are gross, as in memory; the medians found
    exactly with small histograms (several narrowing passes each)."""
    scenario, folder, memory, flyby, _ = slips
    problem = symcal.load_problem(ROOT / PLATEN)
    monkeypatch.setattr(order, "BINS", 8)
    monkeypatch.setattr(order, "GATHER", 40)
    sharded = solve_partitioned(problem, folder, data={"flyby": flyby})
    monkeypatch.undo()
    full = symcal.solve(problem, {"calibration": memory, "flyby": flyby})
    assert differences(sharded.to_dict(), full.to_dict()) == []
    outliers = sharded.outliers
    assert outliers is not None and outliers.squared and outliers.dominate
    assert outliers.clean_std is not None and outliers.gross
    assert sorted(o.row for o in outliers.listed) == \
        slipped_rows(scenario, "calibration", 11)["p1"]
    from symcal.report.text import text_report

    assert "outliers dominate:" in text_report(sharded).split("\n\n")[1]


def test_the_exact_median_of_a_log_by_passes(tmp_path, monkeypatch) -> None:
    """The order statistics by passes equal numpy's median, ties and a single value
    included, whatever the bins (every narrowing path: gathered at once, histograms,
    an interval of equal values)."""
    from symcal.data.shards import open_shards as opened

    class Column:
        def __call__(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            return u.T, np.ones(u.T.shape, dtype=bool)

    rng = np.random.default_rng(7)
    cases = {"cauchy": rng.standard_cauchy(3001), "ties": np.round(rng.normal(size=2000)),
             "one": np.array([2.5]), "even": rng.normal(size=1000) * 1e-9 + 3.0}
    for bins, gather in ((4096, 1 << 16), (8, 5), (2, 1)):
        monkeypatch.setattr(order, "BINS", bins)
        monkeypatch.setattr(order, "GATHER", gather)
        for name, x in cases.items():
            cuts = sorted({0, x.size, *rng.integers(0, x.size, 3).tolist()})
            folder = tmp_path / f"{name}-{bins}"
            folder.mkdir()
            for i, (a, b) in enumerate(zip(cuts, cuts[1:], strict=False)):
                write_table(folder / f"p{i}.npz", {"x": x[a:b]})
            log = opened("d", folder, ["x"])
            got, counted = order.medians(Column(), log, ("x",))
            assert int(counted.n[0]) == x.size
            assert got[0] == np.median(x), (name, bins)


def test_serial_correlation_on_shards_shorter_than_its_lags(tmp_path) -> None:
    """Serially correlated rows (AR(1), ρ = 0.9) in shards of 3, 1000, 5, 2 and 990 rows:
    the lag-1 autocorrelation joined across the boundaries, the Newey-West standard errors
    with pairs that straddle several shards (69 lags), as in memory."""
    from test_serial import GAUGE, PROBLEM, _recording

    (tmp_path / "gauge.yaml").write_text(textwrap.dedent(GAUGE))
    (tmp_path / "two.yaml").write_text(textwrap.dedent(PROBLEM))
    problem = symcal.load_problem(tmp_path / "two.yaml")
    cols = _recording(3, 0.9, 2000)
    folder = write_shards(tmp_path / "log", cols, "npz", (3, 1000, 5, 2, 990))
    sharded = solve_partitioned(problem, folder)
    full = symcal.solve(problem, {"calibration": make_dataset("calibration", "m", cols, [])})
    serial = sharded.stages[-1].serial
    assert serial is not None and serial.detected and serial.lags > 5
    assert differences(sharded.to_dict(), full.to_dict()) == []
    # out of time order across a boundary: not examined, as in memory
    shuffled = write_shards(tmp_path / "late", {k: np.concatenate([v[1000:], v[:1000]])
                                                for k, v in cols.items()}, "npz",
                            (1000, 1000))
    assert solve_partitioned(problem, shuffled).stages[-1].serial is None


@pytest.mark.slow
def test_propagated_weights_of_two_constraints_on_shards(tmp_path) -> None:
    """The dual problem's 'propagated' weighting (each observation's 2 × 2 C_i^-½ of g_x,
    g_y, computed in every pass from the noisy view, never held): the same weights'
    decisions, estimate, standard errors, floors and tests as in memory."""
    problem = symcal.load_problem(ROOT / "problems/dual_sensor_calibration.yaml")
    assert problem.weighting == "propagated"
    cols = _columns("", "problems/scenarios/courier_dual.yaml", 900, seed=3)
    folder = write_shards(tmp_path / "log", cols, "npz", (300, 400, 200))
    memory = make_dataset("calibration", "memory", cols, needed_columns(problem))
    with counting() as counts:
        sharded = solve_partitioned(problem, folder)
    full = symcal.solve(problem, {"calibration": memory})
    assert sharded.success
    assert differences(sharded.to_dict(), full.to_dict()) == []
    coordination = next(s for s in sharded.stages if s.name == "coordination")
    assert any("propagated from the readings' declared noise" in n for n in coordination.notes)
    assert "residuals" not in counts.by_method and "score_chunks" not in counts.by_method


LOG_FIT = """\
problem: log_fit
columns: {x: {unit: "1"}, y: {unit: mm}}
parameters:
  a: {value: 1, scale: 1}
  b: {value: 0, scale: 1}
constraints:
  r: {expr: y - a*log(x) - b, sigma: 0.1}
datasets:
  calibration: {path: d.csv}
"""


def test_refusals_on_shards_are_those_in_memory(tmp_path, slips) -> None:
    """What solve refuses, a log kept as shards refuses with the same words: a constraint
    that is not finite at the start (its observation counted over the whole log), a
    robust loss with per-row weighting."""
    (tmp_path / "fit.yaml").write_text(LOG_FIT)
    x = np.linspace(0.5, 3, 200)
    x[137] = 0.0                                    # y - log(0): inf on observation 138
    cols = {"x": x, "y": 2 * np.log(np.maximum(x, 1e-3)) + 0.1}
    folder = write_shards(tmp_path / "log", cols, "npz", (100, 60, 40))
    problem = symcal.load_problem(tmp_path / "fit.yaml")
    messages = []
    for data in (folder, make_dataset("calibration", "memory", cols, [])):
        with pytest.raises(symcal.SymcalError) as caught:
            (solve_partitioned(problem, data) if isinstance(data, Path)
             else symcal.solve(problem, {"calibration": data}))
        messages.append(str(caught.value).replace(str(folder), "memory"))
    assert messages[0] == messages[1]
    assert "'r' is inf at the initial parameters on observation 138 of 'calibration'" in \
        messages[0]
    _, log, _, _, tmp = slips
    robust = symcal.load_problem(tmp / "robust.yaml").with_weighting("propagated")
    with pytest.raises(symcal.SymcalError, match=r"is a robust loss, which weighting "
                                                 r"'propagated' does not support"):
        solve_partitioned(robust, log)


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
def test_a_partitioned_solve_on_dask_equals_the_in_memory_solve(cluster, tmp_path, slips
                                                                 ) -> None:
    """On a local Dask cluster (every task pickled to a worker process, the weighers and
    analyses with it): the propagated weighting, a robust loss, the outliers' refit and
    their medians give the in-memory solve's document."""
    problem = symcal.load_problem(ROOT / "problems/platen_self_calibration.yaml")
    cols = _columns("", "problems/scenarios/courier_platen.yaml", 6000, seed=2)
    folder = write_shards(tmp_path / "log", cols, "parquet", (2000, 2500, 1500))
    memory = make_dataset("calibration", "memory", cols, needed_columns(problem))
    on_dask = solve_partitioned(problem, folder, executor=cluster)
    assert differences(on_dask.to_dict(),
                       symcal.solve(problem, {"calibration": memory}).to_dict()) == []
    _, log, memory, flyby, tmp = slips
    for robust in (symcal.load_problem(ROOT / PLATEN),
                   symcal.load_problem(tmp / "robust.yaml")):
        on_dask = solve_partitioned(robust, log, data={"flyby": flyby}, executor=cluster)
        full = symcal.solve(robust, {"calibration": memory, "flyby": flyby})
        assert differences(on_dask.to_dict(), full.to_dict()) == []


@pytest.mark.slow
def test_a_nonlinear_partitioned_solve_equals_the_in_memory_solve(tmp_path) -> None:
    """The dual problem (closed form, closed form, then lm, weighting estimated) on NPZ
    shards: the estimate equals symcal.solve's on the data in memory to 1e-10 of each
    parameter's scale, although the passes reduce in another order (lm's last
    Gauss-Newton step settles what the cost's rounding cannot), and so is the rest of its
    document."""
    problem = symcal.load_problem(ROOT / "problems/dual_sensor_calibration.yaml")
    problem = problem.with_weighting("estimated")
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
    # the weighting's note, the standard errors, outliers, floors and tests too; the
    # covariances to 1e-8: the sandwich with the declared noise (equal weights, then one
    # whitening) takes its sums in the shards' order, and the coordination stage's l_x
    # and o_x (correlation -1.0) carry that rounding into them at 3e-9
    a, b = sharded.to_dict(), full.to_dict()
    assert differences(a, b, skip=("uncertainty",)) == []
    for x, y in [(a["uncertainty"], b["uncertainty"]),
                 *((s["uncertainty"], t["uncertainty"])
                   for s, t in zip(a["stages"], b["stages"], strict=True))]:
        assert differences(x, y, rel=1e-8) == []


@pytest.mark.slow
def test_implicit_definitions_on_shards(tmp_path) -> None:
    """The implicit dual problem (started from its explicit twin's closed form, lm on the
    implicit model, 'propagated' weighting) on shards: the same estimate to 1e-10 of each
    parameter's scale.  lm stops at the rounding of the cost, which the shards reduce in
    another order: it may stop one iteration later (8 against 7 here), so the quantities
    found as small differences (correlations of 1e-5, the definitions' last fixed-point
    step) agree to 1e-7, not 1e-9, and the iteration counts and messages are not
    compared."""
    problem = symcal.load_problem(ROOT / "problems/dual_sensor_calibration_implicit.yaml")
    cols = _columns("", "problems/scenarios/courier_dual.yaml", 900, seed=3)
    folder = write_shards(tmp_path / "log", cols, "npz", (300, 400, 200))
    sharded = solve_partitioned(problem, folder)
    full = symcal.solve(problem, {"calibration": make_dataset("calibration", "m", cols, [])})
    assert sharded.success and full.success and sharded.implicit
    scales = np.array([p.scale for p in problem.parameters])
    np.testing.assert_allclose(sharded.theta / scales, full.theta / scales, rtol=0,
                               atol=1e-10)
    assert differences(sharded.to_dict(), full.to_dict(), rel=1e-7,
                       skip=("message", "iterations")) == []


@pytest.mark.slow
def test_a_log_is_diagnosed_on_its_rows_spread_over_the_whole_log(tmp_path,
                                                                    monkeypatch) -> None:
    """symcal.diagnose takes a partitioned result: a log within symcal's bound is
    diagnosed on all its rows (the same candidates, to 1e-9, as the same data in
    memory); a larger one on rows spread evenly over every shard, in time order."""
    import symcal.revise.diagnose as diagnosing

    problem = symcal.load_problem(ROOT / "problems/platen_self_calibration.yaml")
    cols = _columns("", "problems/scenarios/courier_platen.yaml", 1200, seed=4)
    folder = write_shards(tmp_path / "log", cols, "npz", (500, 400, 300))
    memory = make_dataset("calibration", "memory", cols, needed_columns(problem))
    sharded = symcal.diagnose(solve_partitioned(problem, folder, executor=SerialExecutor()))
    full = symcal.diagnose(symcal.solve(problem, {"calibration": memory}))
    assert [c.label for c in sharded.leads[:5]] == [c.label for c in full.leads[:5]]
    for a, b in zip(sharded.leads[:5], full.leads[:5], strict=True):
        assert a.f_stat == pytest.approx(b.f_stat, rel=1e-9)
    monkeypatch.setattr(diagnosing, "LOG_ROWS", 400)
    log = open_shards("calibration", folder, needed_columns(problem))
    sample = diagnosing._in_memory({"calibration": log})["calibration"]
    t = np.asarray(sample.columns["t"])
    assert sample.n == 400 and np.all(np.diff(t) > 0)
    np.testing.assert_array_equal(t, np.asarray(cols["t"])[::3])
    assert "(one row in 3 of its 1200: 400 rows)" in sample.source


@pytest.mark.slow
def test_estimated_floors_on_shards_equal_those_in_memory(tmp_path) -> None:
    """A problem that declares no reading noise (the triad: every floor estimated by
    successive differences) with its calibration log as shards and its validation held
    out: the held-out test's estimate share takes the floors estimated on the log, found
    in passes over the shards (the differences across each boundary included), and the
    whole document equals the in-memory solve's."""
    triad = ROOT / "examples" / "accelerometer_triad"
    problem = symcal.load_problem(triad / "problem_fixed.yaml")
    cols = simulate_run(load_scenario(triad / "scenario.yaml"), "calibration", seed=5)
    folder = write_shards(tmp_path / "log", cols, "npz", (400, 500, 300))
    memory = make_dataset("calibration", "memory", cols, needed_columns(problem))
    sharded = solve_partitioned(problem, folder, executor=SerialExecutor())
    full = symcal.solve(problem, {"calibration": memory})
    assert sharded.success and full.success
    held = next(t for t in full.floor_tests if t.dataset == "validation")
    assert held.method == "combined" and held.rows        # the estimate's share counted
    assert differences(sharded.to_dict(), full.to_dict()) == []
