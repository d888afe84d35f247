"""The one home of dataset loading: a problem's datasets from files, objects or simulation.

Every command reads data through :func:`load_datasets`, so an unknown dataset name, a
missing file or a missing column is answered the same way everywhere.  Simulated datasets
(``simulate:`` in a problem's ``datasets``) come from the courier simulator, the one
dataset source that is not a file.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import DataError
from symcal.base.forks import ForkLock
from symcal.base.units import size
from symcal.data.dataset import Dataset, make_dataset, read_table
from symcal.data.derived import sources, with_derived
from symcal.language.problem_file import DatasetSpec
from symcal.language.yamlio import display_path
from symcal.problem.symbolic import Problem


def needed_columns(problem: Problem) -> list[str]:
    """Columns every dataset must have: those the constraints read."""
    needed: list[str] = []
    for c in problem.constraints:
        needed += [col for col in problem.columns_of(c.sx) if col not in needed]
    return needed


def load_dataset(
    spec: DatasetSpec, needed: Iterable[str], path: str | Path | None = None,
    drop_invalid: bool = False,
) -> Dataset:
    """Load the dataset ``spec`` describes, or the file ``path`` that replaces it; a
    folder is a partitioned log (:func:`~symcal.data.shards.open_shards`: opened, not read)."""
    if path is not None and Path(path).is_dir():
        from symcal.data.shards import open_shards

        return open_shards(spec.name, path, tuple(needed))  # type: ignore[return-value]
    if path is not None:
        return make_dataset(spec.name, display_path(Path(path)), read_table(path), needed,
                            drop_invalid, copy=False)
    if spec.path is not None:
        return make_dataset(spec.name, spec.source, read_table(spec.path), needed, drop_invalid,
                            copy=False)
    from symcal.simulation import simulate_run

    assert spec.scenario is not None and spec.run is not None
    columns = simulate_run(scenario(spec.scenario), spec.run, seed=spec.seed, n=spec.n)
    return make_dataset(spec.name, spec.source, columns, needed, drop_invalid)


#: Scenarios loaded in this process: path → (the state of every file it was read from,
#: the scenario).  A problem solved again re-simulates its datasets from it.
_SCENARIOS: dict[Path, tuple[tuple[tuple[Path, Any], ...], Any]] = {}
_SCENARIOS_LOCK = ForkLock()
#: Scenarios kept at most.
SCENARIOS_KEPT = 16


def _state(path: Path) -> Any:
    """What tells a file changed: inode, size, modification time (ns); None if gone."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_ino, st.st_size, st.st_mtime_ns)


def scenario(path: str | Path) -> Any:
    """The scenario file ``path`` loaded (:func:`symcal.simulation.load_scenario`), kept
    while it and every file it extends are unchanged (same inode, size and modification
    time): a problem solved again (``improve``, ``design``, a fleet, a benchmark) does not
    parse its scenario again for the datasets it simulates (it was 20 to 40 ms a solve)."""
    from symcal.language.overlay import extends_chain
    from symcal.simulation import load_scenario

    key = Path(path).resolve()
    with _SCENARIOS_LOCK:
        kept = _SCENARIOS.get(key)
    if kept is not None and all(_state(f) == st for f, st in kept[0]):
        return kept[1]
    files = tuple((f, _state(f)) for f in extends_chain(key, "scenario"))
    loaded = load_scenario(key)
    with _SCENARIOS_LOCK:
        if len(_SCENARIOS) >= SCENARIOS_KEPT:
            _SCENARIOS.clear()
        _SCENARIOS[key] = (files, loaded)
    return loaded


def column_noise(problem: Problem) -> dict[str, float]:
    """The declared noise of each data column (standard deviation, in the column's
    unit)."""
    return {name: r.sigma / size(r.unit) for name, r in problem.noise_columns().items()
            if r.unit}


def load_datasets(
    problem: Problem,
    given: Mapping[str, Dataset | str | Path] | None = None,
    drop_invalid: bool = False,
    names: Iterable[str] | None = None,
) -> dict[str, Dataset]:
    """Every dataset of ``problem`` (or those in ``names``), ``given`` ones replacing it.

    Parameters
    ----------
    problem
        The problem whose ``datasets`` section says where data comes from.
    given
        Dataset name → :class:`~symcal.data.dataset.Dataset` or CSV/NPZ path
        (``--data NAME=PATH``).
    drop_invalid
        Drop rows with NaN/inf in a needed column instead of refusing the data.
    names
        Load only these datasets (default: all of the problem's).

    Raises
    ------
    DataError
        Unknown dataset name, missing file or column, malformed cells, invalid rows.
    """
    given = dict(given or {})
    for name in given:
        if name not in problem.datasets:
            raise DataError(f"--data {name}=...: the problem has no dataset '{name}'"
                            f"{did_you_mean(name, problem.datasets)}; it has: "
                            f"{', '.join(problem.datasets)}")
    needed = needed_columns(problem)
    read = sources(problem.column_specs, needed)   # derived columns: what they come from
    wanted = list(problem.datasets) if names is None else list(names)
    out: dict[str, Dataset] = {}
    for name in wanted:
        item = given.get(name)
        if isinstance(item, Dataset):
            out[name] = item
        elif item is not None and Path(item).is_dir():   # shards: derived columns refused
            out[name] = load_dataset(problem.datasets[name], needed, item, drop_invalid)
        else:
            out[name] = load_dataset(problem.datasets[name], read, item, drop_invalid)
        if isinstance(out[name], Dataset):
            out[name] = with_derived(problem.column_specs, out[name], needed,
                                     column_noise(problem))
    return out
