"""Fleet calibration on Dask: every unit of a fleet folder solved in parallel, one
result per unit, and the fleet's summary.

A fleet folder holds one subfolder per unit, ``FLEET/UNIT/NAME.csv`` (or ``.npz`` or
``.parquet``) for each of the problem's datasets ``NAME`` the unit has; the datasets a
unit lacks come from ``data`` (``--data``) or the problem's own.  Each unit is one Dask
task that runs exactly what ``symcal solve PROBLEM --data NAME=FLEET/UNIT/NAME.csv ...``
runs, so its result equals that local solve's.  A unit's failure (bad data, a failed
solve, even a worker that died) is that unit's result, ``{"error": MESSAGE}`` or its
failed document, and never stops the others.

Dask is imported only here, inside :func:`solve_fleet` and :func:`fleet_client`, never at
``import symcal``.  By default the fleet runs on an embedded local cluster: one worker
process per core, one thread each, BLAS pinned to one thread.  ``executor`` names a
running Dask scheduler instead (its workers must have symcal installed and see the
problem and data files at the same absolute paths).
"""

from __future__ import annotations

import contextlib
import time
import uuid
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from symcal.base.cores import mark_pool_thread, usable_cores
from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import DataError, SymcalError, excerpt
from symcal.base.files import display_path, json_plain
from symcal.base.options import SolveOptions
from symcal.base.progress import Bars, Progress, reporting
from symcal.calibrate.fleet_summary import failure_reason, summarise
from symcal.calibrate.result import Result, file_hashes
from symcal.calibrate.solve import solve
from symcal.problem.build import load_problem
from symcal.problem.symbolic import Problem
from symcal.solvers.dask_executor import DaskExecutor

if TYPE_CHECKING:
    from distributed import Client

#: Suffixes of a unit's data files, in the order they are looked for.
SUFFIXES = (".csv", ".npz", ".parquet")
#: What the client hears of each finished unit: ``on_unit(unit, document, report)``.
UnitCallback = Callable[[str, Mapping[str, Any], str | None], None]


# ------------------------------------------------------------------------ the fleet folder

@dataclass(frozen=True)
class Unit:
    """One unit of a fleet folder.

    Attributes
    ----------
    name
        The subfolder's name.
    files
        Dataset name → the unit's file for it.
    error
        Why the unit cannot be solved, found before solving (None: it can be).
    """

    name: str
    files: Mapping[str, Path] = field(default_factory=dict)
    error: str | None = None


def _unit(problem: Problem, folder: Path) -> Unit:
    """The data files of one unit folder, or why they cannot be used."""
    files: dict[str, Path] = {}
    shown = display_path(folder)
    names = list(problem.datasets)
    for path in sorted(folder.iterdir()):
        if path.name.startswith(".") or path.suffix.lower() not in SUFFIXES:
            continue
        if not path.is_file():
            return Unit(folder.name, error=f"{display_path(path)}: not a regular file")
        stem = path.stem
        if stem not in problem.datasets:
            return Unit(folder.name, error=(
                f"{display_path(path)}: the problem has no dataset '{excerpt(stem)}'"
                f"{did_you_mean(stem, names)}; its datasets: {', '.join(names)}"))
        if stem in files:
            return Unit(folder.name, error=(
                f"{shown}: two files for dataset '{stem}' ({files[stem].name} and "
                f"{path.name}); keep one"))
        files[stem] = path
    if not files:
        return Unit(folder.name, error=(
            f"{shown}: no data file; a unit folder holds NAME.csv, NAME.npz or "
            f"NAME.parquet for datasets NAME of the problem ({', '.join(names)})"))
    return Unit(folder.name, files)


def find_units(problem: Problem, fleet: str | Path) -> list[Unit]:
    """The units of a fleet folder, sorted by name, each with its files or its error.

    Parameters
    ----------
    problem
        The problem whose dataset names the files must have.
    fleet
        The fleet folder: one subfolder per unit (hidden ones are skipped).

    Raises
    ------
    DataError
        When ``fleet`` is not a folder or has no unit subfolder.
    """
    folder = Path(fleet)
    shown = display_path(folder)
    if not folder.is_dir():
        what = "not found" if not folder.exists() else "is not a folder"
        raise DataError(f"fleet folder {shown}: {what}")
    subfolders = sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))
    if not subfolders:
        raise DataError(f"fleet folder {shown}: no unit subfolder; a fleet folder holds one "
                        "folder per unit, each with NAME.csv, NAME.npz or NAME.parquet for "
                        f"datasets NAME of the problem ({', '.join(problem.datasets)})")
    return [_unit(problem, sub) for sub in subfolders]


# ------------------------------------------------------------------------ one unit (worker)

@dataclass(frozen=True)
class UnitTask:
    """Everything a worker needs to solve one unit: plain, picklable data.

    The problem is loaded again on the worker from ``problem_file`` (once per process
    and problem) and refused when its files differ from ``hashes`` (a remote worker that
    sees other files).
    """

    unit: str
    problem_file: str
    hashes: tuple[tuple[str, str], ...]
    weighting: str
    data: tuple[tuple[str, str], ...]
    method: str | None
    max_iter: int
    tol: float
    ipopt: tuple[tuple[str, Any], ...]
    drop_invalid: bool
    report: Callable[[Result], str] | None = None


#: Problems loaded in this (worker) process, by file, file hashes and weighting.
_LOADED: dict[tuple[str, tuple[tuple[str, str], ...], str], Problem] = {}


def _problem_for(task: UnitTask) -> Problem:
    key = (task.problem_file, task.hashes, task.weighting)
    if key not in _LOADED:
        problem = load_problem(task.problem_file)
        if tuple(sorted(file_hashes(problem).items())) != task.hashes:
            raise SymcalError(f"{task.problem_file}: the problem or model files on this "
                              "worker differ from those the fleet was started with")
        if len(_LOADED) >= 4:
            _LOADED.clear()
        _LOADED[key] = problem.with_weighting(task.weighting)
    return _LOADED[key]


def _message(exc: BaseException) -> str:
    if isinstance(exc, SymcalError):
        return str(exc)
    if isinstance(exc, MemoryError):
        return "out of memory: the unit's data are too large for a worker"
    if isinstance(exc, OSError):
        where = f"{excerpt(exc.filename, 200)}: " if exc.filename else ""
        return f"{where}{exc.strerror or exc.__class__.__name__}"
    return (f"internal error ({exc.__class__.__name__}: {excerpt(exc, 200)}); please report "
            "it")


def _document(result: Result) -> dict[str, Any]:
    """The unit's ``result.json`` document as JSON gives it back (the same values as
    ``json.loads(json_text(...))``), made by :func:`~symcal.base.files.json_plain`
    without writing the text: the round trip through JSON took a unit as long as a
    twentieth of its solve."""
    doc = json_plain(result.to_dict())
    assert isinstance(doc, dict)
    return doc


def solve_unit(task: UnitTask) -> dict[str, Any]:
    """Solve one unit (the Dask task): ``{"document": ..., "report": ...}`` with the
    unit's ``symcal solve --json`` document and, when the task carries a renderer, its
    text report; or ``{"error": MESSAGE}``.

    Never raises for a fault of the unit (its data, its solve): the message says what."""
    try:
        problem = _problem_for(task)
        options = SolveOptions(task.method, task.max_iter, task.tol, dict(task.ipopt))
        result = solve(problem, dict(task.data), options, drop_invalid=task.drop_invalid)
        outcome: dict[str, Any] = {"document": _document(result)}
        if task.report is not None:
            outcome["report"] = task.report(result)
        return outcome
    except Exception as exc:  # noqa: BLE001 - one unit's fault is that unit's result
        return {"error": _message(exc)}


# ------------------------------------------------------------------------ the fleet (client)

@dataclass(frozen=True)
class FleetResult:
    """The result of a fleet: a :class:`~symcal.calibrate.result.Result` per unit that
    was solved, the reason for each unit that could not be, and the summary.

    Attributes
    ----------
    problem
        The problem every unit was solved with.
    results
        Unit name (sorted) → its result (``success`` False for a failed solve).
    errors
        Unit name → why it has no result (bad data, a worker that died).
    summary
        :func:`symcal.calibrate.fleet_summary.summarise` of the units' documents:
        parameter distributions, outliers and failures with their reasons.
    seconds
        Wall time of the whole fleet.
    """

    problem: Problem
    results: Mapping[str, Result]
    errors: Mapping[str, str]
    summary: Mapping[str, Any]
    seconds: float = 0.0

    @property
    def units(self) -> tuple[str, ...]:
        """Every unit's name, sorted (those with a result and those without)."""
        return tuple(sorted({*self.results, *self.errors}))

    @property
    def success(self) -> bool:
        """Whether every unit was solved successfully (outliers do not count)."""
        return not self.summary["failed"]

    @property
    def failed(self) -> Mapping[str, str]:
        """Failed unit → reason."""
        return self.summary["failed"]

    @property
    def outliers(self) -> Mapping[str, list[Mapping[str, Any]]]:
        """Outlier unit → its findings, each with its ``reason``."""
        return self.summary["outliers"]

    def to_dict(self) -> dict[str, Any]:
        """``{"units": {UNIT: document or {"error": MESSAGE}}, "summary": {...}}``: what
        ``symcal solve --fleet DIR --json`` prints."""
        units = {u: (self.results[u].to_dict() if u in self.results
                     else {"error": self.errors[u]}) for u in self.units}
        return {"units": units, "summary": dict(self.summary)}


@contextlib.contextmanager
def fleet_client(scheduler: str | None = None, workers: int | None = None) -> Iterator[Client]:
    """A Dask client: to the scheduler at ``scheduler``, or to an embedded local cluster.

    Parameters
    ----------
    scheduler
        Address of a running Dask scheduler (``tcp://host:8786``); None starts a local
        cluster of processes, closed when the block ends.
    workers
        Worker processes of the local cluster (default: one per core), one thread each,
        with one BLAS thread.

    Raises
    ------
    SymcalError
        When the scheduler cannot be reached (exit code 2).
    """
    from symcal.solvers.dask_executor import dask_client

    with dask_client(scheduler, workers, "--scheduler") as client:
        yield client


def _tasks(problem: Problem, hashes: Mapping[str, str], units: list[Unit],
           data: Mapping[str, str | Path], options: SolveOptions, drop_invalid: bool,
           report: Callable[[Result], str] | None) -> dict[str, UnitTask]:
    checked = tuple(sorted(hashes.items()))
    shared = {name: str(Path(path).resolve()) for name, path in data.items()}
    out = {}
    for unit in units:
        if unit.error is not None:
            continue
        files = {**shared, **{k: str(p.resolve()) for k, p in unit.files.items()}}
        out[unit.name] = UnitTask(unit.name, str(Path(problem.path).resolve()), checked,
                                  problem.weighting, tuple(sorted(files.items())),
                                  options.method, options.max_iter, options.tol,
                                  tuple(sorted(options.ipopt.items())), drop_invalid, report)
    return out


def solve_units(tasks: tuple[UnitTask, ...]) -> list[dict[str, Any]]:
    """Solve a batch of units one after the other (one Dask task): their outcomes as
    :func:`solve_unit` gives them, in order.  The worker's thread is one of its pass
    threads: a unit's evaluations are not split again."""
    mark_pool_thread()
    return [solve_unit(task) for task in tasks]


#: Batches per worker: units are sent in batches, so that a quick unit does not pay a
#: task's round trip of its own, and several per worker, so that the load stays balanced.
BATCHES_PER_WORKER = 12


def batches(units: list[str], workers: int) -> list[list[str]]:
    """``units`` in contiguous batches, :data:`BATCHES_PER_WORKER` per worker (at most one
    batch per unit)."""
    count = max(1, min(len(units), BATCHES_PER_WORKER * max(1, workers)))
    size, extra = divmod(len(units), count)
    out, start = [], 0
    for i in range(count):
        end = start + size + (i < extra)
        out.append(units[start:end])
        start = end
    return [b for b in out if b]


def _workers_of(client: Client) -> int:
    try:
        return max(1, len(client.scheduler_info().get("workers", {})))
    except Exception:  # noqa: BLE001 - a scheduler that does not say: one batch per unit
        return 0


def _run(client: Client, tasks: Mapping[str, UnitTask],
         finish: Callable[[str, dict[str, Any]], None]) -> None:
    """Submit the units in batches (:func:`batches`); hand each unit's outcome to
    ``finish`` as its batch completes."""
    from distributed import as_completed

    token = uuid.uuid4().hex[:12]
    names = list(tasks)
    workers = _workers_of(client)
    groups = batches(names, workers) if workers else [[n] for n in names]
    futures = {client.submit(solve_units, tuple(tasks[u] for u in group),
                             key=f"symcal-units-{i}-{token}", pure=False): group
               for i, group in enumerate(groups)}
    try:
        for future in as_completed(futures):
            group = futures[future]
            try:
                outcomes = future.result()
            except Exception as exc:  # noqa: BLE001 - a worker died, a task was lost
                why = f"{exc.__class__.__name__}: {excerpt(exc, 200)}"
                outcomes = [{"error": f"the Dask task of unit '{unit}' failed: {why}"}
                            for unit in group]
            finally:
                future.release()
            for unit, outcome in zip(group, outcomes, strict=True):
                finish(unit, outcome)
    except BaseException:
        client.cancel(list(futures))
        raise


def solve_fleet(
    problem: Problem | str | Path,
    fleet: str | Path,
    data: Mapping[str, str | Path] | None = None,
    options: SolveOptions | None = None,
    *,
    drop_invalid: bool = False,
    executor: str | Client | DaskExecutor | None = None,
    workers: int | None = None,
    bars: Bars | None = None,
    on_unit: UnitCallback | None = None,
    report: Callable[[Result], str] | None = None,
    progress: Progress | None = None,
) -> FleetResult:
    """Calibrate every unit of a fleet folder on Dask.

    Each unit is solved as ``symcal.solve(problem, files, options)`` on a worker, its
    files being ``FLEET/UNIT/NAME.csv`` (``.npz``, ``.parquet``) for each dataset NAME
    it has, then ``data``, then the problem's own datasets.  The problem is loaded again
    from its file on the workers, with its weighting.  Run it from a script under
    ``if __name__ == "__main__":`` (the local cluster starts processes).

    Parameters
    ----------
    problem
        A :class:`~symcal.problem.symbolic.Problem` or the path of a problem file.
    fleet
        The fleet folder: one subfolder per unit.
    data
        Dataset name → file, for every unit that has no file of its own for it.
    options
        How to solve (default: the problem file's ``solver:`` section).
    drop_invalid
        Drop rows with NaN/inf instead of refusing a unit's data.
    executor
        Where to run, as for :func:`symcal.solve_partitioned`: None, an embedded local
        cluster (``workers`` processes, one per core by default); a scheduler address;
        a :class:`distributed.Client` of your own or a
        :class:`~symcal.solvers.dask_executor.DaskExecutor` (left open).
    workers
        Worker processes of the embedded cluster: at most one per usable core, and never
        more than there are units to solve.
    bars
        Progress bars (:func:`symcal.base.progress.terminal_bars`): one meter counting
        the units done, the latest unit's outcome beside it (then not passed to
        ``progress``).  None: no bars.
    on_unit
        Called on this process as each unit finishes, with the unit's name, its
        document (or ``{"error": MESSAGE}``) and its text report (or None).
    report
        Renders a unit's text report on its worker (the command line passes
        :func:`symcal.report.text.text_report`); None: no text reports.
    progress
        Called with each line of progress (:mod:`symcal.base.progress`): one per unit
        done, ``fleet: K/N unit NAME: solved`` (or ``FAILED: REASON``).  None: no lines.

    Returns
    -------
    FleetResult
        Every unit's result or error, and the summary.

    Raises
    ------
    SymcalError
        Only for the fleet as a whole: an unreadable problem, a missing or empty fleet
        folder, an unknown ``data`` name, an unreachable scheduler.
    """
    start = time.perf_counter()
    if not isinstance(problem, Problem):
        problem = load_problem(problem)
    options = options or problem.options
    data = dict(data or {})
    for name in data:
        if name not in problem.datasets:
            raise DataError(f"--data {name}=...: the problem has no dataset '{name}'"
                            f"{did_you_mean(name, problem.datasets)}; it has: "
                            f"{', '.join(problem.datasets)}")
    if workers is not None and workers < 1:
        raise SymcalError(f"workers: must be at least 1, found {workers}")
    if workers is not None and workers > usable_cores():
        raise SymcalError(f"workers: at most {usable_cores()} on this machine (one worker "
                          f"process per usable core), found {workers}")
    units = find_units(problem, fleet)
    hashes = file_hashes(problem)     # once: every unit's task and document checks them
    tasks = _tasks(problem, hashes, units, data, options, drop_invalid, report)
    docs: dict[str, Mapping[str, Any]] = {}
    results: dict[str, Result] = {}

    failed: list[str] = []

    def finish(unit: str, outcome: dict[str, Any]) -> None:
        doc = outcome["document"] if "document" in outcome else {"error": outcome["error"]}
        docs[unit] = doc
        if "error" not in doc:        # built while the workers go on with other units
            results[unit] = Result.from_document(doc, problem, hashes=hashes)
        if on_unit is not None:
            on_unit(unit, doc, outcome.get("report"))
        reason = failure_reason(doc)
        if reason is not None:
            failed.append(unit)
        state = "solved" if reason is None else f"FAILED: {reason}"
        more = f" (failed={len(failed)})" if failed and shown.bar is not None else ""
        shown.step(f"  fleet: {len(docs)}/{len(units)} unit {unit}: {state}{more}")

    with reporting(progress, bars, "fleet", total=len(units), unit="unit") as shown:
        for unit in units:
            if unit.error is not None:
                finish(unit.name, {"error": unit.error})
        if tasks:
            if isinstance(executor, DaskExecutor):
                _run(executor.client, tasks, finish)
            elif executor is not None and not isinstance(executor, str):
                _run(executor, tasks, finish)
            else:
                local = min(workers or usable_cores(), len(tasks))
                with fleet_client(executor, local) as client:
                    _run(client, tasks, finish)
    ordered = {u.name: docs[u.name] for u in units}
    results = {u: results[u] for u in ordered if u in results}
    errors = {u: str(doc["error"]) for u, doc in ordered.items() if "error" in doc}
    return FleetResult(problem, results, errors, summarise(ordered),
                       time.perf_counter() - start)
