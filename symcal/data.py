"""Datasets: CSV/NPZ reading and writing, column checks.

A dataset is a table with one row per observation and named numeric columns (the data
contract in the README).  Loading checks what a person would otherwise discover late:
missing columns (with did-you-mean), non-numeric cells and non-finite values, by row.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from symcal.errors import DataError
from symcal.files import atomic_write_bytes, atomic_write_text
from symcal.language.yamlio import display_path
from symcal.suggest import did_you_mean


@dataclass(frozen=True, eq=False)
class Dataset:
    """A named table of observations.

    Attributes
    ----------
    name
        The dataset's role in the problem (``calibration``, ``flyby``, ...).
    source
        Where it came from, for reports.
    columns
        Column name → read-only 1-D float array, all of the same length.
    dropped
        How many rows were dropped as invalid (``drop_invalid``).
    """

    name: str
    source: str
    columns: Mapping[str, np.ndarray]
    dropped: int = 0

    @property
    def n(self) -> int:
        """Number of observations."""
        return len(next(iter(self.columns.values()))) if self.columns else 0

    def matrix(self, names: Iterable[str]) -> np.ndarray:
        """Columns ``names`` stacked as rows (shape ``len(names) × n``); NaN where absent."""
        names = list(names)
        out = np.full((len(names), self.n), np.nan)
        for i, name in enumerate(names):
            if name in self.columns:
                out[i] = self.columns[name]
        return out


def _freeze(columns: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    out = {}
    for k, v in columns.items():
        arr = np.array(v, dtype=float)
        arr.setflags(write=False)
        out[k] = arr
    return out


def _find_bad_cell(path: Path, text: str) -> DataError:
    """Locate the first malformed row or cell (slow path, only after a failed fast read)."""
    shown = display_path(path)
    reader = csv.reader(io.StringIO(text))
    header = next(reader)
    for lineno, row in enumerate(reader, start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            return DataError(f"{shown}:{lineno}: row has {len(row)} fields, "
                             f"the header has {len(header)}")
        for name, cell in zip(header, row, strict=True):
            try:
                float(cell)
            except ValueError:
                return DataError(f"{shown}:{lineno}: column '{name.strip()}': "
                                 f"'{cell.strip()}' is not a number")
    return DataError(f"{shown}: could not be read as a numeric CSV table")


def read_table(path: str | Path) -> dict[str, np.ndarray]:
    """Read a CSV (header row, one row per observation) or NPZ file into columns.

    Raises
    ------
    DataError
        If the file is missing, empty, malformed or has a non-numeric cell (naming the line
        and column).
    """
    path = Path(path)
    shown = display_path(path)
    if not path.is_file():
        raise DataError(f"{shown}: data file not found")
    if path.suffix.lower() == ".npz":
        with np.load(path, allow_pickle=False) as npz:
            columns = {k: np.asarray(npz[k], dtype=float).ravel() for k in npz.files}
        lengths = {len(v) for v in columns.values()}
        if len(lengths) > 1:
            raise DataError(f"{shown}: arrays have different lengths {sorted(lengths)}")
        return columns
    text = path.read_text(encoding="utf-8-sig")
    lines = text.splitlines()
    if not lines or not lines[0].strip():
        raise DataError(f"{shown}: empty file (expected a header row naming the columns)")
    header = [h.strip() for h in next(csv.reader([lines[0]]))]
    if len(set(header)) != len(header):
        dup = next(h for h in header if header.count(h) > 1)
        raise DataError(f"{shown}:1: column '{dup}' appears twice in the header")
    if any(not h for h in header):
        raise DataError(f"{shown}:1: the header has an empty column name")
    if not any(line.strip() for line in lines[1:]):
        raise DataError(f"{shown}: no observations (the file has a header but no rows)")
    try:
        values = np.loadtxt(io.StringIO(text), delimiter=",", skiprows=1, ndmin=2, dtype=float)
    except ValueError:
        raise _find_bad_cell(path, text) from None
    if values.shape[1] != len(header):
        raise _find_bad_cell(path, text)
    return {name: values[:, i] for i, name in enumerate(header)}


def make_dataset(
    name: str,
    source: str,
    columns: Mapping[str, np.ndarray],
    needed: Iterable[str],
    drop_invalid: bool = False,
) -> Dataset:
    """Check a table against the columns a problem needs and wrap it as a :class:`Dataset`.

    Parameters
    ----------
    needed
        Columns that must be present and finite (those the constraints read).
    drop_invalid
        Drop rows with NaN or inf in a needed column instead of refusing them.

    Raises
    ------
    DataError
        On a missing column (with did-you-mean), an empty table, or non-finite values.
    """
    needed = list(needed)
    for col in needed:
        if col not in columns:
            raise DataError(
                f"{source}: missing column '{col}'{did_you_mean(col, columns)}; "
                f"the file has: {', '.join(columns)}"
            )
    n = len(next(iter(columns.values()))) if columns else 0
    if n == 0:
        raise DataError(f"{source}: no observations")
    bad = np.zeros(n, dtype=bool)
    for col in needed:
        bad |= ~np.isfinite(np.asarray(columns[col], dtype=float))
    dropped = 0
    if bad.any():
        if not drop_invalid:
            rows = np.flatnonzero(bad)
            shown = ", ".join(str(r + 2) for r in rows[:5]) + (", ..." if len(rows) > 5 else "")
            which = f"line {shown}" if len(rows) == 1 else f"lines {shown}"
            raise DataError(f"{source}: {len(rows)} row(s) with NaN or inf in a needed column "
                            f"({which}); fix them or pass --drop-invalid to drop them")
        columns = {k: np.asarray(v)[~bad] for k, v in columns.items()}
        dropped = int(bad.sum())
        if dropped == n:
            raise DataError(f"{source}: every row has NaN or inf in a needed column")
    return Dataset(name, source, _freeze(dict(columns)), dropped)


def write_table(path: str | Path, columns: Mapping[str, np.ndarray]) -> None:
    """Write columns as CSV (or NPZ for a ``.npz`` path), atomically."""
    path = Path(path)
    names = list(columns)
    table = np.column_stack([np.asarray(columns[k], dtype=float) for k in names])
    if path.suffix.lower() == ".npz":
        binary = io.BytesIO()
        arrays: dict[str, Any] = {k: np.asarray(columns[k], dtype=float) for k in names}
        np.savez(binary, **arrays)
        atomic_write_bytes(path, binary.getvalue())
        return
    text = io.StringIO()
    text.write(",".join(names) + "\n")
    np.savetxt(text, table, delimiter=",", fmt="%.15g")
    atomic_write_text(path, text.getvalue())
