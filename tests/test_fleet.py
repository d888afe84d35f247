"""Fleet calibration on Dask (`symcal solve --fleet`, `symcal.solve_fleet`), the fleet
summary, Parquet/NPZ unit files and the progress seam.

One local cluster (2 worker processes) serves the whole module; the API tests pass its
client, the command-line tests its address (``--scheduler``)."""

from __future__ import annotations

import io
import json
import logging
import multiprocessing
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, courier_data, write_csv

import symcal
from symcal.base.errors import DataError
from symcal.base.progress import meter, terminal_bars, write_line
from symcal.calibrate.fleet import find_units, solve_fleet
from symcal.calibrate.fleet_summary import MAD_TO_SIGMA, OUTLIER_SCORE, summarise
from symcal.cli import main
from symcal.data.dataset import read_table, write_table

PROBLEM = ROOT / "problems" / "platen_self_calibration.yaml"
NOISE = 0.5e-3
N = 300
#: Unit → (format of its files, its calibration seed, whether it has its own fly-by).
GOOD = {"a_csv": ("csv", 11, True), "b_npz": ("npz", 12, False),
        "c_parquet": ("parquet", 13, True)}
ODD, BROKEN, TYPO = "d_odd", "e_broken", "f_typo"
#: The outlier unit's s2.k1 is this much larger than the fleet's (mm).
ODD_K1 = 0.02


def _write(path: Path, cols: dict[str, np.ndarray]) -> Path:
    if path.suffix == ".parquet":
        import pyarrow as pa
        import pyarrow.parquet as pq

        pq.write_table(pa.table({k: np.asarray(v) for k, v in cols.items()}), path)
        return path
    write_table(path, cols)
    return path


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, np.ndarray]]:
    """A fleet folder of six units, and each solvable unit's true eq. (3) coefficients."""
    root = tmp_path_factory.mktemp("fleet")
    rng = np.random.default_rng(42)
    k = rng.normal(0, 0.004, (4, 9)) / np.array([1, 1, 1, 2, 2, 4, 4, 6, 6])
    truths = {}
    for unit, (fmt, seed, flyby) in GOOD.items():
        (root / unit).mkdir()
        _write(root / unit / f"calibration.{fmt}", courier_data(N, k, NOISE, seed))
        if flyby:
            _write(root / unit / f"flyby.{fmt}", courier_data(100, k, NOISE, seed + 100))
        truths[unit] = k
    odd = k.copy()
    odd[1, 1] += ODD_K1
    (root / ODD).mkdir()
    write_csv(root / ODD / "calibration.csv", courier_data(N, odd, NOISE, 14))
    write_csv(root / ODD / "flyby.csv", courier_data(100, odd, NOISE, 114))
    truths[ODD] = odd
    (root / BROKEN).mkdir()
    lines = write_csv(root / BROKEN / "calibration.csv",
                      courier_data(N, k, NOISE, 15)).read_text().splitlines()
    cells = lines[4].split(",")
    cells[2] = "n/a"
    lines[4] = ",".join(cells)
    (root / BROKEN / "calibration.csv").write_text("\n".join(lines) + "\n")
    (root / TYPO).mkdir()
    write_csv(root / TYPO / "calibraton.csv", courier_data(50, k, NOISE, 16))
    return root, truths


@pytest.fixture(scope="module")
def client():
    """The module's one local Dask cluster: 2 worker processes, 1 thread each."""
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None, silence_logs=logging.ERROR) as cluster, \
            Client(cluster) as c:
        yield c


@pytest.fixture(scope="module")
def result(fleet, client) -> symcal.FleetResult:
    return solve_fleet(PROBLEM, fleet[0], executor=client)


def _local(fleet_dir: Path, unit: str) -> dict[str, str]:
    return {p.stem: str(p) for p in sorted((fleet_dir / unit).iterdir())}


# ------------------------------------------------------------------ the fleet on a cluster

@pytest.mark.slow
def test_each_unit_equals_its_local_solve(fleet, result) -> None:
    fleet_dir, _ = fleet
    for unit in (*GOOD, ODD):
        local = symcal.solve(PROBLEM, _local(fleet_dir, unit))
        doc = result.to_dict()["units"][unit]
        assert doc["solver"]["success"] and local.success and result.results[unit].success
        got = {p["name"]: p for p in doc["parameters"]}
        for p in local.params.values():
            assert abs(got[p.name]["value"] - p.value) <= 1e-12, (unit, p.name)
            if p.se is not None:
                assert abs(got[p.name]["se"] - p.se) <= 1e-12 * max(1.0, p.se)
        assert doc["information_criteria"]["rss"] == pytest.approx(local.rss, rel=1e-12)
        files = {d["name"]: d["file"] for d in doc["datasets"]}
        assert files["calibration"] == str(Path(_local(fleet_dir, unit)["calibration"])
                                           .resolve())
    # b_npz has no fly-by of its own: the problem's simulated one stands in
    assert {d.name: d.file for d in result.results["b_npz"].provenance}["flyby"] is None


@pytest.mark.slow
@pytest.mark.parametrize("start", ["auto", "fork", "forkserver", "spawn"])
def test_the_embedded_clusters_units_equal_their_local_solves(fleet, monkeypatch,
                                                              start) -> None:
    """The embedded cluster (``workers=2``), its workers started each way
    ``SYMCAL_WORKER_START`` names, gives every unit its local solve's estimate, standard
    errors and RSS to 1e-12."""
    import symcal.calibrate.fleet as fleet_module

    if start != "auto" and start not in multiprocessing.get_all_start_methods():
        pytest.skip(f"no {start} on this platform")
    monkeypatch.setenv("SYMCAL_WORKER_START", start)
    fleet_dir, _ = fleet
    made = fleet_module.solve_fleet(PROBLEM, fleet_dir, workers=2)
    assert set(made.results) == {*GOOD, ODD} and set(made.errors) == {BROKEN, TYPO}
    for unit in (*GOOD, ODD):
        local = symcal.solve(PROBLEM, _local(fleet_dir, unit)).to_dict()
        got = made.results[unit].to_dict()
        assert got["solver"]["success"] and local["solver"]["success"]
        for mine, theirs in zip(got["parameters"], local["parameters"], strict=True):
            assert mine["name"] == theirs["name"]
            assert abs(mine["value"] - theirs["value"]) <= 1e-12, (unit, mine["name"])
            if theirs["se"] is None:
                assert mine["se"] is None
            else:
                assert abs(mine["se"] - theirs["se"]) <= 1e-12 * max(1.0, theirs["se"])
        assert got["information_criteria"]["rss"] == pytest.approx(
            local["information_criteria"]["rss"], rel=1e-12)


def test_a_units_document_is_what_json_gives_back(fleet) -> None:
    """A unit's document (made without writing JSON text) equals its result's
    ``symcal solve --json`` document read back, to the type; an odd document too."""
    from symcal.base.files import json_plain, json_text
    from symcal.calibrate.fleet import _document

    fleet_dir, _ = fleet
    local = symcal.solve(PROBLEM, _local(fleet_dir, "a_csv"))
    doc = _document(local)
    back = json.loads(json_text(local.to_dict()))
    assert doc == back
    assert json.dumps(doc, sort_keys=True) == json.dumps(back, sort_keys=True)
    odd = {2: (np.float64(2.5), float("nan")), True: {None: [float("-inf")]}, "a": 3}
    assert json_plain(odd) == json.loads(json.dumps(odd).replace("NaN", "null")
                                     .replace("-Infinity", "null"))
    assert type(json_plain(odd)["2"][0]) is float


@pytest.mark.slow
def test_units_recover_their_own_truth(result, fleet) -> None:
    _, truths = fleet
    for unit, k in truths.items():
        params = result.results[unit].params
        for i in range(4):
            for j in range(1, 9):
                p = params[f"s{i + 1}.k{j}"]
                assert abs(p.value - k[i, j]) < 4 * p.se, (unit, p.name)


@pytest.mark.slow
def test_failed_units_have_their_reason_and_stop_nobody(result, fleet) -> None:
    fleet_dir, _ = fleet
    broken = fleet_dir / BROKEN / "calibration.csv"
    assert result.errors[BROKEN] == f"{broken}:5: column 'p2': 'n/a' is not a number"
    assert result.errors[TYPO] == (
        f"{fleet_dir / TYPO / 'calibraton.csv'}: the problem has no dataset "
        "'calibraton' (did you mean 'calibration'?); its datasets: calibration, flyby")
    assert result.to_dict()["units"][BROKEN] == {"error": result.errors[BROKEN]}
    assert result.failed == {u: result.errors[u] for u in (BROKEN, TYPO)}
    assert not result.success
    assert result.summary["counts"] == {"units": 6, "solved": 4, "failed": 2, "outliers": 2}
    assert BROKEN not in result.results and TYPO not in result.results


@pytest.mark.slow
def test_outlier_units_are_named_with_their_reason(result) -> None:
    assert list(result.outliers) == ["b_npz", ODD]
    # b_npz has no fly-by of its own: the problem's, simulated from another courier,
    # does not fit its calibration: a residual outlier
    [flyby] = result.outliers["b_npz"]
    assert (flyby["kind"], flyby["name"], flyby["dataset"]) == ("residual", "g_p", "flyby")
    assert flyby["reason"].startswith("residual g_p on 'flyby': RMS ")
    assert flyby["value"] > 10 * flyby["median"]
    assert [f["name"] for f in result.outliers[ODD]] == ["s2.k1"]
    finding = next(f for f in result.outliers[ODD] if f["name"] == "s2.k1")
    # the score again, with numpy alone, from the units' documents
    solved = [*GOOD, ODD]
    values = np.array([result.results[u].params["s2.k1"].value for u in solved])
    ses = [result.results[u].params["s2.k1"].se for u in solved]
    median = np.median(values)
    spread = max(MAD_TO_SIGMA * np.median(np.abs(values - median)), np.median(ses))
    score = (result.results[ODD].params["s2.k1"].value - median) / spread
    assert finding["score"] == pytest.approx(score, rel=1e-12)
    assert score > OUTLIER_SCORE
    assert finding["reason"].startswith(f"parameter s2.k1 = {values[-1]:.4g} mm is ")
    dist = result.summary["parameters"]["s2.k1"]
    assert dist["median"] == pytest.approx(median, rel=1e-12)
    assert dist["values"] == {u: result.results[u].params["s2.k1"].value for u in solved}


@pytest.mark.slow
def test_cli_json_shape_and_outputs(fleet, client, tmp_path, capsys) -> None:
    fleet_dir, _ = fleet
    out = tmp_path / "res"
    code = main(["solve", str(PROBLEM), "--fleet", str(fleet_dir), "--scheduler",
                 client.scheduler.address, "--json", "--out", str(out)])
    assert code == 1  # two units failed; the others were solved and written
    doc = json.loads(capsys.readouterr().out)
    assert list(doc) == ["units", "summary"]
    assert list(doc["units"]) == sorted([*GOOD, ODD, BROKEN, TYPO])
    assert list(doc["summary"]) == ["problem", "counts", "failed", "outliers", "parameters",
                                    "residuals", "rules"]
    assert doc["units"][BROKEN].keys() == {"error"}
    # a unit's document is what `symcal solve --json` prints for that unit alone
    local = [a for name, path in _local(fleet_dir, "c_parquet").items()
             for a in ("--data", f"{name}={path}")]
    assert main(["solve", str(PROBLEM), *local, "--json"]) == 0
    alone = json.loads(capsys.readouterr().out)
    unit = doc["units"]["c_parquet"]
    for d in (alone, unit):
        d["solver"].pop("seconds")
        for st in d["stages"]:
            st.pop("seconds")
    assert unit == alone
    saved = json.loads((out / "fleet.json").read_text())
    assert saved["summary"] == doc["summary"]
    assert saved["units"][BROKEN] == doc["units"][BROKEN]
    assert (out / "fleet.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "Outlier units" in (out / "fleet.txt").read_text()
    loaded = symcal.Result.load(out / "a_csv" / "result.json")
    assert {n: p.value for n, p in loaded.params.items()} == result_params(doc, "a_csv")
    assert json.loads((out / BROKEN / "result.json").read_text()) == doc["units"][BROKEN]


def result_params(doc: dict, unit: str) -> dict[str, float]:
    return {p["name"]: p["value"] for p in doc["units"][unit]["parameters"]}


@pytest.mark.slow
def test_cli_exit_0_when_every_unit_solves(fleet, client, tmp_path, capsys) -> None:
    fleet_dir, _ = fleet
    small = tmp_path / "small"
    small.mkdir()
    (small / "a_csv").symlink_to(fleet_dir / "a_csv", target_is_directory=True)
    code = main(["solve", str(PROBLEM), "--fleet", str(small), "--scheduler",
                 client.scheduler.address])
    captured = capsys.readouterr()
    assert code == 0
    assert "1 unit(s): 1 solved, 0 failed, 0 outlier(s)" in captured.out
    assert "no outlier test: fewer than 3 units solved" in captured.out
    assert "fleet: 1/1 unit a_csv: solved" in captured.err  # stderr is no terminal: lines


# ------------------------------------------------------------------ fast: no cluster

def test_fleet_folder_errors(tmp_path: Path) -> None:
    problem = symcal.load_problem(PROBLEM)
    with pytest.raises(DataError, match="fleet folder .*missing: not found"):
        find_units(problem, tmp_path / "missing")
    with pytest.raises(DataError, match="no unit subfolder"):
        find_units(problem, tmp_path)
    (tmp_path / "u1").mkdir()
    write_csv(tmp_path / "u1" / "calibration.csv", {"t": np.arange(3.0)})
    write_table(tmp_path / "u1" / "calibration.npz", {"t": np.arange(3.0)})
    (tmp_path / "u2").mkdir()
    (tmp_path / "u2" / "notes.txt").write_text("not data")
    (tmp_path / ".hidden").mkdir()
    units = find_units(problem, tmp_path)
    assert [u.name for u in units] == ["u1", "u2"]
    assert units[0].error == (f"{tmp_path / 'u1'}: two files for dataset 'calibration' "
                              "(calibration.csv and calibration.npz); keep one")
    assert units[1].error is not None and units[1].error.endswith(
        "no data file; a unit folder holds NAME.csv, NAME.npz or NAME.parquet for datasets "
        "NAME of the problem (calibration, flyby)")


def test_cli_options_need_fleet(capsys) -> None:
    assert main(["solve", str(PROBLEM), "--scheduler", "tcp://127.0.0.1:1"]) == 2
    assert "--scheduler applies only with --fleet DIR" in capsys.readouterr().err


def test_cli_refuses_bad_fleet_input_before_any_work(tmp_path: Path, capsys) -> None:
    (tmp_path / "u1").mkdir()
    write_csv(tmp_path / "u1" / "calibration.csv", courier_data(20, np.zeros((4, 9)), NOISE, 1))
    args = ["solve", str(PROBLEM), "--fleet", str(tmp_path)]
    assert main([*args, "--out", str(tmp_path / "results")]) == 2
    assert ("a folder inside the fleet folder would be taken for a unit by the next run"
            in capsys.readouterr().err)
    assert not (tmp_path / "results").exists()
    assert main([*args, "--workers", "0"]) == 2
    assert "--workers 0: must be at least 1" in capsys.readouterr().err
    assert main(["solve", str(PROBLEM), "--fleet", str(tmp_path / "none"), "--json"]) == 2
    doc = json.loads(capsys.readouterr().out)
    assert doc == {"error": {"message": f"fleet folder {tmp_path / 'none'}: not found",
                             "exit_code": 2}}


def test_parquet_npz_and_csv_read_the_same_table(tmp_path: Path) -> None:
    cols = courier_data(50, np.zeros((4, 9)), NOISE, 3)
    read = {suffix: read_table(_write(tmp_path / f"d.{suffix}", cols))
            for suffix in ("csv", "npz", "parquet")}
    for suffix, got in read.items():
        assert list(got) == list(cols), suffix
        for name, values in cols.items():  # binary formats exact; CSV has 15 digits
            np.testing.assert_allclose(got[name], values, atol=0,
                                       rtol=1e-14 if suffix == "csv" else 0)


def test_parquet_refusals(tmp_path: Path) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    pq.write_table(pa.table({"t": [1.0, 2.0], "name": ["a", "b"]}), tmp_path / "s.parquet")
    with pytest.raises(DataError, match=r"s\.parquet: column 'name' holds string values"):
        read_table(tmp_path / "s.parquet")
    (tmp_path / "x.parquet").write_text("t,p\n1,2\n")
    with pytest.raises(DataError, match=r"x\.parquet: not a Parquet file \(no PAR1"):
        read_table(tmp_path / "x.parquet")
    pq.write_table(pa.table({"t": [1.0, None]}), tmp_path / "n.parquet")
    assert np.isnan(read_table(tmp_path / "n.parquet")["t"][1])


def _doc(name: str, values: dict[str, float], rms: float, se: float = 1e-3) -> dict:
    return {"problem": "p", "solver": {"success": True}, "stages": [],
            "parameters": [{"name": k, "value": v, "se": se, "unit": "mm", "fixed": False}
                           for k, v in values.items()],
            "statistics": [{"name": "g", "kind": "constraint", "dataset": "calibration",
                            "unit": "um", "after": {"rms": rms}}]}


def test_summary_against_numpy() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(1.0, 0.01, 8)
    units = {f"u{i}": _doc(f"u{i}", {"a": float(x), "b": 2.0}, 3.0 + 0.01 * i)
             for i, x in enumerate(a)}
    units["u3"]["parameters"][0]["value"] = 1.5          # far off in a
    units["u5"]["statistics"][0]["after"]["rms"] = 9.0   # fits much worse
    units["u7"] = {"error": "broken"}
    units["u6"]["solver"]["success"] = False
    units["u6"]["stages"] = [{"name": "s", "success": False, "message": "diverged"}]
    s = summarise(units)
    assert s["failed"] == {"u6": "stage 's' failed: diverged", "u7": "broken"}
    assert s["counts"] == {"units": 8, "solved": 6, "failed": 2, "outliers": 2}
    solved = [u for u in units if u not in ("u6", "u7")]
    vals = np.array([units[u]["parameters"][0]["value"] for u in solved])
    med = np.median(vals)
    spread = max(1.4826 * np.median(np.abs(vals - med)), 1e-3)
    assert s["parameters"]["a"]["median"] == med
    assert s["outliers"]["u3"][0]["score"] == pytest.approx((1.5 - med) / spread)
    assert s["outliers"]["u5"][0]["kind"] == "residual"
    assert s["outliers"]["u5"][0]["reason"].startswith("residual g on 'calibration': RMS 9 µm")
    # b is the same everywhere: spread is the standard error, nobody is flagged on it
    assert s["parameters"]["b"]["spread"] == 0.0
    assert all(f["name"] != "b" for fs in s["outliers"].values() for f in fs)


# ------------------------------------------------------------------ progress and start-up

class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_bars_only_on_a_terminal() -> None:
    assert terminal_bars(io.StringIO()) is None
    with meter(None, "fleet", 3) as m:   # no bars: silent, and nothing to close
        m.advance()
    screen = _Terminal()
    bars = terminal_bars(screen)
    assert bars is not None
    with meter(bars, "fleet", total=3, unit="unit") as m:
        for _ in range(3):
            m.advance()
        m.note("failed=1")
        write_line("a line above the bar", screen)
    text = screen.getvalue()
    assert "fleet" in text and "3/3" in text and "a line above the bar" in text


def test_quiet_means_no_bars() -> None:
    import argparse

    from symcal.cli.common import progress_bars

    assert progress_bars(argparse.Namespace(quiet=True)) is None


def test_dask_and_tqdm_are_not_imported_up_front() -> None:
    code = ("import sys, symcal, symcal.cli; symcal.cli._parser(); "
            "print(sorted({m.split('.')[0] for m in sys.modules} & "
            "{'dask', 'distributed', 'tqdm', 'pyarrow'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "[]"


def test_units_are_sent_in_balanced_contiguous_batches() -> None:
    from symcal.calibrate.fleet import BATCHES_PER_WORKER, batches

    names = [f"u{i}" for i in range(203)]
    groups = batches(names, 2)
    assert len(groups) == 2 * BATCHES_PER_WORKER
    assert [u for g in groups for u in g] == names            # every unit once, in order
    assert max(map(len, groups)) - min(map(len, groups)) <= 1
    assert batches(names[:3], 2) == [["u0"], ["u1"], ["u2"]]  # never an empty batch
