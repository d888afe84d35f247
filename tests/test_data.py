"""The data contract: reading, checking and writing tables (exact messages)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from symcal.base.errors import DataError
from symcal.data.dataset import Table, make_dataset, read_table, write_table


def _csv(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "d.csv"
    path.write_text(text)
    return path


def test_reads_header_and_rows(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    cols = read_table(_csv(tmp_path, "t, p1,p2\n0,1.5,2e-3\n1,-1,3\n"))
    assert list(cols) == ["t", "p1", "p2"]
    np.testing.assert_array_equal(cols["p2"], [2e-3, 3])


@pytest.mark.parametrize(("text", "message"), [
    ("", "d.csv: empty file (expected a header row naming the columns)"),
    ("t,p1\n", "d.csv: no observations (the file has a header but no rows)"),
    ("t,p1\n0,1\n1,abc\n", "d.csv:3: column 'p1': 'abc' is not a number"),
    ("t,p1\n0,1\n1,2,3\n", "d.csv:3: row has 3 fields, the header has 2"),
    ("t,t\n0,1\n", "d.csv:1: column 't' appears twice in the header"),
])
def test_malformed_files(tmp_path, monkeypatch, text, message) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(DataError) as err:
        read_table(_csv(tmp_path, text))
    assert str(err.value) == message


def test_missing_file(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(DataError, match="^nope.csv: data file not found$"):
        read_table("nope.csv")


def test_missing_column_suggests() -> None:
    cols = {"t": np.zeros(2), "p_1": np.zeros(2)}
    with pytest.raises(DataError) as err:
        make_dataset("calibration", "d.csv", cols, ["p1"])
    assert str(err.value) == ("d.csv: missing column 'p1' (did you mean 'p_1'?); "
                              "the file has: t, p_1")


def test_non_finite_rows_refused_or_dropped() -> None:
    cols = {"p1": np.array([1.0, np.nan, 3.0, np.inf]), "x_ref": np.array([np.nan] * 4)}
    with pytest.raises(DataError) as err:
        make_dataset("calibration", "d.csv", cols, ["p1"])
    assert str(err.value) == ("d.csv: 2 row(s) with NaN or inf in a needed column (rows 2, 4); "
                              "fix them or pass --drop-invalid to drop them")
    with pytest.raises(DataError) as err:   # read from a CSV file: its lines
        make_dataset("calibration", "d.csv", Table(cols, "line"), ["p1"])
    assert "(lines 3, 5)" in str(err.value)
    ds = make_dataset("calibration", "d.csv", cols, ["p1"], drop_invalid=True)
    assert ds.dropped == 2 and ds.n == 2
    np.testing.assert_array_equal(ds.columns["p1"], [1.0, 3.0])


def test_dataset_is_read_only() -> None:
    ds = make_dataset("c", "s", {"p1": np.arange(3.0)}, ["p1"])
    with pytest.raises(ValueError):
        ds.columns["p1"][0] = 5.0
    np.testing.assert_array_equal(ds.matrix(["p1", "zz"])[1], [np.nan] * 3)


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
def test_write_read_round_trip(tmp_path, suffix) -> None:
    rng = np.random.default_rng(0)
    cols = {"t": np.arange(5.0), "p1": rng.normal(size=5) * 1e-3 + 10.0}
    path = tmp_path / f"out{suffix}"
    write_table(path, cols)
    back = read_table(path)
    assert list(back) == ["t", "p1"]
    np.testing.assert_allclose(back["p1"], cols["p1"], rtol=1e-14)
    assert not list(tmp_path.glob(".*tmp*")), "temporary file left behind"


def test_npz_headers_are_parsed_one_at_a_time(tmp_path, monkeypatch) -> None:
    """numpy parses a .npy header with ``ast.literal_eval``, whose state CPython 3.11's
    threads share (a log's shards read on two threads failed at random with "AST
    constructor recursion depth mismatch"): two threads reading NPZ files never parse
    headers at the same time."""
    import ast
    import threading
    import time
    from concurrent.futures import ThreadPoolExecutor

    files = []
    for k in range(6):
        path = tmp_path / f"shard{k}.npz"
        np.savez(path, x=np.arange(5.0) + k, y=np.ones(5))
        files.append(path)
    inside, most = [0], [0]
    lock = threading.Lock()
    original = ast.literal_eval

    def slow(text):           # holds the parse long enough for another thread to enter
        with lock:
            inside[0] += 1
            most[0] = max(most[0], inside[0])
        time.sleep(0.01)
        try:
            return original(text)
        finally:
            with lock:
                inside[0] -= 1

    monkeypatch.setattr(ast, "literal_eval", slow)
    from symcal.data.shards import _rows_npz

    with ThreadPoolExecutor(2) as pool:     # reading shards while others are opened
        tables = list(pool.map(read_table, files))
        rows = list(pool.map(lambda p: _rows_npz(p, p.name), files))
        mixed = list(pool.map(lambda k: read_table(files[k]) if k % 2 else
                              _rows_npz(files[k], "s"), range(6)))
    assert [float(t["x"][0]) for t in tables] == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    assert rows == [5] * 6 and mixed[0] == 5 and float(mixed[1]["x"][0]) == 1.0
    assert most[0] == 1


def test_a_column_view_reads_blocks_of_the_matrix() -> None:
    """A pass reads a dataset's columns block by block (``view[:, part]``): the same
    values as the whole matrix's block, NaN for an absent column, a fresh C-ordered
    array of that block alone."""
    rng = np.random.default_rng(3)
    cols = {"a": rng.normal(size=1000), "b": rng.normal(size=1000), "t": np.arange(1000.0)}
    ds = make_dataset("calibration", "memory", cols, ("a", "b", "t"))
    names = ("b", "missing", "a")
    view, whole = ds.columns_view(names), ds.matrix(names)
    assert view.shape == whole.shape == (3, 1000)
    for part in (slice(0, 1000), slice(0, 1), slice(512, 1000), slice(999, 1000),
                 slice(40, 40), slice(0, 1000, 7)):
        block = view[:, part]
        np.testing.assert_array_equal(block, whole[:, part])     # NaN where NaN
        assert block.flags.c_contiguous and block.shape == whole[:, part].shape
        assert not np.shares_memory(block, ds.columns["a"])
    assert np.isnan(view[:, 0:5][1]).all()
    for key in (0, (0, slice(0, 5)), (slice(None), 3)):
        with pytest.raises(TypeError, match=r"read as view\[:, start:stop\]"):
            view[key]  # type: ignore[index]
