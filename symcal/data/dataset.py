"""Datasets: CSV/NPZ reading and writing, column checks.

A dataset is a table with one row per observation and named numeric columns (the data
contract in the README).  Loading checks what a person would otherwise discover late:
missing columns (with did-you-mean), non-numeric cells and non-finite values, by row.
"""

from __future__ import annotations

import csv
import io
import os
import warnings
import zipfile
import zlib
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, BinaryIO

import numpy as np

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import DataError, excerpt
from symcal.base.files import atomic_write_bytes, atomic_write_text, display_path, input_refusal
from symcal.base.forks import ForkLock


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
        """Columns ``names`` stacked as rows (shape ``len(names) × n``); NaN where absent
        (the whole of :meth:`columns_view`)."""
        return self.columns_view(names)[:, :]

    def columns_view(self, names: Iterable[str]) -> ColumnView:
        """:meth:`matrix`'s rows of observations as a pass reads them, ``view[:, part]``,
        without forming the whole matrix (see :class:`ColumnView`)."""
        return ColumnView(self, tuple(names))


@dataclass(frozen=True)
class ColumnView:
    """A dataset's columns ``names`` as :meth:`Dataset.matrix` would stack them, read a
    block of observations at a time: ``view[:, part]`` is ``matrix(names)[:, part]``
    (the same values, NaN where a column is absent) made for that block alone.

    A pass over the data evaluates it chunk by chunk, so it never needs the whole
    ``len(names) × N`` copy that :meth:`Dataset.matrix` makes (61 MiB for the dual
    problem's eight columns at N = 1e6, at every pass)."""

    data: Dataset
    names: tuple[str, ...]

    @property
    def shape(self) -> tuple[int, int]:
        """``(len(names), N)``, as the matrix's."""
        return len(self.names), self.data.n

    def __getitem__(self, key: tuple[slice, slice]) -> np.ndarray:
        if not (isinstance(key, tuple) and len(key) == 2 and key[0] == slice(None)
                and isinstance(key[1], slice)):
            raise TypeError("a ColumnView is read as view[:, start:stop]")
        part = key[1]
        start, stop, step = part.indices(self.data.n)
        out = np.empty((len(self.names), len(range(start, stop, step))))
        for i, name in enumerate(self.names):
            column = self.data.columns.get(name)
            out[i] = np.nan if column is None else column[part]
        return out


class Table(dict):
    """Columns read from a file (name → 1-D float array), with where each row came from.

    Attributes
    ----------
    unit
        How a row is named in messages: ``"line"`` (CSV) or ``"row"`` (NPZ, Parquet,
        columns given in Python: counted from 1).
    lines
        For a CSV file, the line of each row when blank lines were skipped; None when
        row ``r`` (from 0) is on line ``r + 2``.
    """

    def __init__(self, columns: Mapping[str, np.ndarray], unit: str = "row",
                 lines: np.ndarray | None = None) -> None:
        super().__init__(columns)
        self.unit = unit
        self.lines = lines


def rows_text(columns: Mapping[str, np.ndarray], rows: np.ndarray) -> str:
    """Where rows ``rows`` (from 0) of ``columns`` are, in words: ``line 8`` or
    ``lines 3, 5, ...`` for a CSV file, ``rows 4, 7`` (from 1) otherwise; at most five."""
    unit = getattr(columns, "unit", "row")
    lines = getattr(columns, "lines", None)
    first = np.asarray(rows[:5], dtype=int)
    numbers = (first + 1 if unit != "line" else first + 2 if lines is None else lines[first])
    shown = ", ".join(str(int(k)) for k in numbers) + (", ..." if len(rows) > 5 else "")
    return f"{unit}{'' if len(rows) == 1 else 's'} {shown}"


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
    """Whether numpy reads ``cell`` as a number (Python's ``float`` also takes ``1_0``
    and the digits of other scripts, such as Arabic-Indic ones; numpy does not)."""
    try:
        float(cell)
    except ValueError:
        return False
    return "_" not in cell and cell.isascii()


def _why_not(cell: str) -> str:
    """What to add to "is not a number" about ``cell``."""
    if not cell.isascii() and any(ch.isdigit() for ch in cell):
        return " (a number is written with the ASCII digits 0-9)"
    return ""


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
                                 f"'{_name(cell)}' is not a number{_why_not(cell)}")
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


def _blocks(fh: BinaryIO, shown: str, cr_only: bool = False
            ) -> Iterator[tuple[int, list[str]]]:
    """(number of the first line, lines) of a CSV file, a few MiB of whole lines at a time.

    Lines end with LF or CRLF, or, in a file whose lines all end with CR alone
    (``cr_only``), with CR; a CR alone inside a file of LF lines is refused.
    """
    lineno, rest = 1, b""
    while True:
        data = fh.read(BLOCK_BYTES)
        if not data:
            break
        if cr_only:
            data = data.replace(b"\r", b"\n")
        data = rest + data
        cut = data.rfind(b"\n") + 1
        if len(data) - cut > MAX_LINE_BYTES:
            line = lineno + data.count(b"\n", 0, cut)
            raise DataError(f"{shown}:{line}: a line is longer than {MAX_LINE_BYTES} bytes; "
                            "this is not a CSV table")
        block, rest = data[:cut], data[cut:]
        if block:
            text = _decode(block, shown, lineno).replace("\r\n", "\n")
            if "\r" in text:
                _lone_cr(shown, text, lineno)
            yield lineno, text.split("\n")[:-1]
            lineno += block.count(b"\n")
    if rest:
        text = _decode(rest, shown, lineno).removesuffix("\r")
        if "\r" in text:
            _lone_cr(shown, text, lineno)
        yield lineno, [text]


def _lone_cr(shown: str, text: str, first: int) -> None:
    """Refuse a carriage return that does not end a line of a file of LF lines."""
    line = first + text.count("\n", 0, text.index("\r"))
    raise DataError(f"{shown}:{line}: a carriage return (CR) inside a line; a line ends with "
                    "LF, CRLF, or CR throughout the file")


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


def _count_lines(path: Path, end: bytes = b"\n") -> int:
    """Lines of a file ending with ``end`` (a last line without it counts), in blocks."""
    count, last = 0, end
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(BLOCK_BYTES), b""):
            count += block.count(end)
            last = block[-1:]
    return count + (last != end)


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


def _read_csv(path: Path, shown: str) -> Table:
    """Stream a CSV file into one preallocated (columns × rows) array, a block at a time."""
    with open(path, "rb") as fh:
        head = fh.read(8192)
    for magic, words in _NOT_CSV:
        if head.startswith(magic):
            raise DataError(f"{shown}: the file {words}; a dataset is CSV text or an NPZ file")
    if b"\0" in head:
        raise DataError(f"{shown}: a binary file, not CSV text; a dataset is CSV text or an "
                        "NPZ file")
    cr_only = b"\r" in head and b"\n" not in head     # classic Mac OS line ends
    rows = max(_count_lines(path, b"\r" if cr_only else b"\n") - 1, 0)
    header: list[str] | None = None
    out: np.ndarray | None = None
    filled = 0
    blocks: list[tuple[int, int, list[int] | None]] = []  # first row, first line, lines
    with open(path, "rb") as fh:
        for first, lines in _blocks(fh, shown, cr_only):
            if header is None:
                header = _header(shown, lines[0].removeprefix("\ufeff"))
                out = np.empty((len(header), rows))
                first, lines = first + 1, lines[1:]
            assert out is not None
            values = _parse_lines(shown, header, lines, first) if lines else np.empty((0, 0))
            if filled + len(values) > rows:
                raise DataError(f"{shown}: the file changed while it was read")
            kept = None if len(values) == len(lines) else [     # blank lines skipped
                first + i for i, text in enumerate(lines) if text.strip()]
            blocks.append((filled, first, kept))
            if len(values):
                out[:, filled:filled + len(values)] = values.T
                filled += len(values)
    if header is None or out is None:
        raise DataError(f"{shown}: empty file (expected a header row naming the columns)")
    if filled == 0:
        raise DataError(f"{shown}: no observations (the file has a header but no rows)")
    if filled < rows:
        out = out[:, :filled].copy() if filled < 0.9 * rows else out[:, :filled]
    return Table({name: out[i] for i, name in enumerate(header)}, "line",
                 _row_lines(filled, blocks))


def _row_lines(rows: int, blocks: list[tuple[int, int, list[int] | None]]
               ) -> np.ndarray | None:
    """The line of every row when blank lines were skipped, else None (row r on line
    r + 2); ``blocks`` gives each block's first row and line, and the lines of its rows
    when it had blank lines."""
    if all(kept is None for _, _, kept in blocks):
        return None
    lines = np.empty(rows, dtype=np.int64)
    ends = [start for start, _, _ in blocks[1:]] + [rows]
    for (start, first, kept), end in zip(blocks, ends, strict=True):
        lines[start:end] = kept if kept is not None else np.arange(first, first + end - start)
    return lines


#: Most observations an NPZ file may hold (as many as a simulated dataset): its arrays are
#: inflated whole, so a longer log is a folder of shards (:mod:`symcal.data.shards`).
MAX_NPZ_ROWS = 100_000_000
#: Bytes of an NPZ array inflated at a time.
NPZ_CHUNK_BYTES = 1 << 22


@dataclass(frozen=True)
class _Member:
    """One array of an NPZ file as its ``.npy`` header describes it."""

    info: zipfile.ZipInfo
    dtype: np.dtype
    length: int
    offset: int      # bytes of the header, before the data


def _physical_memory() -> int | None:
    """Bytes of memory of this machine, or None where it cannot be told."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return None


#: numpy parses a ``.npy`` header with ``ast.literal_eval``, and CPython 3.11's AST
#: constructor keeps its recursion depth in state every thread shares: shards read on
#: several threads at once failed at random with "SystemError: AST constructor recursion
#: depth mismatch" (CPython gh-106905).  Headers are a few hundred bytes: one at a time.
_HEADER_LOCK = ForkLock()


def npy_header(fh: IO[bytes]) -> tuple[tuple[int, ...], np.dtype]:
    """The shape and dtype of the ``.npy`` array whose file ``fh`` is at its start, the
    file left at its data (raises ``ValueError`` where it holds no ``.npy`` header)."""
    version = np.lib.format.read_magic(fh)
    read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
            else np.lib.format.read_array_header_2_0)
    with _HEADER_LOCK:
        shape, _, dtype = read(fh)
    return shape, dtype


def _npz_member(shown: str, zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> _Member:
    """Read and check one member's ``.npy`` header (a few hundred bytes inflated)."""
    name = _name(info.filename.removesuffix(".npy"))
    try:
        with zf.open(info) as fh:
            shape, dtype = npy_header(fh)
            offset = fh.tell()
    except ValueError:
        raise DataError(f"{shown}: member '{_name(info.filename)}' is not a NumPy array (no "
                        ".npy header); an NPZ file holds one .npy array per column, as "
                        "numpy.savez writes it") from None
    if dtype.hasobject:
        raise DataError(f"{shown}: array '{name}' holds Python objects; a dataset's arrays "
                        "hold numbers")
    if len(shape) != 1:
        raise DataError(f"{shown}: array '{name}' has shape {shape}; every array must be "
                        "1-D, one value per observation (one array per column)")
    if dtype.kind not in "fiu":
        raise DataError(f"{shown}: array '{name}' holds {dtype} values; every array must "
                        "hold real numbers (float or integer)")
    claimed, held = shape[0] * dtype.itemsize, info.file_size - offset
    if claimed != held:
        raise DataError(f"{shown}: array '{name}': its header claims {shape[0]} values "
                        f"({claimed} bytes) but its member holds {held} bytes; the file is "
                        "damaged or not written by numpy")
    return _Member(info, dtype, shape[0], offset)


def _npz_members(shown: str, zf: zipfile.ZipFile) -> dict[str, _Member]:
    """Every array of an NPZ file from its header alone, checked before any is inflated:
    one ``.npy`` member per name, 1-D real numbers, sizes that agree with the zip's
    directory, one length, and a size this machine can hold."""
    members: dict[str, _Member] = {}
    for info in zf.infolist():
        if not info.filename.endswith(".npy"):
            raise DataError(f"{shown}: member '{_name(info.filename)}' is not a NumPy array "
                            "(.npy); an NPZ file holds one .npy array per column, as "
                            "numpy.savez writes it")
        key = info.filename[:-4]
        if key in members:
            raise DataError(f"{shown}: array '{_name(key)}' appears twice (two members "
                            f"named '{_name(info.filename)}'); an NPZ file names each array "
                            "once")
        members[key] = _npz_member(shown, zf, info)
    lengths = {m.length for m in members.values()}
    if len(lengths) > 1:
        raise DataError(f"{shown}: arrays have different lengths {sorted(lengths)}")
    rows = lengths.pop() if lengths else 0
    if rows > MAX_NPZ_ROWS:
        raise DataError(f"{shown}: the arrays hold {rows} observations; an NPZ file holds at "
                        f"most {MAX_NPZ_ROWS} (a longer log is a folder of shards)")
    need, have = rows * len(members) * 8, _physical_memory()
    if have is not None and need > have:
        raise DataError(f"{shown}: the arrays need {need / 2**30:.1f} GiB as numbers, more "
                        f"than this machine's {have / 2**30:.1f} GiB of memory")
    return members


def _npz_array(zf: zipfile.ZipFile, member: _Member) -> np.ndarray:
    """A member's values as floats, inflated a few MiB at a time."""
    out = np.empty(member.length)
    step = max(NPZ_CHUNK_BYTES // member.dtype.itemsize, 1)
    with zf.open(member.info) as fh:
        fh.read(member.offset)
        for start in range(0, member.length, step):
            count = min(step, member.length - start)
            data = fh.read(count * member.dtype.itemsize)
            if len(data) != count * member.dtype.itemsize:
                raise EOFError("the array ends early")
            out[start:start + count] = np.frombuffer(data, dtype=member.dtype)
        fh.read(1)  # reach the end: zipfile checks the CRC there
    return out


def _read_npz(path: Path, shown: str) -> Table:
    """The arrays of an NPZ file: 1-D real numbers, all of one length.

    Every member's ``.npy`` header is read and checked first (names, shapes, types, sizes
    against the zip's directory, lengths, the machine's memory), so a damaged file or a
    deflate bomb is refused before any array is inflated; then each array is inflated
    into floats a few MiB at a time.
    """
    with open(path, "rb") as fh:
        head = fh.read(4)
    if head not in (b"PK\x03\x04", b"PK\x05\x06"):
        raise DataError(f"{shown}: not an NPZ file (no zip signature); write one with "
                        "numpy.savez")
    try:
        with zipfile.ZipFile(path) as zf:
            members = _npz_members(shown, zf)
            return Table({key: _npz_array(zf, m) for key, m in members.items()})
    except DataError:
        raise
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, KeyError, zlib.error,
            NotImplementedError, RuntimeError) as exc:
        reason = excerpt(exc, 80)
        raise DataError(f"{shown}: not a readable NPZ file ({reason})") from None


#: The first (and last) bytes of a Parquet file.
_PARQUET_MAGIC = b"PAR1"


def _read_parquet(path: Path, shown: str) -> Table:
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
        # integers beyond 2**53 (a uint64 counter) round to the nearest double, as numpy
        # and a CSV file's digits do; Arrow's checked cast would refuse them
        column = table.column(field.name).cast(pa.float64(), safe=False)
        if column.null_count:  # a null is a missing value: NaN, refused or dropped later
            column = column.fill_null(float("nan"))
        columns[field.name] = np.asarray(column.to_numpy(), dtype=float)
    if not columns:
        raise DataError(f"{shown}: the Parquet file has no columns")
    return Table(columns)


def read_table(path: str | Path) -> Table:
    """Read a CSV (header row, one row per observation), NPZ or Parquet file into columns.

    A CSV file is read in blocks of whole lines into one array sized from a first count
    of its lines, so memory stays near the size of the numbers themselves.  Blank lines
    are skipped; a line starting with ``#`` is refused (data files have no comments).
    An NPZ file must hold 1-D arrays of real numbers, all of one length.  A ``.parquet``
    file (one file, read with pyarrow) must hold columns of real numbers; its nulls
    become NaN, refused or dropped like any invalid value.

    Returns
    -------
    Table
        Column name → float array (a dict), knowing the line or row each row came from.

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
            raise DataError(f"{source}: {len(rows)} row(s) with NaN or inf in a needed column "
                            f"({rows_text(columns, rows)}); fix them or pass --drop-invalid "
                            "to drop them")
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
