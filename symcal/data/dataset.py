"""Datasets: CSV/NPZ reading and writing, column checks.

A dataset is a table with one row per observation and named numeric columns (the data
contract in the README).  Loading checks what a person would otherwise discover late:
missing columns (with did-you-mean), non-numeric cells and non-finite values, by row.
"""

from __future__ import annotations

import csv
import io
import warnings
import zipfile
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import DataError, excerpt
from symcal.base.files import atomic_write_bytes, atomic_write_text, display_path, input_refusal


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


def _freeze(columns: dict[str, np.ndarray], copy: bool = True) -> dict[str, np.ndarray]:
    out = {}
    for k, v in columns.items():
        arr = np.array(v, dtype=float) if copy else np.asarray(v, dtype=float)
        arr.setflags(write=False)
        out[k] = arr
    return out


#: Bytes read from a CSV file at a time (whole lines of it are parsed together).
BLOCK_BYTES = 1 << 22
#: Longest line accepted in a CSV file, in bytes.
MAX_LINE_BYTES = 1 << 20
#: Longest excerpt of a cell or column name quoted in a message.
CELL_CHARS = 24
#: Most column names a message lists.
MAX_LISTED = 20
#: Magic bytes of formats that are not CSV text, and what to say about them.
_NOT_CSV = ((b"\x1f\x8b", "is gzip-compressed; decompress it first"),
            (b"PK\x03\x04", "is a zip archive; an NPZ file needs the suffix .npz"),
            (b"\x93NUMPY", "is a NumPy .npy file; save the columns with numpy.savez as .npz"),
            (b"PAR1", "is a Parquet file; a Parquet dataset needs the suffix .parquet"))


def _name(text: str) -> str:
    """A column name or cell as quoted in messages: short and escaped."""
    return excerpt(text.strip(), CELL_CHARS)


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return "_" not in cell


def _bad_lines(shown: str, header: list[str], lines: list[str], first: int) -> DataError:
    """Locate the first malformed row or cell of ``lines`` (line ``first`` onwards)."""
    for lineno, line in enumerate(lines, start=first):
        if not line.strip():
            continue
        row = next(csv.reader([line]))
        if len(row) != len(header):
            return DataError(f"{shown}:{lineno}: row has {len(row)} fields, "
                             f"the header has {len(header)}")
        for name, cell in zip(header, row, strict=True):
            if not _is_number(cell):
                return DataError(f"{shown}:{lineno}: column '{_name(name)}': "
                                 f"'{_name(cell)}' is not a number")
    return DataError(f"{shown}: could not be read as a numeric CSV table")


def _decode(block: bytes, shown: str, lineno: int) -> str:
    """UTF-8 text of a block of whole lines starting at line ``lineno``."""
    try:
        return block.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = lineno + block.count(b"\n", 0, exc.start)
        column = exc.start - (block.rfind(b"\n", 0, exc.start) + 1) + 1
        raise DataError(f"{shown}:{line}: not UTF-8 text (byte 0x{block[exc.start]:02x} at "
                        f"column {column}); a dataset is CSV text or an NPZ file") from None


def _blocks(fh: BinaryIO, shown: str) -> Iterator[tuple[int, list[str]]]:
    """(number of the first line, lines) of a CSV file, a few MiB of whole lines at a time."""
    lineno, rest = 1, b""
    while True:
        data = fh.read(BLOCK_BYTES)
        if not data:
            break
        data = rest + data
        cut = data.rfind(b"\n") + 1
        if len(data) - cut > MAX_LINE_BYTES:
            line = lineno + data.count(b"\n", 0, cut)
            raise DataError(f"{shown}:{line}: a line is longer than {MAX_LINE_BYTES} bytes; "
                            "this is not a CSV table")
        block, rest = data[:cut], data[cut:]
        if block:
            text = _decode(block, shown, lineno)
            yield lineno, text.replace("\r\n", "\n").split("\n")[:-1]
            lineno += block.count(b"\n")
    if rest:
        yield lineno, [_decode(rest, shown, lineno).rstrip("\r")]


def _refuse_comments(shown: str, lines: list[str], first: int) -> None:
    """Data files have no comment lines: refuse a line that starts with ``#``."""
    if "#" not in "".join(lines):
        return
    for lineno, line in enumerate(lines, start=first):
        if line.lstrip().startswith("#"):
            raise DataError(f"{shown}:{lineno}: the line starts with '#': data files have no "
                            "comment lines (the first line is the header, every other line "
                            "an observation); remove it")


def _loadtxt(lines: list[str]) -> np.ndarray:
    return np.loadtxt(lines, delimiter=",", ndmin=2, dtype=float, comments=None,
                      quotechar='"')


def _parse_lines(shown: str, header: list[str], lines: list[str], first: int) -> np.ndarray:
    """The numbers of data lines (line ``first`` onwards) as rows × columns; blank lines
    are skipped."""
    _refuse_comments(shown, lines, first)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "input contained no data"
        try:
            values = _loadtxt(lines)
        except ValueError:
            kept = [line for line in lines if line.strip()]
            if len(kept) == len(lines):
                raise _bad_lines(shown, header, lines, first) from None
            try:
                values = _loadtxt(kept) if kept else np.empty((0, len(header)))
            except ValueError:
                raise _bad_lines(shown, header, lines, first) from None
    if values.size == 0 and not any(line.strip() for line in lines):
        return np.empty((0, len(header)))
    if values.shape[1] != len(header):
        raise _bad_lines(shown, header, lines, first)
    return values


def _count_lines(path: Path) -> int:
    """Lines of a file (a last line without newline counts), read in blocks."""
    count, last = 0, b"\n"
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(BLOCK_BYTES), b""):
            count += block.count(b"\n")
            last = block[-1:]
    return count + (last != b"\n")


def _header(shown: str, line: str) -> list[str]:
    if not line.strip():
        raise DataError(f"{shown}: empty file (expected a header row naming the columns)")
    if line.lstrip().startswith("#"):
        raise DataError(f"{shown}:1: the line starts with '#': data files have no comment "
                        "lines (the first line is the header, naming the columns); remove "
                        "the '#'")
    header = [h.strip() for h in next(csv.reader([line]))]
    if len(set(header)) != len(header):
        dup = next(h for h in header if header.count(h) > 1)
        raise DataError(f"{shown}:1: column '{_name(dup)}' appears twice in the header")
    if any(not h for h in header):
        raise DataError(f"{shown}:1: the header has an empty column name")
    return header


def _read_csv(path: Path, shown: str) -> dict[str, np.ndarray]:
    """Stream a CSV file into one preallocated (columns × rows) array, a block at a time."""
    with open(path, "rb") as fh:
        head = fh.read(8192)
    for magic, words in _NOT_CSV:
        if head.startswith(magic):
            raise DataError(f"{shown}: the file {words}; a dataset is CSV text or an NPZ file")
    if b"\0" in head:
        raise DataError(f"{shown}: a binary file, not CSV text; a dataset is CSV text or an "
                        "NPZ file")
    rows = max(_count_lines(path) - 1, 0)
    header: list[str] | None = None
    out: np.ndarray | None = None
    filled = 0
    with open(path, "rb") as fh:
        for first, lines in _blocks(fh, shown):
            if header is None:
                header = _header(shown, lines[0].removeprefix("\ufeff"))
                out = np.empty((len(header), rows))
                first, lines = first + 1, lines[1:]
            assert out is not None
            values = _parse_lines(shown, header, lines, first) if lines else np.empty((0, 0))
            if filled + len(values) > rows:
                raise DataError(f"{shown}: the file changed while it was read")
            if len(values):
                out[:, filled:filled + len(values)] = values.T
                filled += len(values)
    if header is None or out is None:
        raise DataError(f"{shown}: empty file (expected a header row naming the columns)")
    if filled == 0:
        raise DataError(f"{shown}: no observations (the file has a header but no rows)")
    if filled < rows:
        out = out[:, :filled].copy() if filled < 0.9 * rows else out[:, :filled]
    return {name: out[i] for i, name in enumerate(header)}


def _read_npz(path: Path, shown: str) -> dict[str, np.ndarray]:
    """The arrays of an NPZ file: 1-D real numbers, all of one length."""
    with open(path, "rb") as fh:
        head = fh.read(4)
    if head not in (b"PK\x03\x04", b"PK\x05\x06"):
        raise DataError(f"{shown}: not an NPZ file (no zip signature); write one with "
                        "numpy.savez")
    columns: dict[str, np.ndarray] = {}
    try:
        with np.load(path, allow_pickle=False) as npz:
            for key in npz.files:
                columns[key] = _npz_column(shown, key, npz, columns)
    except DataError:
        raise
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, KeyError) as exc:
        reason = excerpt(exc, 80)
        raise DataError(f"{shown}: not a readable NPZ file ({reason})") from None
    lengths = {len(v) for v in columns.values()}
    if len(lengths) > 1:
        raise DataError(f"{shown}: arrays have different lengths {sorted(lengths)}")
    return columns


def _npz_column(shown: str, key: str, npz: Any, columns: dict[str, np.ndarray]) -> np.ndarray:
    name = _name(key)
    try:
        arr = npz[key]
    except ValueError as exc:
        if "allow_pickle" in str(exc):
            raise DataError(f"{shown}: array '{name}' holds Python objects; a dataset's arrays "
                            "hold numbers") from None
        raise
    if arr.ndim != 1:
        raise DataError(f"{shown}: array '{name}' has shape {arr.shape}; every array must be "
                        "1-D, one value per observation (one array per column)")
    if arr.dtype.kind not in "fiu":
        raise DataError(f"{shown}: array '{name}' holds {arr.dtype} values; every array must "
                        "hold real numbers (float or integer)")
    return np.asarray(arr, dtype=float)


#: The first (and last) bytes of a Parquet file.
_PARQUET_MAGIC = b"PAR1"


def _read_parquet(path: Path, shown: str) -> dict[str, np.ndarray]:
    """The columns of a single Parquet file (pyarrow): flat real numbers, nulls as NaN."""
    with open(path, "rb") as fh:
        head = fh.read(4)
    if head != _PARQUET_MAGIC:
        raise DataError(f"{shown}: not a Parquet file (no PAR1 signature); write one with "
                        "pyarrow.parquet.write_table")
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        table = pq.read_table(path)
    except (pa.ArrowException, OSError, ValueError) as exc:
        raise DataError(f"{shown}: not a readable Parquet file ({excerpt(exc, 80)})") from None
    columns: dict[str, np.ndarray] = {}
    for field in table.schema:
        name = _name(field.name)
        if field.name in columns:
            raise DataError(f"{shown}: column '{name}' appears twice")
        kind = field.type
        if not (pa.types.is_integer(kind) or pa.types.is_floating(kind)):
            raise DataError(f"{shown}: column '{name}' holds {kind} values; every column "
                            "must hold real numbers (float or integer)")
        column = table.column(field.name).cast(pa.float64())
        if column.null_count:  # a null is a missing value: NaN, refused or dropped later
            column = column.fill_null(float("nan"))
        columns[field.name] = np.asarray(column.to_numpy(), dtype=float)
    if not columns:
        raise DataError(f"{shown}: the Parquet file has no columns")
    return columns


def read_table(path: str | Path) -> dict[str, np.ndarray]:
    """Read a CSV (header row, one row per observation), NPZ or Parquet file into columns.

    A CSV file is read in blocks of whole lines into one array sized from a first count
    of its lines, so memory stays near the size of the numbers themselves.  Blank lines
    are skipped; a line starting with ``#`` is refused (data files have no comments).
    An NPZ file must hold 1-D arrays of real numbers, all of one length.  A ``.parquet``
    file (one file, read with pyarrow) must hold columns of real numbers; its nulls
    become NaN, refused or dropped like any invalid value.

    Raises
    ------
    DataError
        If the file is missing, not a regular file, empty, compressed, binary, not UTF-8,
        malformed or has a non-numeric cell (naming the line and column), an NPZ
        file's arrays are not 1-D real numbers of one length, or a Parquet file is not
        readable or has a column that is not real numbers.
    """
    path = Path(path)
    shown = display_path(path)
    if not path.exists():
        raise DataError(f"{shown}: data file not found")
    reason = input_refusal(path)
    if reason is not None:
        raise DataError(f"{shown}: cannot read the data file: it {reason}")
    try:
        if path.suffix.lower() == ".npz":
            return _read_npz(path, shown)
        if path.suffix.lower() == ".parquet":
            return _read_parquet(path, shown)
        return _read_csv(path, shown)
    except OSError as exc:
        raise DataError(f"{shown}: cannot read the data file: "
                        f"{exc.strerror or exc.__class__.__name__}") from None


def make_dataset(
    name: str,
    source: str,
    columns: Mapping[str, np.ndarray],
    needed: Iterable[str],
    drop_invalid: bool = False,
    copy: bool = True,
) -> Dataset:
    """Check a table against the columns a problem needs and wrap it as a :class:`Dataset`.

    Parameters
    ----------
    needed
        Columns that must be present and finite (those the constraints read).
    drop_invalid
        Drop rows with NaN or inf in a needed column instead of refusing them.
    copy
        Copy the columns (default).  False adopts float arrays as they are and makes them
        read-only: for tables nobody else holds, such as :func:`read_table`'s.

    Raises
    ------
    DataError
        On a missing column (with did-you-mean), an empty table, or non-finite values.
    """
    needed = list(needed)
    for col in needed:
        if col not in columns:
            names = [_name(c) for c in list(columns)[:MAX_LISTED]]
            more = f" and {len(columns) - MAX_LISTED} more" if len(columns) > MAX_LISTED else ""
            raise DataError(
                f"{source}: missing column '{col}'{did_you_mean(col, columns)}; "
                f"the file has: {', '.join(names)}{more}"
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
    return Dataset(name, source, _freeze(dict(columns), copy and not dropped), dropped)


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
