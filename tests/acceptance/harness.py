"""The acceptance harness of issue 23: symcal run through its command line, as a user runs it.

For one case of ``cases.yaml`` and one seed, in a fresh workspace holding a copy of the
case's project folders (so that what symcal writes beside a problem lands there, never in
the repository):

1. ``symcal simulate SCENARIO -o data/run.csv --seed S`` (one table per run, the truth);
2. ``symcal solve PROBLEM --data NAME=data/run.NAME.csv ... --json``: exit code, each
   dataset's global test, the free parameters against the truth;
3. ``symcal diagnose ... --json``: the significant candidates and what cannot be
   calibrated; the suggestion it prints (the leading candidate's files, or the robust
   loss when outliers dominate) written where it says and solved with ``--json``;
4. ``symcal improve ... --out improve --json``: exit code, rounds, what was added, quiet,
   ``at_floor``; then ``symcal solve FINAL_PROBLEM ... --json``: each dataset's global
   test, the kept physical parameters and the added terms against the truth.

On clean cases, further seeds run only simulate and diagnose (and improve on some of
them), for the false-alarm rates.  :func:`run` runs cases; :func:`markdown` tabulates
them; ``benchmarks/acceptance.py`` is the command line.
"""

from __future__ import annotations

import fnmatch
import json
import math
import os
import re
import shlex
import shutil
import statistics
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
CASES_FILE = HERE / "cases.yaml"

#: A recovered value is consistent with its truth within this many standard errors.
Z_LIMIT = 3.0
#: improve must reach the floor in at most this many kept rounds (issue 23, item 8).
MAX_ROUNDS = 3
#: What each kind of ending expects (see cases.yaml).
EXPECTS = ("clean", "floor", "structure", "aliased")
#: Environment of every symcal process: one BLAS thread (the machine is shared).
THREADS_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
#: A file header in diagnose's printed YAML: ``# models/x.yaml (beside problem.yaml)``.
_HEADER = re.compile(r"^# (?P<path>\S+\.ya?ml) \(beside (?P<beside>\S+?)\)")


# --------------------------------------------------------------------------- cases


@dataclass(frozen=True)
class Term:
    """The hidden effect's own form, where improve could add it."""

    label: str                      #: regular expression on the round's ``added`` label
    params: str                     #: glob of the parameters that round introduced
    truth: str | dict[str, Any]     #: a name in the truth file, or ``{value, unit}``


@dataclass(frozen=True)
class Case:
    """One acceptance case: a problem on data simulated from a scenario."""

    name: str
    system: str
    problem: str          #: relative to the workspace (the repository's layout)
    scenario: str         #: relative to the repository
    kind: str
    expect: str
    doc: str
    copy: tuple[str, ...]
    datasets: tuple[str, ...]
    terms: tuple[Term, ...] = ()

    @property
    def clean(self) -> bool:
        """Whether the data hold no hidden effect (a false-alarm case)."""
        return self.expect == "clean"


def load_cases(path: Path = CASES_FILE) -> dict[str, Case]:
    """The cases of ``cases.yaml``, by name, checked: known system and ending, files that
    exist."""
    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    systems = doc["systems"]
    out: dict[str, Case] = {}
    for name, entry in doc["cases"].items():
        system = systems[entry["system"]]
        if entry["expect"] not in EXPECTS:
            raise ValueError(f"{path}: case {name}: expect must be one of {EXPECTS}")
        terms = tuple(Term(t["label"], t.get("params", "*"), t["truth"])
                      for t in entry.get("terms", ()))
        case = Case(name, entry["system"], entry["problem"], entry["scenario"],
                    entry["kind"], entry["expect"], entry.get("doc", ""),
                    tuple(system["copy"]), tuple(system["datasets"]), terms)
        for rel in (case.problem, case.scenario):
            if not (ROOT / rel).is_file():
                raise ValueError(f"{path}: case {name}: no file {rel}")
        out[name] = case
    return out


def select(cases: dict[str, Case], patterns: Sequence[str] | None) -> list[Case]:
    """The cases whose names match any of ``patterns`` (globs; all when none), in file
    order."""
    if not patterns:
        return list(cases.values())
    chosen = [c for c in cases.values() if any(fnmatch.fnmatchcase(c.name, p) for p in patterns)]
    unknown = [p for p in patterns if not any(fnmatch.fnmatchcase(n, p) for n in cases)]
    if unknown:
        raise ValueError(f"no case matches {', '.join(unknown)}; cases: {', '.join(cases)}")
    return chosen


# --------------------------------------------------------------------------- the CLI


def symcal_command() -> list[str]:
    """The ``symcal`` command of this interpreter's environment (its console script, or
    ``python -m symcal``)."""
    script = Path(sys.executable).with_name("symcal")
    return [str(script)] if script.is_file() else [sys.executable, "-m", "symcal"]


@dataclass
class Call:
    """One symcal command as run: its arguments, exit code (None on a timeout), output."""

    argv: list[str]
    rc: int | None
    stdout: str
    stderr: str
    seconds: float
    workspace: str = ""

    def command(self) -> str:
        """The command line, the workspace written ``$WS`` and the repository ``.``."""
        text = shlex.join(["symcal", *self.argv])
        if self.workspace:
            text = text.replace(self.workspace, "$WS")
        return text.replace(str(ROOT) + "/", "")

    def message(self) -> str:
        """What the command said went wrong: its JSON error or failed stage, else its
        ``symcal:`` lines on stderr, else the last line that is not progress."""
        doc = self.json() or {}
        if isinstance(doc.get("error"), dict):
            return str(doc["error"].get("message", ""))
        failed = [s for s in doc.get("stages", []) if not s.get("success", True)]
        if failed:
            return f"stage '{failed[0].get('name')}': {failed[0].get('message', '')}"
        lines = [ln.strip() for ln in self.stderr.splitlines() if ln.strip()]
        said = [ln for ln in lines if ln.startswith("symcal")]
        if said:
            return " / ".join(said[-2:])
        rest = [ln for ln in lines if " iteration " not in ln]
        if self.rc is None:
            return "timed out"
        return rest[-1] if rest else ""

    def json(self) -> dict[str, Any] | None:
        """The JSON document the command printed (None when there is none)."""
        try:
            doc = json.loads(self.stdout)
        except json.JSONDecodeError:
            return None
        return doc if isinstance(doc, dict) else None

    def record(self) -> dict[str, Any]:
        """The call as plain data (without its output): ``error`` when it printed an error
        document or, asked for JSON, none."""
        doc = self.json() if "--json" in self.argv else {}
        error = doc is None or "error" in doc
        return {"command": self.command(), "rc": self.rc, "seconds": round(self.seconds, 2),
                "error": error, "message": self.message() if self.rc != 0 or error else ""}


def call(args: Sequence[str], cwd: Path, timeout: float, workspace: Path) -> Call:
    """Run ``symcal ARGS`` in ``cwd``."""
    env = {**os.environ, **THREADS_ENV}
    start = time.perf_counter()
    try:
        proc = subprocess.run([*symcal_command(), *args], cwd=cwd, env=env, text=True,
                              capture_output=True, timeout=timeout, check=False)
        rc: int | None = proc.returncode
        out, err = proc.stdout, proc.stderr
    except subprocess.TimeoutExpired as exc:
        rc = None
        out = exc.stdout if isinstance(exc.stdout, str) else ""
        err = exc.stderr if isinstance(exc.stderr, str) else ""
    return Call(list(args), rc, out, err, time.perf_counter() - start, str(workspace))


# --------------------------------------------------------------------------- truth


#: symcal's own functions used in this process (units, problem files) one thread at a time
#: (its unit registry is created on first use).
_SYMCAL_LOCK = threading.Lock()


def unit_size(unit: str | None) -> float:
    """The size of ``unit`` in symcal's internal units (1 for a plain number)."""
    from symcal.base.units import size

    with _SYMCAL_LOCK:
        return float(size(unit or None))


def truth_value(truth: dict[str, Any], ref: str | dict[str, Any]) -> tuple[float, str] | None:
    """A true value and its unit: a name in the truth document, or ``{value, unit}``."""
    if isinstance(ref, dict):
        return float(ref["value"]), str(ref.get("unit", ""))
    values = truth.get("parameters", {})
    if ref not in values:
        return None
    return float(values[ref]), str(truth.get("units", {}).get(ref, ""))


def zscore(param: dict[str, Any], true: tuple[float, str]) -> float | None:
    """(estimate − truth) / se, in the parameter's unit; None where no standard error."""
    se = param.get("se")
    if param.get("fixed") or se is None or not se > 0 or param.get("value") is None:
        return None
    scale = unit_size(param.get("unit"))
    truth_internal = true[0] * unit_size(true[1])
    return float((param["value"] * scale - truth_internal) / (se * scale))


def check_against_truth(params: dict[str, dict[str, Any]], truth: dict[str, Any],
                        names: Iterable[str]) -> list[dict[str, Any]]:
    """Each named free parameter against its truth (where the truth document has it)."""
    out = []
    for name in names:
        param = params.get(name)
        true = truth_value(truth, name)
        if param is None or true is None or param.get("fixed"):
            continue
        out.append({"name": name, "value": param.get("value"), "se": param.get("se"),
                    "unit": param.get("unit"), "truth": true[0], "truth_unit": true[1],
                    "z": zscore(param, true)})
    return out


# --------------------------------------------------------------------------- documents


def solve_summary(doc: dict[str, Any] | None) -> dict[str, Any]:
    """What a ``solve --json`` document says: success, each dataset's global test and its
    worst statistic against the floor, ``at_floor``, the parameters."""
    if not doc or "statistics" not in doc:
        return {"document": False}
    tests = [{"dataset": t["dataset"], "chi2_dof": t.get("chi2_dof"), "band": t.get("band"),
              "verdict": t.get("verdict")} for t in doc.get("floor_tests", [])]
    worst: dict[str, dict[str, Any]] = {}
    for s in doc["statistics"]:
        c = s.get("chi2_dof")
        if c is None:
            continue
        best = worst.get(s["dataset"])
        if best is None or c > best["chi2_dof"]:
            worst[s["dataset"]] = {"name": s["name"], "kind": s["kind"], "chi2_dof": c,
                                   "floor": s.get("floor"), "std": s["after"]["std"],
                                   "unit": s.get("unit")}
    params = {p["name"]: {k: p.get(k) for k in ("value", "se", "unit", "fixed")}
              for p in doc.get("parameters", [])}
    return {"document": True, "success": bool(doc.get("solver", {}).get("success")),
            "at_floor": doc.get("at_floor"), "floor_tests": tests, "worst": worst,
            "params": params}


def diagnose_summary(doc: dict[str, Any] | None) -> dict[str, Any]:
    """What a ``diagnose --json`` document says."""
    if not doc or "candidates" not in doc:
        return {"document": False}
    significant = [c for c in doc["candidates"] if c.get("significant")]
    calibratable = [c for c in significant if c.get("calibratable", True)]
    outliers = doc.get("outliers") or {}
    return {"document": True, "at_floor": doc.get("at_floor"),
            "significant": [c["label"] for c in calibratable],
            "significant_other": [c["label"] for c in significant if c not in calibratable],
            "uncalibratable": [c["label"] for c in doc.get("uncalibratable", [])],
            "references_apart": len(doc.get("references_apart") or []),
            "outliers_dominate": bool(outliers.get("dominate")),
            "tested": doc.get("tested"),
            "floor_tests": [{"dataset": t["dataset"], "chi2_dof": t.get("chi2_dof"),
                             "band": t.get("band"), "verdict": t.get("verdict")}
                            for t in doc.get("floor_tests", [])],
            "verdict": doc.get("verdict", [])}


def improve_summary(doc: dict[str, Any] | None) -> dict[str, Any]:
    """What an ``improve --json`` document says: rounds kept, what each added, the
    ending."""
    if not doc or "rounds" not in doc:
        return {"document": False}
    rounds = doc["rounds"]
    return {"document": True, "quiet": doc.get("quiet"), "at_floor": doc.get("at_floor"),
            "rounds": max(len(rounds) - 1, 0),
            "added": [r.get("added") for r in rounds[1:]],
            "problems": [r.get("problem") for r in rounds],
            "success": [r.get("success") for r in rounds],
            "final_problem": doc.get("final_problem"),
            "rejected": [r.get("label") for r in doc.get("rejected", [])],
            "aliased": [r.get("label") for r in doc.get("aliased", [])],
            "floor_tests": [{"dataset": t["dataset"], "chi2_dof": t.get("chi2_dof"),
                             "band": t.get("band"), "verdict": t.get("verdict")}
                            for t in (rounds[-1].get("floor_tests") or [])] if rounds else []}


# --------------------------------------------------------------------------- suggestions


def split_suggestion(text: str, problem: Path) -> list[tuple[Path, str]]:
    """The files of a suggestion ``diagnose`` prints, with where it says they go.

    Blocks headed ``# PATH (beside PROBLEM.yaml)`` go to PATH beside the problem.  A text
    without headers is one problem file (the model's own approximation, a variant); it is
    written beside the problem under its ``problem:`` name, or that name with
    ``_diagnose`` when a file of that name exists (never over a file)."""
    blocks: list[tuple[str | None, list[str]]] = []
    for line in text.splitlines():
        m = _HEADER.match(line)
        if m:
            blocks.append((m.group("path"), []))
        elif blocks:
            blocks[-1][1].append(line)
        else:
            blocks.append((None, [line]))
    out = []
    for rel, lines in blocks:
        body = "\n".join(lines).strip() + "\n"
        if rel is None:
            name = (yaml.safe_load(body) or {}).get("problem") or f"{problem.stem}_suggested"
            target = problem.parent / f"{name}.yaml"
            if target.exists():
                target = problem.parent / f"{name}_diagnose.yaml"
        else:
            target = problem.parent / rel
        out.append((target, body))
    return out


def _chain(problem: Path) -> list[tuple[Path, dict[str, Any]]]:
    """A problem file and the files it extends, most derived first."""
    out: list[tuple[Path, dict[str, Any]]] = []
    path: Path | None = problem
    while path is not None and len(out) < 32:
        doc = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
        out.append((path, doc))
        base = doc.get("extends")
        path = (path.parent / base).resolve() if base else None
    return out


def robust_overlay(snippet: str, problem: Path) -> tuple[Path, str]:
    """The robust loss ``diagnose`` asks for when outliers dominate ("add to the problem
    file"), as a user adds it: an overlay of the problem whose constraints keep their
    definitions and gain the loss."""
    wanted = (yaml.safe_load(snippet) or {}).get("constraints", {})
    constraints = {}
    for name, extra in wanted.items():
        definition: dict[str, Any] | None = None
        for _, doc in _chain(problem):
            entry = (doc.get("constraints") or {}).get(name)
            if entry is not None:
                definition = {"expr": entry} if isinstance(entry, str) else dict(entry)
                break
        if definition is None:
            raise ValueError(f"constraint {name} not found in {problem}")
        definition.update(extra)
        constraints[name] = definition
    overlay = {"problem": f"{problem.stem}_robust", "extends": problem.name,
               "constraints": constraints}
    return problem.parent / f"{problem.stem}_robust.yaml", yaml.safe_dump(overlay,
                                                                          sort_keys=False)


# --------------------------------------------------------------------------- one seed


@dataclass
class Settings:
    """How a run goes: seeds, work folder, timeouts."""

    seeds: int = 3                 #: full seeds of every case
    clean_seeds: int = 100         #: seeds of a clean case's diagnose (false alarms)
    clean_improve_seeds: int = 20  #: seeds of a clean case's improve
    #: fewer diagnose seeds for some clean cases (glob -> count), where time is short
    clean_seeds_for: dict[str, int] = field(default_factory=dict)
    seed0: int = 1000              #: the first seed (new seeds: the bundled data use 1)
    jobs: int = 1
    work: Path = field(default_factory=lambda: Path("/tmp/symcal-acceptance"))
    keep: bool = False
    timeout: float = 1800.0


def _data_args(case: Case, data: Path) -> list[str]:
    args = []
    for name in case.datasets:
        args += ["--data", f"{name}={data / f'run.{name}.csv'}"]
    return args


def _workspace(case: Case, seed: int, settings: Settings) -> Path:
    ws = settings.work / case.name / f"seed{seed}"
    if ws.exists():
        shutil.rmtree(ws)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "build")
    for folder in case.copy:
        shutil.copytree(ROOT / folder, ws / folder, ignore=ignore)
    (ws / "data").mkdir(parents=True)
    return ws


def parameter_names(problem: str | Path) -> list[str]:
    """The parameter names of a problem file (bookkeeping: which round added what; one
    build at a time in this process)."""
    from symcal import load_problem

    with _SYMCAL_LOCK:
        return list(load_problem(problem).parameter_names)


def term_checks(case: Case, improve: dict[str, Any], final: dict[str, Any],
                truth: dict[str, Any], new_by_round: list[list[str]]) -> list[dict[str, Any]]:
    """Each kept term of the hidden effect's own form against its truth."""
    out = []
    params = final.get("params", {})
    for term in case.terms:
        for added, new in zip(improve.get("added", []), new_by_round, strict=False):
            if not added or not re.search(term.label, added):
                continue
            for name in new:
                if not fnmatch.fnmatchcase(name, term.params) or name not in params:
                    continue
                true = truth_value(truth, term.truth)
                if true is None:
                    continue
                out.append({"term": term.label, "added": added, "name": name,
                            "value": params[name].get("value"), "se": params[name].get("se"),
                            "unit": params[name].get("unit"), "truth": true[0],
                            "truth_unit": true[1], "z": zscore(params[name], true)})
    return out


def term_checks_of(case: Case, rec: dict[str, Any]) -> list[dict[str, Any]]:
    """The term checks of a recorded seed, against ``case.terms`` as they are now (the
    record's own where it lacks what they read)."""
    final = rec.get("final", {})
    if not isinstance(final.get("added_params"), dict) or "truth" not in rec:
        return list(final.get("terms", []))
    return term_checks(case, rec.get("improve", {}), {"params": final["added_params"]},
                       rec["truth"], final.get("new_by_round", []))


def run_seed(case: Case, seed: int, settings: Settings, full: bool, improve: bool
             ) -> dict[str, Any]:
    """One seed of one case: the commands of the module docstring (``full``: solve and the
    diagnose suggestion too; ``improve``: improve and its final problem)."""
    ws = _workspace(case, seed, settings)
    rec: dict[str, Any] = {"case": case.name, "seed": seed, "full": full, "calls": []}

    def run_cli(*args: str) -> Call:
        c = call(args, ws, settings.timeout, ws)
        rec["calls"].append(c.record())
        return c

    try:
        data = ws / "data"
        sim = run_cli("simulate", str(ROOT / case.scenario), "-o", str(data / "run.csv"),
                      "--seed", str(seed))
        if sim.rc != 0:
            rec["error"] = "simulate failed"
            return rec
        truth = yaml.safe_load((data / "run.truth.yaml").read_text(encoding="utf-8"))
        problem = ws / case.problem
        dargs = _data_args(case, data)
        original: dict[str, Any] = {}
        if full:
            solved = run_cli("solve", str(problem), *dargs, "--json")
            original = solve_summary(solved.json())
            rec["solve"] = {"rc": solved.rc, **original}
            free = [n for n, p in original.get("params", {}).items() if not p.get("fixed")]
            rec["physical"] = free
            rec["solve"]["truth"] = check_against_truth(original.get("params", {}), truth, free)
        diag = run_cli("diagnose", str(problem), *dargs, "--json")
        ddoc = diag.json()
        rec["diagnose"] = {"rc": diag.rc, **diagnose_summary(ddoc)}
        if full and ddoc:
            rec["suggestion"] = _apply_suggestion(ddoc, problem, dargs, run_cli)
        if improve:
            out = ws / "improve"
            imp = run_cli("improve", str(problem), *dargs, "--out", str(out), "--json")
            isum = improve_summary(imp.json())
            isum["trail"] = [ln.strip() for ln in imp.stderr.splitlines()
                             if ln.strip().startswith("round")]
            rec["improve"] = {"rc": imp.rc, **isum}
            final_problem = isum.get("final_problem")
            if full and final_problem and Path(final_problem).is_file():
                fin = run_cli("solve", str(final_problem), *dargs, "--json")
                final = solve_summary(fin.json())
                rec["final"] = {"rc": fin.rc, **{k: v for k, v in final.items()
                                                 if k != "params"}}
                # the original problem's free parameters, and those it fixed that the
                # final problem frees (a fixed parameter found off)
                freed = [n for n, p in original.get("params", {}).items() if p.get("fixed")
                         and not final.get("params", {}).get(n, {}).get("fixed", True)]
                physical = [*rec.get("physical", []), *freed]
                rec["final"]["freed"] = freed
                rec["final"]["truth"] = check_against_truth(final.get("params", {}), truth,
                                                            physical)
                new_by_round = _new_parameters(isum, problem, ws)
                added = sorted(n for n in final.get("params", {}) if n not in set(physical)
                               and n not in original.get("params", {}))
                # what the term checks read, kept so that a saved run can be checked again
                # against edited cases.yaml terms (term_checks_of)
                rec["final"]["added_params"] = {n: final["params"][n] for n in added}
                rec["final"]["new_by_round"] = new_by_round
                rec["truth"] = {"parameters": truth.get("parameters", {}),
                                "units": truth.get("units", {})}
                rec["final"]["terms"] = term_checks(case, isum, final, truth, new_by_round)
    finally:
        if not settings.keep:
            shutil.rmtree(ws, ignore_errors=True)
    return rec


def _new_parameters(isum: dict[str, Any], problem: Path, ws: Path) -> list[list[str]]:
    """The parameters each kept round introduced (from the round files improve wrote)."""
    paths = [problem, *[ws / p for p in isum.get("problems", [])[1:] if p]]
    names = []
    for p in paths:
        try:
            names.append(parameter_names(p))
        except Exception:  # noqa: BLE001 - a round file that does not load is reported
            names.append([])
    return [[n for n in later if n not in set(earlier)]
            for earlier, later in zip(names, names[1:], strict=False)]


def _apply_suggestion(ddoc: dict[str, Any], problem: Path, dargs: list[str],
                      run_cli: Callable[..., Call]) -> dict[str, Any]:
    """Write the suggestion diagnose printed where it says, and solve the problem it
    makes."""
    outliers = ddoc.get("outliers") or {}
    files: list[tuple[Path, str]] = []
    if outliers.get("dominate") and outliers.get("remedy"):
        label = "a robust loss (outliers dominate)"
        files = [robust_overlay(outliers["remedy"], problem)]
    else:
        lead = next((c for c in ddoc.get("candidates", [])
                     if c.get("significant") and c.get("calibratable", True) and c.get("yaml")),
                    None)
        if lead is None:
            return {"label": None}
        label = lead["label"]
        files = split_suggestion(lead["yaml"], problem)
    written = []
    for path, text in files:
        if path.exists():
            return {"label": label, "error": f"would overwrite {path.name}"}
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
        written.append(path)
    target = next((p for p, t in reversed(files) if t.lstrip().startswith("problem:")), None)
    if target is None:
        return {"label": label, "error": "no problem file in the suggestion"}
    solved = run_cli("solve", str(target), *dargs, "--json")
    return {"label": label, "files": [str(p.relative_to(problem.parent)) for p in written],
            "rc": solved.rc, **{k: v for k, v in solve_summary(solved.json()).items()
                                if k != "params"}}


# --------------------------------------------------------------------------- many seeds


def plan(cases: Sequence[Case], settings: Settings) -> list[tuple[Case, int, bool, bool]]:
    """The (case, seed, full, improve) tasks of a run."""
    tasks = []
    for case in cases:
        clean = settings.clean_seeds
        for pattern, n in settings.clean_seeds_for.items():
            if fnmatch.fnmatchcase(case.name, pattern):
                clean = n
        count = max(settings.seeds, clean) if case.clean else settings.seeds
        for i in range(count):
            full = i < settings.seeds
            improve = full or (case.clean and i < settings.clean_improve_seeds)
            tasks.append((case, settings.seed0 + i, full, improve))
    return tasks


def run(cases: Sequence[Case], settings: Settings,
        progress: Callable[[str], None] | None = None,
        sink: Callable[[dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """Every task of :func:`plan`, ``settings.jobs`` at a time; records in task order
    (``sink`` receives each record as it completes)."""
    tasks = plan(cases, settings)
    settings.work.mkdir(parents=True, exist_ok=True)
    done = 0
    lock = threading.Lock()

    def one(task: tuple[Case, int, bool, bool]) -> dict[str, Any]:
        nonlocal done
        case, seed, full, improve = task
        start = time.perf_counter()
        try:
            rec = run_seed(case, seed, settings, full, improve)
        except Exception as exc:  # noqa: BLE001 - one seed's harness error is its record
            rec = {"case": case.name, "seed": seed, "full": full, "calls": [],
                   "error": f"harness: {type(exc).__name__}: {exc}"}
        rec["seconds"] = round(time.perf_counter() - start, 1)
        with lock:
            done += 1
            if sink:
                sink(rec)
            if progress:
                progress(f"[{done}/{len(tasks)}] {case.name} seed {seed}: {brief(rec)} "
                         f"({rec['seconds']:.0f} s)")
        return rec

    with ThreadPoolExecutor(max_workers=max(1, settings.jobs)) as pool:
        return list(pool.map(one, tasks))


def load_records(path: Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The settings and records of a run written by ``benchmarks/acceptance.py``: its
    ``FILE.json`` (``{"settings", "records"}``, or a bare list of records) or the
    ``FILE.jsonl`` it appends to while running (one record a line)."""
    text = path.read_text(encoding="utf-8")
    if path.suffix == ".jsonl":
        return {}, [json.loads(line) for line in text.splitlines() if line.strip()]
    doc = json.loads(text)
    if isinstance(doc, list):
        return {}, doc
    return doc.get("settings", {}), doc["records"]


def settings_of(records: list[dict[str, Any]], given: dict[str, Any]) -> Settings:
    """The settings a table needs (seeds, first seed), from a saved run."""
    full = Counter(r["case"] for r in records if r.get("full"))
    seeds = [r["seed"] for r in records]
    return Settings(seeds=int(given.get("seeds", max(full.values(), default=0))),
                    seed0=int(given.get("seed0", min(seeds, default=0))))


def brief(rec: dict[str, Any]) -> str:
    """One line on one seed."""
    parts = [f"{c['command'].split()[1]} {c['rc']}" for c in rec["calls"]]
    imp = rec.get("improve", {})
    if imp.get("document"):
        parts.append(f"rounds {imp['rounds']} quiet {imp['quiet']}")
    return ", ".join(parts)


# --------------------------------------------------------------------------- verdicts


def physics_ok(rows: list[dict[str, Any]]) -> bool | None:
    """Whether every determined parameter is within Z_LIMIT of its truth (None: none)."""
    zs = [r["z"] for r in rows if r.get("z") is not None]
    return None if not zs else all(abs(z) <= Z_LIMIT for z in zs)


def meets(case: Case, rec: dict[str, Any]) -> bool | None:
    """Whether one full seed ends as ``case.expect`` says an honest tool ends."""
    imp, final = rec.get("improve", {}), rec.get("final", {})
    if not imp.get("document"):
        return False
    rc, quiet, rounds = imp.get("rc"), imp.get("quiet"), imp.get("rounds", 0)
    if case.expect in ("clean", "floor"):
        if not (rc == 0 and quiet and imp.get("at_floor") is True):
            return False
        if case.expect == "clean" and rounds:
            return False
        if rounds > MAX_ROUNDS or physics_ok(final.get("truth", [])) is False:
            return False
        return all(abs(t["z"]) <= Z_LIMIT for t in term_checks_of(case, rec)
                   if t.get("z") is not None)
    if case.expect == "structure":
        return rc == 1 and quiet is False and imp.get("at_floor") is not True
    # aliased: nothing kept in its place (the model's own approximation, which an
    # explicit model on the courier's physics needs whatever else is hidden, is no term
    # in the effect's place)
    from symcal.revise.diagnose import APPROXIMATION

    return rc in (0, 1) and all(a == APPROXIMATION for a in imp.get("added", []) if a)


# --------------------------------------------------------------------------- tables


def _frac(k: int, n: int) -> str:
    return f"{k}/{n}" if n else "–"


def _codes(values: Iterable[Any]) -> str:
    counts = Counter("timeout" if v is None else str(v) for v in values)
    return " ".join(f"{k}×{v}" if v > 1 else k for k, v in sorted(counts.items())) or "–"


def _common(labels: Iterable[str | None], n: int, limit: int = 2, width: int = 70) -> str:
    counts = Counter(lb for lb in labels if lb)
    if not counts:
        return "none"
    parts = []
    for label, k in counts.most_common(limit):
        short = label if len(label) <= width else label[:width - 1] + "…"
        parts.append(f"{_esc(short)} ({k}/{n})")
    more = len(counts) - limit
    return "; ".join(parts) + (f"; +{more} other" if more > 0 else "")


def _esc(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _g(x: float | None, digits: int = 3) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{x:.{digits}g}"


def _floors(records: list[dict[str, Any]], key: str) -> str:
    """Median χ²/dof per dataset over seeds, the band, and how many seeds were at it."""
    by: dict[str, list[dict[str, Any]]] = {}
    for rec in records:
        for t in rec.get(key, {}).get("floor_tests", []):
            by.setdefault(t["dataset"], []).append(t)
    parts = []
    for ds, tests in by.items():
        values = [t["chi2_dof"] for t in tests if t.get("chi2_dof") is not None]
        if not values:
            parts.append(f"{ds} unknown")
            continue
        band = tests[0].get("band") or [math.nan, math.nan]
        at = sum(t.get("verdict") == "at" for t in tests)
        parts.append(f"{ds} {_g(statistics.median(values))} [{band[0]:.2f}–{band[1]:.2f}]"
                     f" at {at}/{len(tests)}")
    return "; ".join(parts) or "–"


def _worst_z(rows: Iterable[dict[str, Any]]) -> str:
    best: dict[str, Any] | None = None
    for r in rows:
        if r.get("z") is not None and (best is None or abs(r["z"]) > abs(best["z"])):
            best = r
    return "–" if best is None else f"{best['name']} {best['z']:+.1f}σ"


def _physics(records: list[dict[str, Any]], key: str) -> str:
    """Seeds whose parameters are all within 3σ, the worst, and how many estimates of all
    seeds lie beyond 3σ (by chance 0.27 % of them: with k parameters a seed passes with
    probability 0.9973^k, 91 % for the platen's 33)."""
    oks = [physics_ok(r.get(key, {}).get("truth", [])) for r in records if key in r]
    judged = [o for o in oks if o is not None]
    rows = [row for r in records for row in r.get(key, {}).get("truth", [])
            if row.get("z") is not None]
    beyond = sum(abs(row["z"]) > Z_LIMIT for row in rows)
    return (f"{_frac(sum(judged), len(judged))} (worst {_worst_z(rows)}; {beyond} of "
            f"{len(rows)} beyond)" if judged else "–")


def _terms(case: Case, records: list[dict[str, Any]]) -> str:
    if not case.terms:
        return "n/a"
    rows = [t for r in records for t in term_checks_of(case, r)]
    if not rows:
        return "not added"
    ok = sum(1 for t in rows if t.get("z") is not None and abs(t["z"]) <= Z_LIMIT)
    zs = ", ".join(f"{t['name']} {_g(t['z'], 2)}σ" for t in rows[:4])
    return f"{ok}/{len(rows)} within 3σ ({zs})"


def hidden_row(case: Case, records: list[dict[str, Any]]) -> str:
    """One Markdown row of a case with full seeds."""
    full = [r for r in records if r["full"]]
    n = len(full)
    diag = [r.get("diagnose", {}) for r in full]
    sugg = [r.get("suggestion", {}) for r in full]
    imp = [r.get("improve", {}) for r in full]
    tops = [(d.get("significant") or [None])[0] if d.get("document") else "(no document)"
            for d in diag]
    if any(d.get("outliers_dominate") for d in diag):
        tops = ["outliers dominate" if d.get("outliers_dominate") else t
                for d, t in zip(diag, tops, strict=True)]
    applied = [s for s in sugg if s.get("label")]
    sugg_text = ("none printed" if not applied else
                 f"rc {_codes(s.get('rc') for s in applied)}, at floor "
                 f"{_frac(sum(s.get('at_floor') is True for s in applied), len(applied))}")
    added = [a for i in imp for a in i.get("added", []) if a]
    rounds = ",".join(str(i.get("rounds", "–")) for i in imp)
    quiet = _frac(sum(i.get("quiet") is True for i in imp), n)
    at_floor = _frac(sum(r.get("final", {}).get("at_floor") is True for r in full), n)
    ok = _frac(sum(meets(case, r) is True for r in full), n)
    cells = [f"`{case.name}`", case.expect,
             _codes(r.get("solve", {}).get("rc") for r in full),
             _common(tops, n, limit=1),
             sugg_text,
             _codes(i.get("rc") for i in imp), rounds, quiet,
             _common(added, n),
             _floors(full, "final"), at_floor,
             _physics(full, "solve"), _physics(full, "final"),
             _terms(case, full), f"**{ok}**"]
    return "| " + " | ".join(cells) + " |"


HIDDEN_HEADER = (
    "| case | expect | solve rc | diagnose: leading candidate | diagnose's suggestion solved |"
    " improve rc | rounds kept | quiet | added | final χ²/dof per dataset [95 % band], seeds at"
    " the floor | final at_floor | physics ≤3σ before | physics ≤3σ after | effect's term vs"
    " truth | meets expect |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")


def clean_row(case: Case, records: list[dict[str, Any]]) -> str:
    """One Markdown row of a clean case's false alarms."""
    diag = [r["diagnose"] for r in records if r.get("diagnose", {}).get("document")]
    n = len(diag)
    sig = sum(bool(d["significant"]) for d in diag)
    other = sum(bool(d["uncalibratable"] or d["significant_other"]) for d in diag)
    outl = sum(d["outliers_dominate"] for d in diag)
    off = sum(d.get("at_floor") is False for d in diag)
    unknown = sum(d.get("at_floor") is None for d in diag)
    imps = [r["improve"] for r in records if "improve" in r]
    not_quiet = sum(i.get("quiet") is not True for i in imps)
    kept = sum(bool(i.get("rounds")) for i in imps)
    full = [r for r in records if r["full"]]
    cells = [f"`{case.name}`", str(n), _frac(sig, n), _frac(other, n), _frac(outl, n),
             _frac(off, n) + (f" ({unknown} unknown)" if unknown else ""),
             str(len(imps)), _frac(not_quiet, len(imps)), _frac(kept, len(imps)),
             _codes(i.get("rc") for i in imps),
             _common((a for i in imps for a in i.get("added", [])), len(imps), limit=1),
             _common((d["significant"][0] for d in diag if d["significant"]), n, limit=1),
             _physics(full, "solve")]
    return "| " + " | ".join(cells) + " |"


CLEAN_HEADER = (
    "| case | diagnose seeds | significant candidate | \"cannot determine\" reported |"
    " outliers dominate | at_floor false | improve seeds | improve not quiet | improve kept a"
    " term | improve rc | kept | most frequent false candidate | physics ≤3σ (solve) |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|---|---|")


def failures(records: list[dict[str, Any]]) -> list[str]:
    """Every command that did not exit as it should (a timeout, a bad-input exit, an
    error document, a failed simulation, diagnosis or solve; improve's exit 1 with its
    document is an ending, not a failure), grouped by command and message."""
    groups: dict[tuple[str, str, str], list[tuple[str, str]]] = {}
    for rec in records:
        if rec.get("error", "").startswith("harness"):
            groups.setdefault(("harness", "-", rec["error"][:400]), []).append(
                (f"{rec['case']}#{rec['seed']}", "(the harness itself)"))
        for c in rec["calls"]:
            verb = c["command"].split()[1]
            if not c.get("error") and (c["rc"] == 0 or (verb == "improve" and c["rc"] == 1)):
                continue
            # one group per message up to its numbers and file names
            shape = re.sub(r"[-+]?\d[\d.e+-]*", "#", c["message"][:400])
            shape = re.sub(r"[\w./]+\.yaml", "F.yaml", shape)
            key = (verb, str(c["rc"]), shape)
            where = f"{rec['case']}#{rec['seed']}"
            groups.setdefault(key, []).append((where, c["command"], c["message"][:400]))
    out = []
    for (verb, rc, _), hits in sorted(groups.items()):
        cases = Counter(w.split("#")[0] for w, _, _ in hits)
        listing = ", ".join(f"{c} ×{k}" for c, k in cases.items())
        where, command, message = hits[0]
        out.append(f"- `{verb}` exit {rc} ({len(hits)} runs: {listing}): {_esc(message)}\n"
                   f"  e.g. `{command}` ({where})")
    return out


def markdown(cases: Sequence[Case], records: list[dict[str, Any]], settings: Settings,
             header: str = "") -> str:
    """The report: the hidden-effect table, the false-alarm table, what failed where."""
    by: dict[str, list[dict[str, Any]]] = {}
    for rec in records:
        by.setdefault(rec["case"], []).append(rec)
    lines = [header] if header else []
    lines += ["## Cases with a hidden effect (and every case's full seeds)", "",
              f"{settings.seeds} seeds per case (seeds {settings.seed0}–"
              f"{settings.seed0 + settings.seeds - 1}); each seed runs simulate, solve,"
              " diagnose (its printed suggestion written and solved), improve and a solve"
              " of improve's final problem. \"physics\" counts seeds whose free parameters"
              " of the original problem (the kept ones after improve) are all within 3"
              " standard errors of the scenario's truth; \"meets expect\" counts seeds that"
              " end as the case's honest ending says (see tests/acceptance/cases.yaml).", "",
              HIDDEN_HEADER]
    for case in cases:
        if case.name in by:
            lines.append(hidden_row(case, by[case.name]))
    clean = [c for c in cases if c.clean and c.name in by]
    if clean:
        lines += ["", "## False alarms on clean data", "",
                  "diagnose's level is 0.01 family-wise (Bonferroni over the candidates"
                  " tested), so a significant candidate should appear on at most about 1 %"
                  " of clean seeds; the global test's band is 95 % per dataset, so"
                  " at_floor false (any dataset outside its band) should appear on about"
                  " 5–10 % of them.", "", CLEAN_HEADER]
        lines += [clean_row(c, by[c.name]) for c in clean]
    fails = failures(records)
    lines += ["", "## What failed where", ""]
    lines += fails or ["nothing: every command exited 0 or 1 where it may"]
    return "\n".join(lines) + "\n"
