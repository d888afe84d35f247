"""A log too large for one process: a dataset kept as shards on disk, read one at a time.

A partitioned dataset is a folder of shard files of one kind, in the order of their
paths (sorted; sub-folders included, as a partitioned Parquet dataset has them):
Parquet files (read with pyarrow), NPZ files, or CSV files, each a table with the
columns the problem needs.  Nothing is read when it is opened but the row counts
(Parquet metadata, NPZ array headers; CSV shards are counted line by line); a shard's
numbers are read by the task that processes it (:mod:`symcal.solvers.passes`), on a Dask
worker or in this process, and checked like any data file (missing columns, NaN or inf).
"""

from __future__ import annotations

import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from symcal.base.errors import DataError
from symcal.base.files import display_path
from symcal.data.dataset import Dataset, make_dataset, npy_header, read_table

#: Shard kinds by file suffix.
KINDS = {".parquet": "parquet", ".npz": "npz", ".csv": "csv"}


@dataclass(frozen=True)
class Shard:
    """One file of a partitioned dataset.

    Attributes
    ----------
    path
        The file.
    rows
        Its observations.
    needed
        Columns that must be present and finite.
    """

    path: Path
    rows: int
    needed: tuple[str, ...]

    def read(self, columns: tuple[str, ...]) -> np.ndarray:
        """``columns`` of the shard stacked as rows (``len(columns) × rows``), checked."""
        return self.dataset("shard").matrix(columns)

    def dataset(self, name: str) -> Dataset:
        """The whole shard as an in-memory dataset called ``name``, checked."""
        shown = display_path(self.path)
        data = make_dataset(name, shown, read_table(self.path), self.needed, copy=False)
        if data.n != self.rows:
            raise DataError(f"{shown}: {data.n} rows, but it had {self.rows} when the "
                            "partitioned dataset was opened (changed meanwhile?)")
        return data


@dataclass(frozen=True)
class ShardedDataset:
    """A dataset kept on disk as shards (see the module's docstring).

    Attributes
    ----------
    name
        The dataset's role in the problem.
    source
        Where it came from, for reports.
    shards
        The shards, in order.
    """

    name: str
    source: str
    shards: tuple[Shard, ...]

    @property
    def n(self) -> int:
        """Observations in all shards."""
        return sum(s.rows for s in self.shards)

    def sample(self, count: int) -> Dataset:
        """At most ``count`` observations, evenly spaced over the first shards that hold
        them, as an in-memory dataset (a bounded sample: for the gauge analysis)."""
        parts: list[Dataset] = []
        rows = 0
        for shard in self.shards:
            parts.append(shard.dataset(self.name))
            rows += parts[-1].n
            if rows >= count:
                break
        names = [c for c in parts[0].columns if all(c in p.columns for p in parts)]
        merged = {c: np.concatenate([np.asarray(p.columns[c]) for p in parts]) for c in names}
        take = np.unique(np.linspace(0, rows - 1, min(rows, count)).round().astype(int))
        return make_dataset(self.name, f"{self.source} (a sample of {take.size} rows)",
                            {c: v[take] for c, v in merged.items()}, shard.needed)

    def spread(self, count: int) -> Dataset:
        """At most ``count`` observations spread evenly over the whole log (every shard
        read once, in order; the rows kept in time order), as an in-memory dataset: what a
        diagnosis of the log examines."""
        total = self.n
        every = max(1, -(-total // max(count, 1)))       # keep one row in `every`
        parts: dict[str, list[np.ndarray]] = {}
        start = 0
        needed: tuple[str, ...] = ()
        for shard in self.shards:
            data = shard.dataset(self.name)
            needed = shard.needed
            take = np.arange((-start) % every, data.n, every)
            for c, v in data.columns.items():
                parts.setdefault(c, []).append(np.asarray(v)[take])
            start += data.n
        names = [c for c, v in parts.items() if len(v) == len(self.shards)]
        merged = {c: np.concatenate(parts[c]) for c in names}
        kept = len(next(iter(merged.values()))) if merged else 0
        return make_dataset(self.name, f"{self.source} (one row in {every} of its {total}: "
                            f"{kept} rows)" if every > 1 else self.source, merged, needed)

    def manifest(self) -> str:
        """A digest of the shards' paths, sizes and modification times: what a result
        checks to know that the log did not change (its bytes are not hashed: a day's
        log is read once per pass, not once more to hash it)."""
        import hashlib

        h = hashlib.sha256()
        for shard in self.shards:
            st = shard.path.stat()
            h.update(f"{shard.path.resolve()}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
        return "shards:" + h.hexdigest()


def _rows_npz(path: Path, shown: str) -> int:
    try:
        with zipfile.ZipFile(path) as zf:
            names = [n for n in zf.namelist() if n.endswith(".npy")]
            if not names:
                raise DataError(f"{shown}: the NPZ shard holds no arrays")
            with zf.open(names[0]) as fh:
                shape, _ = npy_header(fh)
    except (zipfile.BadZipFile, ValueError, OSError) as exc:
        raise DataError(f"{shown}: not a readable NPZ file ({exc})") from None
    if len(shape) != 1:
        raise DataError(f"{shown}: arrays must be 1-D columns, found shape {shape}")
    return int(shape[0])


def _rows_parquet(path: Path, shown: str) -> int:
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        return int(pq.ParquetFile(path).metadata.num_rows)
    except (pa.ArrowException, OSError, ValueError) as exc:
        raise DataError(f"{shown}: not a readable Parquet file ({exc})") from None


def _rows(path: Path, kind: str, needed: tuple[str, ...]) -> int:
    shown = display_path(path)
    if kind == "npz":
        return _rows_npz(path, shown)
    if kind == "parquet":
        return _rows_parquet(path, shown)
    return make_dataset("shard", shown, read_table(path), needed, copy=False).n


def open_shards(name: str, where: str | Path | Sequence[str | Path],
                needed: Sequence[str]) -> ShardedDataset:
    """Open a partitioned dataset: a folder of shards, or the shard files in order.

    Parameters
    ----------
    name
        The dataset's role in the problem (``calibration``, ...).
    where
        A folder (every ``.parquet``, ``.npz`` or ``.csv`` file under it, sorted by path)
        or a list of shard files.
    needed
        Columns every shard must have, finite.

    Raises
    ------
    DataError
        If there is no shard, shards of more than one kind, or a shard that cannot be
        read.
    """
    if isinstance(where, str | Path):
        root = Path(where)
        if not root.is_dir():
            raise DataError(f"{display_path(root)}: not a folder of shards")
        paths = sorted(p for p in root.rglob("*") if p.suffix.lower() in KINDS and p.is_file())
        source = display_path(root)
    else:
        paths = [Path(p) for p in where]
        source = f"{len(paths)} shard file(s)"
    if not paths:
        raise DataError(f"{source}: no shard files (.parquet, .npz or .csv)")
    kinds = {KINDS.get(p.suffix.lower(), p.suffix) for p in paths}
    if len(kinds) > 1:
        raise DataError(f"{source}: shards of more than one kind ({', '.join(sorted(kinds))})"
                        "; a partitioned dataset is all Parquet, all NPZ or all CSV")
    (kind,) = kinds
    if kind not in KINDS.values():
        raise DataError(f"{source}: shards must be .parquet, .npz or .csv files")
    cols = tuple(needed)
    shards = tuple(Shard(p, _rows(p, kind, cols), cols) for p in paths)
    return ShardedDataset(name, source, shards)
