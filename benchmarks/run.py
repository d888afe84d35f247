"""symcal's benchmark harness: symcal against what a user would write instead.

Run from the repository root (``make bench`` does)::

    .venv/bin/python benchmarks/run.py                    # full run -> benchmarks/RESULTS.md
    .venv/bin/python benchmarks/run.py --quick --out /tmp/bench.md   # smoke run, N = 1e3

For the §3.1 linear problem and the §3.2 dual problem, on the same simulated data, at
each N it times symcal's default path and the peers of ``benchmarks/peers.py``, each
(method, N) in a fresh subprocess (wall time: median of repeats; peak memory: the
child's peak resident set size).  It skips a peer where its time, projected from the
smaller sizes, would pass the cap, fits the exponent of time against N, checks the
issue's targets and writes the table to ``--out``.  See benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import os
import platform
import resource
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import peers  # noqa: E402  (benchmarks/ is not a package)

MARK = "BENCH-RESULT "
SEED = 1
DEFAULT_SIZES = (1_000, 10_000, 100_000, 1_000_000)

PROBLEMS: dict[str, dict[str, Any]] = {
    "linear": {
        "path": "problems/platen_self_calibration.yaml",
        "scenario": "problems/scenarios/courier_platen.yaml",
        "title": "§3.1 platen self-calibration: linear, 36 parameters, cost Σ g_p²",
        "methods": ("symcal", "floor", "least_squares", "bfgs", "symcal_analysis"),
    },
    "dual": {
        "path": "problems/dual_sensor_calibration.yaml",
        "scenario": "problems/scenarios/courier_dual.yaml",
        "title": "§3.2 dual-sensor calibration: nonlinear, 49 parameters, "
                 "cost Σ g_x² + g_y² + g_p²",
        "methods": ("symcal", "least_squares", "bfgs", "symcal_analysis"),
    },
}

LABELS = {
    "symcal": "symcal (default path)",
    "floor": "numpy Γ + lstsq (floor)",
    "least_squares": "scipy least_squares, FD Jacobian",
    "bfgs": "scipy BFGS, FD gradient",
    "symcal_analysis": "symcal run_stage (solver + stage analysis)",
}
#: Rows that are never skipped: the issue's targets are about them.
UNCAPPED = {"symcal", "floor"}


# =========================================================================== child side


def _rss_now_mib() -> float:
    """Current resident set size of this process (MiB), from /proc (Linux)."""
    try:
        with open("/proc/self/statm") as fh:
            pages = int(fh.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:  # pragma: no cover - not Linux
        return float("nan")


def _peak_rss_mib() -> float:
    """Peak resident set size of this process so far (MiB).

    VmHWM of /proc/self/status: the high-water mark of this address space.  (On Linux
    ``ru_maxrss`` survives ``execve``, so a child would inherit the parent's peak.)
    """
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:  # pragma: no cover - not Linux
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _load_columns(path: str) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as npz:
        return {k: np.asarray(npz[k], dtype=float) for k in npz.files}


def _residual(problem: str):
    return peers.platen_residual if problem == "linear" else peers.dual_residual


def _cost(problem: str, theta: np.ndarray, cols: dict[str, np.ndarray]) -> float:
    r = _residual(problem)(theta, cols)
    return float(r @ r)


def _single_stage_problem(problem: str):
    """The problem file with one stage over every parameter and all constraints."""
    from symcal.problem import build_problem
    from symcal.language.problem import load_problem_spec

    spec = load_problem_spec(ROOT / PROBLEMS[problem]["path"])
    return build_problem(dataclasses.replace(spec, stages=()))


#: Passes over the data made by symcal, counted by wrapping Objective's evaluators, and
#: the Gauss-Newton decrements its IPOPT path tested.
PASSES: dict[str, Any] = {"n": 0, "decrements": [], "by": {}}


def _count_passes() -> None:
    """Count every pass of symcal's Objective over the data (cost, normal equations, R
    factor, residual statistics): the analogue of a peer's residual evaluation.  The
    wrappers only count; they are installed in the benchmark's child process only."""
    from symcal.solvers.objective import Objective

    if getattr(Objective, "_bench_counted", False):
        return
    for name in ("cost", "normal_equations", "accumulate_r", "residual_covariance",
                 "cost_terms"):
        original = getattr(Objective, name)

        def counted(self, *args, _original=original, _name=name, **kwargs):
            PASSES["n"] += 1
            PASSES["by"][_name] = PASSES["by"].get(_name, 0) + 1
            return _original(self, *args, **kwargs)

        setattr(Objective, name, counted)
    Objective._bench_counted = True
    from symcal.solve import nlp

    tested = nlp._Oracle.decrement

    def decrement(self, x, _tested=tested):
        value = _tested(self, x)
        PASSES["decrements"].append(float(value))
        return value

    nlp._Oracle.decrement = decrement


def _symcal_solver(problem: str, cols: dict[str, np.ndarray]):
    """A function theta0 -> (theta, iterations, message, passes) running symcal's
    default path for the single stage: Objective + closed form (linear) or IPOPT."""
    from symcal.calibrate import needed_columns
    from symcal.data import make_dataset
    from symcal.solvers.linear import solve_linear
    from symcal.solvers.nlp import solve_ipopt
    from symcal.solvers.objective import Objective

    _count_passes()
    prob = _single_stage_problem(problem)
    stage = prob.stages[0]
    data = make_dataset("calibration", "benchmark", cols, needed_columns(prob))
    free = np.array([p.name in stage.free for p in prob.parameters])

    def run(theta0: np.ndarray) -> tuple[np.ndarray, int, str, int]:
        PASSES.update(n=0, decrements=[], by={})
        objective = Objective(prob, stage.constraints, free)
        if objective.nonlinear():
            out = solve_ipopt(objective, data, theta0)
        else:
            out = solve_linear(objective, data, theta0)
        return out.theta, out.iterations, f"{out.method}: {out.message}", PASSES["n"]

    return run


def _symcal_analysis(problem: str, cols: dict[str, np.ndarray]):
    """theta0 -> ... running ``symcal.calibrate.run_stage`` (solver + stage analysis)."""
    from symcal.calibrate import needed_columns, run_stage
    from symcal.data import make_dataset

    _count_passes()
    prob = _single_stage_problem(problem)
    data = make_dataset("calibration", "benchmark", cols, needed_columns(prob))

    def run(theta0: np.ndarray) -> tuple[np.ndarray, int, str, int]:
        PASSES.update(n=0, decrements=[], by={})
        theta, result = run_stage(prob, prob.stages[0], data, theta0, weighting="equal")
        return theta, result.iterations, f"{result.method}: {result.message}", PASSES["n"]

    return run


def _peer(problem: str, method: str, cols: dict[str, np.ndarray], cap: float):
    residual = _residual(problem)

    def run(theta0: np.ndarray) -> tuple[np.ndarray, int, str, int]:
        if method == "floor":
            res = peers.numpy_floor(theta0, cols)
        elif method == "least_squares":
            res = peers.least_squares(residual, theta0, cols, max_seconds=cap)
        else:
            res = peers.bfgs(residual, theta0, cols, max_seconds=cap)
        return res.theta, res.iterations, res.message, res.evaluations

    return run


def child_solve(job: dict[str, Any]) -> dict[str, Any]:
    """Time one method on one dataset, ``repeats`` times at most (see ``repeat_budget``)."""
    problem, method = job["problem"], job["method"]
    cols = _load_columns(job["data"])
    theta0 = np.load(job["start"])
    if method == "symcal":
        run = _symcal_solver(problem, cols)
    elif method == "symcal_analysis":
        run = _symcal_analysis(problem, cols)
    else:
        run = _peer(problem, method, cols, job["cap"])
    baseline = _rss_now_mib()
    times: list[float] = []
    out: tuple = ()
    while len(times) < job["repeats"]:
        start = time.perf_counter()
        out = run(theta0.copy())
        times.append(time.perf_counter() - start)
        if sum(times) + times[-1] > job["repeat_budget"]:
            break
    theta, iterations, message = out[:3]
    stopped = "cap" in message
    return {
        "times": times, "seconds": statistics.median(times), "iterations": iterations,
        "evaluations": out[3], "message": message,
        "cost": _cost(problem, theta, cols), "baseline_mib": baseline,
        "peak_mib": _peak_rss_mib(), "theta": [float(v) for v in theta], "stopped": stopped,
        "decrements": list(PASSES["decrements"]) if method == "symcal" else None,
        "passes_by": dict(PASSES["by"]) if method.startswith("symcal") else None,
    }


def child_start(job: dict[str, Any]) -> dict[str, Any]:
    """The common start: the problem's initial values (linear), or symcal's first two
    stages, in closed form with equal weights (dual)."""
    import symcal
    from symcal.calibrate import needed_columns, run_stage
    from symcal.data import make_dataset

    prob = symcal.load_problem(ROOT / PROBLEMS[job["problem"]]["path"])
    theta = np.array([p.value for p in prob.parameters])
    cols = _load_columns(job["data"])
    start = time.perf_counter()
    methods = []
    if job["problem"] == "dual":
        data = make_dataset("calibration", "benchmark", cols, needed_columns(prob))
        for stage in prob.stages[:2]:
            theta, result = run_stage(prob, stage, data, theta, weighting="equal")
            methods.append(result.method)
    seconds = time.perf_counter() - start
    np.save(job["out"], theta)
    return {"seconds": seconds, "methods": methods, "cost": _cost(job["problem"], theta, cols),
            "peak_mib": _peak_rss_mib()}


def child_assemble(job: dict[str, Any]) -> dict[str, Any]:
    """YAML to a ready solver: load and build the problem, make each stage's objective
    and its mapped per-observation functions, and evaluate each once on every chunk
    length N needs (which builds whatever ``symcal.numeric`` builds on first use)."""
    start = time.perf_counter()
    import symcal
    from symcal.numeric import CHUNK, chunks
    from symcal.solvers.objective import Objective

    imported = time.perf_counter()
    prob = symcal.load_problem(ROOT / PROBLEMS[job["problem"]]["path"])
    loaded = time.perf_counter()
    lengths = sorted({s.stop - s.start for s in chunks(job["n"], CHUNK)})
    dummy = np.zeros((len(prob.columns), max(lengths)))
    for stage in prob.stages:
        free = np.array([p.name in stage.free for p in prob.parameters])
        objective = Objective(prob, stage.constraints, free)
        objective.nonlinear()
        theta = np.array([p.value for p in prob.parameters])
        for name, outputs in (("linearised", [objective.g, objective.jac.T]),
                              ("residual", [objective.g])):
            fn = objective._mapped(name, outputs)  # what the solvers build on first use
            for n in lengths:  # one evaluation per chunk length builds what it needs
                fn.chunk(theta, dummy[:, :n])
    done = time.perf_counter()
    return {"import": imported - start, "load": loaded - imported, "assemble": done - loaded,
            "total": done - imported, "stages": len(prob.stages), "chunks": lengths}


def child_profile(job: dict[str, Any]) -> dict[str, Any]:
    """Where symcal's time per pass goes, on one full chunk and on the smallest N.

    Only symcal's public objects and ``Objective``'s evaluators are timed, so the profile
    follows whatever ``symcal.numeric`` does; the cost of building a mapped function is
    taken as the first call minus a repeated call."""
    out: dict[str, Any] = {}
    for problem in ("linear", "dual"):
        for label in ("chunk", "small"):
            try:
                out[f"{problem}/{label}"] = _profile_problem(
                    problem, job[label][problem], job["start"][problem])
            except Exception as exc:  # noqa: BLE001 - a profile must not stop the run
                out[f"{problem}/{label}"] = {"error": f"{type(exc).__name__}: {exc}"}
    return out


def _timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def _profile_problem(problem: str, data_path: str, start_path: str) -> dict[str, Any]:
    from symcal.calibrate import needed_columns
    from symcal.data import make_dataset
    from symcal.solvers.objective import Objective

    prob = _single_stage_problem(problem)
    cols = _load_columns(data_path)
    n = len(next(iter(cols.values())))
    data = make_dataset("calibration", "benchmark", cols, needed_columns(prob))
    theta = np.load(start_path)
    stage = prob.stages[0]
    free = np.array([p.name in stage.free for p in prob.parameters])
    u = data.matrix(prob.columns)

    def fresh() -> Any:
        return Objective(prob, stage.constraints, free)

    objective = fresh()
    rec: dict[str, Any] = {"n": n}
    lin = objective._mapped("linearised", [objective.g, objective.jac.T])
    before = _peak_rss_mib()
    rec["chunk_first"] = _timed(lambda: lin.chunk(theta, u))
    rec["chunk_first_peak_mib"] = _peak_rss_mib() - before
    rec["chunk"] = _best(lambda: lin.chunk(theta, u))
    try:  # the mapped function's work vector, if symcal keeps it where it does today
        entry = lin._maps[max(lin._maps)]
        fn = entry[0] if isinstance(entry, tuple) else entry
        rec["work_mib"] = fn.sz_w() * 8 / 2**20
    except Exception:  # noqa: BLE001 - informative only
        rec["work_mib"] = None
    for name in ("normal_equations", "accumulate_r", "cost"):
        other = fresh()
        first = _timed(lambda o=other, m=name: getattr(o, m)(data, theta))
        rec[name] = _best(lambda o=other, m=name: getattr(o, m)(data, theta))
        rec[f"{name}_first"] = first
    return rec


def _best(fn, repeats: int = 2) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def child_read(job: dict[str, Any]) -> dict[str, Any]:
    """symcal.data.read_table on the CSV and on the NPZ of the same table."""
    from symcal.data import read_table

    out = {}
    for kind in ("csv", "npz"):
        start = time.perf_counter()
        cols = read_table(job[kind])
        out[kind] = time.perf_counter() - start
        out[f"{kind}_rows"] = len(next(iter(cols.values())))
        del cols
    return out


CHILDREN = {"solve": child_solve, "start": child_start, "assemble": child_assemble,
            "profile": child_profile, "read": child_read}


def child_main(spec: str) -> int:
    job = json.loads(spec)
    result = CHILDREN[job["kind"]](job)
    sys.stdout.flush()
    print(MARK + json.dumps(result), flush=True)
    return 0


# =========================================================================== parent side


@dataclasses.dataclass
class Settings:
    sizes: tuple[int, ...]
    repeats: int
    cap: float
    repeat_budget: float
    budget: float
    blas_threads: str | None
    out: Path
    quick: bool


def child_env(threads: str | None) -> dict[str, str]:
    env = dict(os.environ)
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        if threads is None:
            env.pop(var, None)
        else:
            env[var] = threads
    return env


def run_child(job: dict[str, Any], settings: Settings, timeout: float,
              threads: str | None = "settings") -> dict[str, Any]:
    """Run one job in a fresh interpreter; return its result, or {'error': ...}."""
    env = child_env(settings.blas_threads if threads == "settings" else threads)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", json.dumps(job)]
    start = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env,
                              cwd=ROOT)
    except subprocess.TimeoutExpired:
        return {"error": f"killed after the {timeout:.0f} s time limit",
                "wall": time.perf_counter() - start}
    for line in reversed(proc.stdout.splitlines()):
        if line.startswith(MARK):
            result = json.loads(line[len(MARK):])
            result["wall"] = time.perf_counter() - start
            return result
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
    return {"error": f"exit {proc.returncode}: {' | '.join(tail)}",
            "wall": time.perf_counter() - start}


def say(text: str) -> None:
    print(text, flush=True)


def machine() -> dict[str, str]:
    """What the run ran on."""
    info: dict[str, str] = {}
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo")
                   if line.startswith("model name"))
    except (OSError, StopIteration):
        cpu = platform.processor() or "unknown"
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        usable = os.cpu_count() or 0
    info["CPU"] = f"{cpu}; {usable} usable core(s) (os.cpu_count() = {os.cpu_count()})"
    try:
        kib = next(int(line.split()[1]) for line in open("/proc/meminfo")
                   if line.startswith("MemTotal"))
        info["memory"] = f"{kib / 2**20:.1f} GiB"
    except (OSError, StopIteration):
        pass
    info["OS"] = platform.platform()
    import casadi
    import scipy

    info["software"] = (f"Python {platform.python_version()}, numpy {np.__version__}, "
                        f"scipy {scipy.__version__}, casadi {casadi.__version__}")
    try:
        blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
        info["BLAS"] = f"{blas.get('name')} {blas.get('version', '')}".strip()
    except Exception:  # noqa: BLE001 - informative only
        pass
    return info


def code_state() -> dict[str, str]:
    """Which symcal was measured: a hash of symcal/**/*.py, and the git commit (read only)."""
    import hashlib

    digest = hashlib.sha256()
    for path in sorted((ROOT / "symcal").rglob("*.py")):
        digest.update(path.relative_to(ROOT).as_posix().encode())
        digest.update(path.read_bytes())
    state = {"hash": digest.hexdigest()[:12]}
    try:
        state["commit"] = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                                         capture_output=True, text=True,
                                         timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "symcal"], cwd=ROOT,
                               capture_output=True, text=True, timeout=10).stdout.strip()
        state["dirty"] = ", ".join(line[3:] for line in dirty.splitlines())
    except (OSError, subprocess.SubprocessError):
        pass
    return state


def load_average() -> str:
    try:
        return "{:.2f} {:.2f} {:.2f}".format(*os.getloadavg())
    except OSError:  # pragma: no cover
        return "n/a"


def make_data(workdir: Path, sizes: tuple[int, ...]) -> dict[tuple[str, int], dict[str, str]]:
    """Simulate every (problem, N) once; the same file feeds every method."""
    from symcal.data import write_table
    from symcal.simulate import load_scenario, simulate_run

    files = {}
    for problem, info in PROBLEMS.items():
        scenario = load_scenario(ROOT / info["scenario"])
        for n in sizes:
            path = workdir / f"{problem}_{n}.npz"
            write_table(path, simulate_run(scenario, "calibration", seed=SEED, n=n))
            files[(problem, n)] = {"data": str(path), "start": str(workdir /
                                                                 f"{problem}_{n}_start.npy")}
    return files


def check_residuals() -> dict[str, float]:
    """Largest |peer residual − symcal residual| at a perturbed test point, per problem."""
    import casadi as ca

    import symcal
    from symcal.simulate import load_scenario, simulate_run

    out = {}
    for problem, info in PROBLEMS.items():
        prob = symcal.load_problem(ROOT / info["path"])
        cols = simulate_run(load_scenario(ROOT / info["scenario"]), "calibration", seed=7,
                            n=500)
        rng = np.random.default_rng(7)
        theta = np.array([p.value + 0.3 * p.scale * rng.standard_normal()
                          for p in prob.parameters])
        fn = ca.Function("g", [prob.theta, prob.u],
                         [ca.vertcat(*(c.sx / c.sigma for c in prob.constraints))])
        u = np.vstack([cols[c] for c in prob.columns])
        ours = np.asarray(fn.map(500, "serial")(theta, u))
        theirs = _residual(problem)(theta, cols).reshape(len(prob.constraints), -1)
        out[problem] = float(np.abs(ours - theirs).max())
    return out


def projected(history: list[tuple[int, float]], n: int) -> float | None:
    """Time at ``n`` extrapolated linearly from the largest N measured so far."""
    if not history:
        return None
    n1, t1 = history[-1]
    return t1 * n / n1


class Clock:
    """The run's wall-clock budget: capped rows are skipped or stopped to stay within it."""

    def __init__(self, budget: float) -> None:
        self.start = time.perf_counter()
        self.budget = budget

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def left(self) -> float:
        return self.budget - self.elapsed()


def compute_starts(settings: Settings, files: dict, report: dict) -> None:
    """The common start of every (problem, N), in a child (symcal's stages 1-2 for dual)."""
    report["starts"] = {}
    for problem in PROBLEMS:
        for n in settings.sizes:
            job = {"kind": "start", "problem": problem, "data": files[(problem, n)]["data"],
                   "out": files[(problem, n)]["start"]}
            start = run_child(job, settings, timeout=1800)
            if "error" in start:
                raise SystemExit(f"could not compute the start for {problem} N={n}: "
                                 f"{start['error']}")
            report["starts"][(problem, n)] = start
    say("== common starts: " + ", ".join(f"{p} N={fmt_n(n)} {r['seconds']:.2f} s"
                                         for (p, n), r in report["starts"].items()))


def run_benchmarks(settings: Settings, files: dict, report: dict, clock: Clock) -> None:
    """Every (problem, N, method), N ascending; symcal and the floor first at each N."""
    rows: list[dict[str, Any]] = []
    report["rows"] = rows
    history: dict[tuple[str, str], list[tuple[int, float]]] = {}
    dead: dict[tuple[str, str], str] = {}
    for n in settings.sizes:
        for problem, info in PROBLEMS.items():
            for method in info["methods"]:
                key = (problem, method)
                row = {"problem": problem, "n": n, "method": method}
                rows.append(row)
                guess = projected(history.get(key, []), n)
                if key in dead:
                    row["skipped"] = dead[key]
                elif method not in UNCAPPED and guess is not None and guess > settings.cap:
                    row["skipped"] = (f"projected {guess:.0f} s > the {settings.cap:.0f} s "
                                      "cap")
                elif method not in UNCAPPED and guess is not None and guess > clock.left():
                    row["skipped"] = (f"projected {guess:.0f} s would pass the run's "
                                      f"{settings.budget / 60:.0f} min budget")
                if "skipped" in row:
                    say(f"  {problem:6s} N={n:>8} {method:16s} skipped: {row['skipped']}")
                    continue
                stop = (settings.cap if method in UNCAPPED
                        else max(1.0, min(settings.cap, clock.left())))
                job = {"kind": "solve", "problem": problem, "method": method,
                       "data": files[(problem, n)]["data"], "start": files[(problem, n)]["start"],
                       "repeats": settings.repeats if n < 1_000_000 else 1,
                       "repeat_budget": settings.repeat_budget, "cap": stop}
                limit = (max(5 * (guess or 0), 900) if method in UNCAPPED
                         else max(3 * (guess or 0), 3 * stop) + 120)
                result = run_child(job, settings, timeout=limit)
                row.update(result)
                if "error" in result:
                    dead[key] = f"failed at N = {fmt_n(n)}: {result['error']}"
                    say(f"  {problem:6s} N={n:>8} {method:16s} ERROR {result['error']}")
                    continue
                history.setdefault(key, []).append((n, result["seconds"]))
                if result["stopped"]:
                    dead[key] = f"stopped at its cap at N = {fmt_n(n)}"
                iters = "—" if result["iterations"] is None else result["iterations"]
                say(f"  {problem:6s} N={n:>8} {method:16s} {result['seconds']:9.3f} s "
                    f"(median of {len(result['times'])})  peak {result['peak_mib']:6.0f} MiB"
                    f"  iter {iters!s:>4}  passes {result['evaluations']!s:>5}  "
                    f"J = {result['cost']:.12e}{'  STOPPED AT CAP' if result['stopped'] else ''}")


def run_extras(settings: Settings, files: dict, workdir: Path, report: dict) -> None:
    """Load+assemble by N, `symcal simulate` and CSV/NPZ reading at the largest N, the
    profile of symcal's per-chunk evaluation, and the BLAS-threads check."""
    big = max(settings.sizes)
    assemble = {}
    for problem in PROBLEMS:
        for n in settings.sizes:
            assemble[(problem, n)] = run_child({"kind": "assemble", "problem": problem, "n": n},
                                               settings, timeout=300)
    report["assemble"] = assemble
    say("== load + assemble (s): " + ", ".join(
        f"{p} N={fmt_n(n)}: {r.get('total', float('nan')):.3f}"
        for (p, n), r in assemble.items()))

    sim = {}
    for suffix in ("npz", "csv"):
        target = workdir / f"simulated.{suffix}"
        cmd = [sys.executable, "-m", "symcal", "simulate",
               str(ROOT / PROBLEMS["dual"]["scenario"]), "-o", str(target), "-n", str(big),
               "--run", "calibration", "--seed", str(SEED)]
        start = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT,
                              env=child_env(settings.blas_threads))
        sim[suffix] = {"seconds": time.perf_counter() - start, "ok": proc.returncode == 0,
                       "error": proc.stderr.strip()[-300:], "path": str(target),
                       "bytes": target.stat().st_size if target.exists() else 0}
    report["simulate"] = sim
    say(f"== symcal simulate, N={fmt_n(big)}: " + ", ".join(
        f"{k} {v['seconds']:.2f} s" for k, v in sim.items()))
    if sim["csv"]["ok"] and sim["npz"]["ok"]:
        report["read"] = run_child({"kind": "read", "csv": sim["csv"]["path"],
                                    "npz": sim["npz"]["path"]}, settings, timeout=600)
        say(f"== read_table, N={fmt_n(big)}: csv {report['read'].get('csv', float('nan')):.2f} s,"
            f" npz {report['read'].get('npz', float('nan')):.3f} s")
    for suffix in ("npz", "csv"):
        Path(sim[suffix]["path"]).unlink(missing_ok=True)

    from symcal.data import write_table
    from symcal.numeric import CHUNK
    from symcal.simulate import load_scenario, simulate_run

    n_prof = min(big, CHUNK)
    profile_files: dict[str, dict[str, str]] = {"chunk": {}, "small": {}}
    for problem, info in PROBLEMS.items():
        path = workdir / f"profile_{problem}.npz"
        write_table(path, simulate_run(load_scenario(ROOT / info["scenario"]), "calibration",
                                       seed=SEED, n=n_prof))
        profile_files["chunk"][problem] = str(path)
        profile_files["small"][problem] = files[(problem, min(settings.sizes))]["data"]
    starts = {p: files[(p, min(settings.sizes))]["start"] for p in PROBLEMS}
    report["profile"] = run_child({"kind": "profile", **profile_files, "start": starts},
                                  settings, timeout=600)
    say("== profile: " + "; ".join(
        f"{k}: " + ", ".join(f"{m} {v:.3g}" if isinstance(v, float) else f"{m} {v}"
                             for m, v in rec.items())
        for k, rec in report["profile"].items() if isinstance(rec, dict)))

    # BLAS threads: the same jobs pinned to one thread and with the library default.
    n_lin = 100_000 if 100_000 in settings.sizes else min(settings.sizes)
    jobs = (("dual", "symcal", min(settings.sizes)), ("dual", "least_squares",
                                                      min(settings.sizes)),
            ("linear", "symcal", n_lin), ("linear", "floor", n_lin))
    sens = {}
    for label, threads in (("1 thread", "1"), ("BLAS default", None)):
        for problem, method, n in jobs:
            job = {"kind": "solve", "problem": problem, "method": method,
                   "data": files[(problem, n)]["data"], "start": files[(problem, n)]["start"],
                   "repeats": 3, "repeat_budget": 10, "cap": settings.cap}
            sens[(label, problem, method, n)] = run_child(job, settings, timeout=600,
                                                          threads=threads)
    report["blas"] = sens
    say("== BLAS threads: " + ", ".join(
        f"{lab} {p} {m} N={fmt_n(n)}: {r.get('seconds', float('nan')):.3f} s"
        for (lab, p, m, n), r in sens.items()))


# --------------------------------------------------------------------------- analysis


def exponent(points: list[tuple[int, float]]) -> float | None:
    """Slope of log(time) against log(N), least squares."""
    if len(points) < 2:
        return None
    x = np.log([p[0] for p in points])
    y = np.log([p[1] for p in points])
    return float(np.polyfit(x, y, 1)[0])


def measured(rows: list[dict], problem: str, method: str,
             finished: bool = False) -> dict[int, dict]:
    """Rows of one method that ran, by N (``finished``: not stopped at the cap)."""
    return {r["n"]: r for r in rows if r["problem"] == problem and r["method"] == method
            and "seconds" in r and not (finished and r.get("stopped"))}


def exponents(rows: list[dict]) -> dict[tuple[str, str], tuple[float | None, ...]]:
    """Per (problem, method): the exponent of time over all sizes, over N >= 1e4, and of
    time per pass over the data over N >= 1e4 (what is left once iteration counts that
    differ between sizes are divided out)."""
    out = {}
    for problem, info in PROBLEMS.items():
        for method in info["methods"]:
            got = measured(rows, problem, method, finished=True)
            pts = sorted((n, r["seconds"]) for n, r in got.items())
            per_pass = sorted((n, r["seconds"] / r["evaluations"]) for n, r in got.items()
                              if n >= 10_000 and r.get("evaluations"))
            out[(problem, method)] = (exponent(pts), exponent([p for p in pts if p[0] >= 10_000]),
                                      exponent(per_pass))
    return out


def targets(report: dict, settings: Settings) -> list[dict[str, str]]:
    """The issue's targets: measured value, met or missed, and by how much."""
    rows = report["rows"]
    out: list[dict[str, str]] = []
    sym = measured(rows, "dual", "symcal")
    ls = measured(rows, "dual", "least_squares")
    bf = measured(rows, "dual", "bfgs")
    n0 = min(settings.sizes)
    if n0 in sym:
        s = sym[n0]
        for name, peer, want in (("least_squares", ls, 20.0), ("BFGS", bf, 100.0)):
            if n0 not in peer:
                out.append({"target": f"dual, N = {n0}: symcal ≥ {want:g}× faster than {name}",
                            "measured": "peer not measured", "verdict": "not measured"})
                continue
            ratio = peer[n0]["seconds"] / s["seconds"]
            out.append({
                "target": f"dual, N = {n0}: symcal ≥ {want:g}× faster than {name}",
                "measured": f"{ratio:.1f}× ({peer[n0]['seconds']:.3f} s / {s['seconds']:.4f} s)",
                "verdict": "met" if ratio >= want else
                f"missed: {ratio:.1f}× is {want / ratio:.2f}× short (symcal would need "
                f"≤ {peer[n0]['seconds'] / want * 1e3:.1f} ms)"})
            rel = (peer[n0]["cost"] - s["cost"]) / s["cost"]
            out.append({
                "target": f"dual, N = {n0}: same final cost as {name} to 1e-8 relative",
                "measured": f"(J_{name} − J_symcal)/J_symcal = {rel:+.2e}",
                "verdict": "met" if abs(rel) <= 1e-8 else
                ("met by symcal (lower cost; the peer stops short of the minimum)"
                 if rel > 0 else "missed: symcal's cost is higher")})
    lin, floor = measured(rows, "linear", "symcal"), measured(rows, "linear", "floor")
    nb = max(settings.sizes)
    if nb in lin and nb in floor:
        ratio = lin[nb]["seconds"] / floor[nb]["seconds"]
        out.append({"target": f"linear, N = {nb}: symcal within 1.5× of the numpy floor",
                    "measured": f"{ratio:.2f}× ({lin[nb]['seconds']:.2f} s vs "
                                f"{floor[nb]['seconds']:.2f} s)",
                    "verdict": "met" if ratio <= 1.5 else f"missed by {ratio / 1.5:.2f}×"})
    if nb in sym:
        t, mem = sym[nb]["seconds"], sym[nb]["peak_mib"]
        out.append({"target": f"dual, N = {nb}: solved in ≤ 60 s",
                    "measured": f"{t:.1f} s",
                    "verdict": "met" if t <= 60 else f"missed by {t / 60:.2f}×"})
        out.append({"target": f"dual, N = {nb}: peak memory ≤ 2 GiB",
                    "measured": f"{mem:.0f} MiB peak RSS of the whole process",
                    "verdict": "met" if mem <= 2048 else f"missed by {mem / 2048:.2f}×"})
    asm = report.get("assemble", {})
    if asm:
        worst = max(r.get("total", float("inf")) for r in asm.values())
        out.append({"target": "load + assemble (YAML to a ready solver) ≤ 1 s, any N",
                    "measured": f"at most {worst:.3f} s over both problems and every N",
                    "verdict": "met" if worst <= 1 else f"missed by {worst:.2f}×"})
    sim = report.get("simulate", {}).get("npz")
    if sim:
        out.append({"target": f"`symcal simulate` of {nb} observations in seconds",
                    "measured": f"{sim['seconds']:.1f} s to NPZ, "
                                f"{report['simulate']['csv']['seconds']:.1f} s to CSV "
                                "(whole command, interpreter start included)",
                    "verdict": "met" if sim["ok"] and sim["seconds"] < 10 else "missed"})
    read = report.get("read", {})
    if "csv" in read and nb in sym:
        share = read["csv"] / sym[nb]["seconds"]
        out.append({"target": f"reading {nb} rows does not dominate the solve",
                    "measured": f"CSV {read['csv']:.2f} s, NPZ {read['npz']:.3f} s; CSV is "
                                f"{100 * share:.0f} % of the dual solve at N = {nb}",
                    "verdict": "met" if share < 0.5 else "missed"})
    return out


# --------------------------------------------------------------------------- report


def _show(a: float | None) -> str:
    return "—" if a is None else f"{a:.2f}"


def fmt_time(t: float) -> str:
    return f"{t * 1e3:.1f} ms" if t < 1 else f"{t:.2f} s"


def fmt_n(n: int) -> str:
    e = int(round(math.log10(n)))
    return f"1e{e}" if 10**e == n else str(n)


def _row_cells(r: dict, ref: float | None, best: float) -> str:
    label = LABELS[r["method"]]
    n = fmt_n(r["n"])
    if "seconds" not in r:
        why = r.get("skipped") or r.get("error", "")
        return (f"| {n} | {label} | — | — | — | — | — | — | — | — | — | "
                f"**skipped**: {why} |")
    stopped = r.get("stopped")
    shown = ("≥ " if stopped else "") + fmt_time(r["seconds"])
    ratio = "—" if not ref else ("≥ " if stopped else "") + f"{r['seconds'] / ref:.1f}×"
    rel = (r["cost"] - best) / best if best > 0 else 0.0
    note = r["message"]
    if len(note) > 100:
        note = note[:97] + "..."
    iters = "—" if r.get("iterations") is None else str(r["iterations"])
    passes = "—" if r.get("evaluations") is None else str(r["evaluations"])
    return (f"| {n} | {label} | {shown} | {len(r['times'])} | {ratio} | "
            f"{r['peak_mib']:.0f} MiB | {r['peak_mib'] - r['baseline_mib']:.0f} MiB | {iters} | "
            f"{passes} | {r['cost']:.12g} | {rel:.1e} | {note.replace('|', '/')} |")


def render(report: dict, settings: Settings) -> str:
    rows = report["rows"]
    lines = [
        "# symcal benchmarks",
        "",
        f"Produced by `{report['command']}` on {report['date']}; the whole run took "
        f"{report['elapsed'] / 60:.1f} min.  Generated by `benchmarks/run.py`: do not edit "
        "by hand.  [README.md](README.md) says what is measured and how.",
        "",
        "## Machine",
        "",
    ]
    lines += [f"- **{k}**: {v}" for k, v in report["machine"].items()]
    code, end = report["code_start"], report["code_end"]
    where = f"commit {code['commit']}" if code.get("commit") else "no git commit found"
    if code.get("dirty"):
        where += f" with uncommitted changes to {code['dirty']}"
    lines.append(f"- **symcal measured**: {where} (source hash {code['hash']})")
    if end["hash"] != code["hash"]:
        lines.append(f"- **WARNING**: symcal's source changed during the run (hash "
                     f"{code['hash']} → {end['hash']}); the rows mix two versions.")
    lines += [
        f"- **load average** (1, 5, 15 min) at the start: {report['load_start']}; at the end: "
        f"{report['load_end']}.  Other jobs were running on the machine; they slow every "
        "method alike, but absolute times vary by tens of percent from run to run.",
        f"- **BLAS threads in every timed process**: "
        f"{settings.blas_threads or 'library default'} (OPENBLAS_NUM_THREADS, "
        "OMP_NUM_THREADS, MKL_NUM_THREADS; see *BLAS threads* below for why)",
        "",
        "## How it was measured",
        "",
        f"- N = {', '.join(fmt_n(n) for n in settings.sizes)} observations of the scenario's "
        f"`calibration` run, simulated once per problem and N (seed {SEED}) and stored as "
        "NPZ: every method reads the same file.",
        "- Each (method, N) runs in a fresh process.  Wall time: `time.perf_counter` around "
        f"the solve only, median of up to {settings.repeats} runs (1 at N = 1e6; repeats stop "
        f"once they would pass {settings.repeat_budget:.0f} s).",
        "- Peak memory: the peak resident set size (VmHWM) of that process, Python, "
        "libraries and the data included.  Δ is the peak minus the resident size just before "
        "the first timed run: what the method itself added.",
        f"- Caps: a peer (or the `run_stage` row) is not started at a size where its time, "
        f"extrapolated linearly from the previous size, passes {settings.cap:.0f} s, or would "
        f"pass the run's {settings.budget / 60:.1f} min budget; a peer that is started is "
        f"stopped at {settings.cap:.0f} s (shown as ≥).  symcal's default path and the numpy "
        "floor are never skipped.",
        "- Iterations: IPOPT iterations (symcal), trial steps `nfev` (least_squares), `nit` "
        "(BFGS).  Passes: passes over the data, i.e. residual evaluations for the peers "
        "(a finite-difference gradient costs one per parameter) and calls of symcal's "
        "`Objective` evaluators (`cost`, `normal_equations`, `accumulate_r`, ...).",
        "- Final J = Σ g² (mm², equal weights) of every method's estimate, evaluated with the "
        "same numpy residual; 'rel.' is (J − J_best)/J_best at that N.",
        "- The numpy residuals of `peers.py` agree with symcal's at a perturbed test point to "
        + ", ".join(f"{v:.1e} mm ({p})" for p, v in report["residual_check"].items()) + ".",
        "",
    ]
    exps = exponents(rows)
    for problem, info in PROBLEMS.items():
        lines += [f"## {info['title']}", ""]
        if problem == "dual":
            lines += [
                "All methods start from the same vector: symcal's first two stages (platen, "
                "then coordination sensor; closed form, equal weights) on the same data.  "
                "From there they minimise the same single cost over all 49 parameters.  "
                "*symcal (default path)* is `Objective` + `symcal.solvers.nlp.solve_ipopt` "
                "(IPOPT with the Gauss-Newton Hessian and CasADi's exact Jacobian, evaluated "
                "by chunks), which is what `solve()` runs for the problem's `full` stage.  "
                "The `run_stage` row is `symcal.calibrate.run_stage`: the same solve plus the "
                "stage's analysis (R factor at the start, identifiability, sandwich "
                "covariance).",
                "",
            ]
        else:
            lines += [
                "All methods start from the problem's initial values (all zero).  *symcal "
                "(default path)* is `Objective` + `symcal.solvers.linear.solve_linear` (closed "
                "form: residual and Jacobian by chunks, TSQR, minimum-norm step from the SVD "
                "of R).  The floor assembles Γ of eq. (7) with numpy and calls "
                "`numpy.linalg.lstsq` once.  The `run_stage` row adds the stage's analysis.",
                "",
            ]
        lines += ["| N | method | time | runs | × symcal | peak RSS | Δ RSS | "
                  "iterations | passes | final J (mm²) | rel. | note |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for n in settings.sizes:
            here = [r for r in rows if r["problem"] == problem and r["n"] == n]
            ok = [r for r in here if "seconds" in r]
            best = min((r["cost"] for r in ok), default=float("nan"))
            ref = next((r["seconds"] for r in ok if r["method"] == "symcal"), None)
            lines += [_row_cells(r, ref, best) for r in here]
        lines += ["", "Fitted exponent a of time ∝ N^a (least squares on log-log; rows "
                  "stopped at the cap left out):", "",
                  "| method | a, all sizes measured | a, N ≥ 1e4 | a of time per pass, "
                  "N ≥ 1e4 |", "|---|---|---|---|"]
        for method in info["methods"]:
            a_all, a_big, a_pass = exps[(problem, method)]
            lines.append(f"| {LABELS[method]} | {_show(a_all)} | {_show(a_big)} | "
                         f"{_show(a_pass)} |")
        if problem == "dual":
            lines += ["", "The common start (symcal's stages 1–2, closed form, in their own "
                      "process) took " + ", ".join(
                          f"{fmt_time(st['seconds'])} at N = {fmt_n(n)}"
                          for (p, n), st in report["starts"].items() if p == "dual") + "."]
        lines.append("")
    lines += ["## Targets", "", "| target | measured | verdict |", "|---|---|---|"]
    lines += [f"| {t['target']} | {t['measured']} | {t['verdict']} |"
              for t in targets(report, settings)]
    lines += ["", *why_section(report, settings), ""]
    lines += extras_section(report, settings)
    return "\n".join(lines) + "\n"


def _estimate(counts: dict[str, int], prof: dict[str, Any], chunks: int) -> float:
    """Time of symcal's passes: calls of each evaluator × its measured time per chunk."""
    return chunks * sum(counts.get(k, 0) * prof.get(k, 0.0)
                        for k in ("normal_equations", "accumulate_r", "cost"))


def why_section(report: dict, settings: Settings) -> list[str]:
    """Where symcal's time goes, from measurements of this run."""
    prof = report.get("profile", {})
    d, lin = prof.get("dual/chunk", {}), prof.get("linear/chunk", {})
    ds = prof.get("dual/small", {})
    if "chunk" not in d or "chunk" not in lin:
        return ["## Where symcal's time goes", "", f"(profile failed: {prof})"]
    n = d["n"]
    rows = report["rows"]
    sym_dual = measured(rows, "dual", "symcal")
    sym_lin = measured(rows, "linear", "symcal")
    floor = measured(rows, "linear", "floor")
    ls = measured(rows, "dual", "least_squares")
    nb, n0 = max(settings.sizes), min(settings.sizes)
    chunks_big = math.ceil(nb / n)

    def work(r: dict[str, Any]) -> str:
        return "—" if r.get("work_mib") is None else f"{r['work_mib']:.0f} MiB"

    lines = [
        "## Where symcal's time goes",
        "",
        "### 1. One pass over the data",
        "",
        f"symcal evaluates its one-observation CasADi functions over chunks of up to {n} "
        "observations (`symcal.numeric.Mapped`, `CHUNK`).  Per chunk of "
        f"{n} observations in this run (best of 2; *first call* includes building the "
        "mapped function for that chunk length):",
        "",
        "| | dual | linear |",
        "|---|---|---|",
        f"| `Mapped.chunk`, residual + Jacobian | {fmt_time(d['chunk'])} | "
        f"{fmt_time(lin['chunk'])} |",
        f"| … its first call | {fmt_time(d['chunk_first'])} | "
        f"{fmt_time(lin['chunk_first'])} |",
        f"| … peak memory added by the first call | {d['chunk_first_peak_mib']:.0f} MiB | "
        f"{lin['chunk_first_peak_mib']:.0f} MiB |",
        f"| … work vector of the mapped function | {work(d)} | {work(lin)} |",
        f"| `Objective.normal_equations` (residual, Jᵀg, JᵀJ) | "
        f"{fmt_time(d['normal_equations'])} | {fmt_time(lin['normal_equations'])} |",
        f"| `Objective.accumulate_r` (TSQR) | {fmt_time(d['accumulate_r'])} | "
        f"{fmt_time(lin['accumulate_r'])} |",
        f"| `Objective.cost` (residual only) | {fmt_time(d['cost'])} | "
        f"{fmt_time(lin['cost'])} |",
        "",
    ]
    if nb in sym_dual and sym_dual[nb].get("passes_by"):
        t = sym_dual[nb]
        est = _estimate(t["passes_by"], d, chunks_big)
        lines.append(
            f"- Dual, N = {fmt_n(nb)}: {t['seconds']:.1f} s for {t['iterations']} IPOPT "
            f"iterations and {t['evaluations']} passes ({_by(t['passes_by'])}).  Those "
            f"passes at the per-chunk times above, × {chunks_big} chunks, come to "
            f"{est:.1f} s; the rest is building the mapped functions and IPOPT itself.")
    if nb in sym_lin and nb in floor:
        lines.append(
            f"- Linear, N = {fmt_n(nb)}: symcal {sym_lin[nb]['seconds']:.2f} s (one "
            f"`accumulate_r` pass: {chunks_big} chunks × {fmt_time(lin['accumulate_r'])}), "
            f"the numpy floor {floor[nb]['seconds']:.2f} s (building Γ, N × 36, in memory, "
            "then one SVD-based `lstsq`).")
    if n0 in sym_dual and n0 in ls and sym_dual[n0].get("passes_by") and "cost" in ds:
        t, peer = sym_dual[n0], ls[n0]
        est = _estimate(t["passes_by"], ds, 1)
        ratio = peer["seconds"] / t["seconds"]
        lines += [
            "",
            f"### 2. The dual problem at N = {fmt_n(n0)}",
            "",
            f"symcal took {fmt_time(t['seconds'])}: {t['evaluations']} passes "
            f"({_by(t['passes_by'])}) at {fmt_time(ds['normal_equations'])} per "
            f"`normal_equations`, {fmt_time(ds['cost'])} per `cost` and "
            f"{fmt_time(ds['accumulate_r'])} per `accumulate_r` make {fmt_time(est)}.  The "
            f"remaining {fmt_time(max(t['seconds'] - est, 0.0))} is building the mapped "
            "functions of a new `Objective` (first `normal_equations` call: "
            f"{fmt_time(ds['normal_equations_first'])}), creating the IPOPT solver and "
            f"its iterations.  least_squares took {fmt_time(peer['seconds'])} for "
            f"{peer['evaluations']} numpy residual evaluations "
            f"({fmt_time(peer['seconds'] / peer['evaluations'])} each), i.e. "
            f"{ratio:.1f}× symcal's time.",
        ]
        if ratio < 20:
            lines.append(
                f"\nReaching 20× needs symcal at ≤ {fmt_time(peer['seconds'] / 20)}: "
                "fewer passes (IPOPT's line search evaluates the residual separately from "
                "the Jacobian pass at the same point) or less fixed cost per solve.")
    lines += ["", "### 3. IPOPT iterating on rounding noise", ""]
    its = sorted(sym_dual.items())
    lines.append("symcal's dual solve by N: " + "; ".join(
        f"N = {fmt_n(k)}: {r['iterations']} iterations, {r['evaluations']} passes, "
        f"{fmt_time(r['seconds'])}" for k, r in its) + ".")
    stalled = [(k, r) for k, r in its
               if sum(1e-14 <= v < 1e-12 for v in (r.get("decrements") or [])) >= 2]
    if stalled:
        k, r = max(stalled, key=lambda kr: kr[1]["evaluations"])
        lines += [
            "",
            f"At N = {fmt_n(k)}, `symcal.solvers.nlp.solve_ipopt` tested the Gauss-Newton "
            "decrement after every iteration.  It stops when a Gauss-Newton step would "
            "lower the cost by less than `GN_DECREMENT` = 1e-14 of itself, and the "
            "decrement went " + ", ".join(f"{v:.3g}" for v in r["decrements"]) + ".  "
            "Once it hovers just above 1e-14, the cost is flat to rounding.  IPOPT's line "
            "search then finds no decrease and backtracks through many residual-only passes "
            f"per iteration: {r['evaluations']} passes for {r['iterations']} iterations "
            f"here, against {its[0][1]['evaluations']} for {its[0][1]['iterations']} at "
            f"N = {fmt_n(its[0][0])}.  1e-14 is at the level of the rounding error of a "
            "sum of 3N squares.  Whether the decrement stalls depends on the data and on "
            "the order of summation, so symcal's time at one N can be several times that "
            "of its neighbours.  That is also why its fitted exponent over N ≥ 1e4 is "
            "below 1; time per pass is the fairer measure of growth.",
        ]
    else:
        lines.append("\nNo size stalled above the 1e-14 decrement in this run.")
    asm = {k: r for k, r in report.get("assemble", {}).items() if "total" in r}
    if asm:
        (wp, wn), worst = max(asm.items(), key=lambda kv: kv[1]["total"])
        lines += [
            "", "### 4. Building the mapped functions (load + assemble)", "",
            f"The slowest load + assemble was {fmt_time(worst['total'])} ({wp}, "
            f"N = {fmt_n(wn)}, chunk lengths {worst['chunks']}), of which "
            f"{fmt_time(worst['assemble'])} is making the objectives and their mapped "
            "functions: one per stage for the residual and one for the residual + "
            "Jacobian, evaluated once on each chunk length.  The first call of a mapped "
            f"function on {n} observations (dual residual + Jacobian) took "
            f"{fmt_time(d['chunk_first'])} against {fmt_time(d['chunk'])} for a repeated "
            f"call, and on {ds.get('n', '?')} observations the first `normal_equations` "
            f"took {fmt_time(ds.get('normal_equations_first', float('nan')))} against "
            f"{fmt_time(ds.get('normal_equations', float('nan')))}: building a mapped "
            "function costs in proportion to the number of observations it maps."]

    blas = report.get("blas", {})
    one = blas.get(("1 thread", "dual", "symcal", n0), {})
    dflt = blas.get(("BLAS default", "dual", "symcal", n0), {})
    if "seconds" in one and "seconds" in dflt:
        lines += ["", "### 5. BLAS threads", "",
                  f"symcal's dual solve at N = {fmt_n(n0)} took {fmt_time(one['seconds'])} "
                  f"with one BLAS thread and {fmt_time(dflt['seconds'])} with OpenBLAS's "
                  f"default of one thread per core ({dflt['seconds'] / one['seconds']:.1f}×) "
                  "in this run.  symcal reduces every chunk with BLAS on tall, thin matrices "
                  "(`jac.T @ jac` in `Objective.normal_equations`, `scipy.linalg.qr` in "
                  "`Objective.accumulate_r`).  How much the default threads cost depends on "
                  "what else is running on the two cores.  The harness pins every timed "
                  "process, peers included, to one BLAS thread; the last table shows both "
                  "settings."]
    return lines


def _by(counts: dict[str, int]) -> str:
    return ", ".join(f"{v} × `{k}`" for k, v in sorted(counts.items(), key=lambda kv: -kv[1]))


def extras_section(report: dict, settings: Settings) -> list[str]:
    lines = ["## Load and assemble (YAML to a ready solver)", "",
             "`load_problem` (parse and validate the YAML, build the symbolic problem), then "
             "for every stage its `Objective` and its mapped residual and residual + Jacobian "
             "functions, each evaluated once on every chunk length N needs (which builds "
             "what symcal builds on first use), in a fresh process.  `import symcal` is shown "
             "apart and not counted.", "",
             "| problem | N | import symcal | load_problem | objectives + maps | load + assemble |",
             "|---|---|---|---|---|---|"]
    for (problem, n), r in report.get("assemble", {}).items():
        if "total" not in r:
            lines.append(f"| {problem} | {fmt_n(n)} | — | — | — | error: {r.get('error')} |")
            continue
        lines.append(f"| {problem} ({r['stages']} stage(s)) | {fmt_n(n)} | "
                     f"{fmt_time(r['import'])} | {fmt_time(r['load'])} | "
                     f"{fmt_time(r['assemble'])} | **{fmt_time(r['total'])}** |")
    big = max(settings.sizes)
    sim = report.get("simulate", {})
    read = report.get("read", {})
    lines += ["", f"## Data at N = {fmt_n(big)}", "",
              "| step | time | file size |", "|---|---|---|"]
    for kind in ("npz", "csv"):
        if kind in sim:
            s = sim[kind]
            status = "" if s["ok"] else f" (failed: {s['error']})"
            lines.append(f"| `symcal simulate problems/scenarios/courier_dual.yaml --run "
                         f"calibration -n {big} -o X.{kind}` (whole command, interpreter "
                         f"start included){status} | {s['seconds']:.2f} s | "
                         f"{s['bytes'] / 2**20:.0f} MiB |")
    for kind in ("csv", "npz"):
        if kind in read:
            lines.append(f"| `symcal.data.read_table` of that {kind.upper()} "
                         f"({read[f'{kind}_rows']} rows) | {fmt_time(read[kind])} | |")
    blas = report.get("blas", {})
    if blas:
        lines += ["", "## BLAS threads", "",
                  "The same job with OPENBLAS_NUM_THREADS (and OMP_, MKL_) = 1, and with the "
                  "variables unset (OpenBLAS then starts one thread per core).  The harness "
                  "imports numpy before symcal, so a default symcal may set on import does "
                  "not apply here.", "",
                  "| problem | method | N | 1 thread | library default | ratio | iterations "
                  "(1 thread / default) |", "|---|---|---|---|---|---|---|"]
        pairs: dict[tuple[str, str, int], dict[str, Any]] = {}
        for (label, problem, method, n), r in blas.items():
            pairs.setdefault((problem, method, n), {})[label] = r
        for (problem, method, n), got in pairs.items():
            a, b = got.get("1 thread", {}), got.get("BLAS default", {})
            if "seconds" in a and "seconds" in b:
                lines.append(f"| {problem} | {LABELS[method]} | {fmt_n(n)} | "
                             f"{fmt_time(a['seconds'])} | {fmt_time(b['seconds'])} | "
                             f"{b['seconds'] / a['seconds']:.1f}× | {a['iterations']} / "
                             f"{b['iterations']} |")
    return lines


def _plain(obj: Any) -> Any:
    """JSON-ready copy: tuple keys joined with '/'."""
    if isinstance(obj, dict):
        return {"/".join(map(str, k)) if isinstance(k, tuple) else str(k): _plain(v)
                for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    return obj


def atomic_write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: N = 1e3 only, one run each (< 1 min)")
    parser.add_argument("--sizes", help="comma-separated N, e.g. 1e3,1e4 "
                                        "(default 1e3,1e4,1e5,1e6)")
    parser.add_argument("--repeats", type=int, help="runs per (method, N) below 1e6 "
                                                    "(default 3; 1 with --quick)")
    parser.add_argument("--cap", type=float, default=120.0,
                        help="skip a peer whose projected time exceeds this (s, default 120)")
    parser.add_argument("--repeat-budget", type=float, default=20.0,
                        help="stop repeating once the runs would pass this (s, default 20)")
    parser.add_argument("--budget", type=float, default=12.5,
                        help="wall-clock budget of the whole run in minutes: capped rows "
                             "are skipped or stopped to stay within it (default 12.5)")
    parser.add_argument("--blas-threads", default="1",
                        help="BLAS threads in every timed process ('default' leaves the "
                             "library's choice; default 1)")
    parser.add_argument("--out", default=str(HERE / "RESULTS.md"),
                        help="where to write the table (default benchmarks/RESULTS.md)")
    parser.add_argument("--json", help="also write the raw measurements here")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.child:
        return child_main(args.child)
    if args.sizes:
        sizes = tuple(sorted({int(float(s)) for s in args.sizes.split(",") if s.strip()}))
    else:
        sizes = (1_000,) if args.quick else DEFAULT_SIZES
    if not sizes or min(sizes) < 10:
        raise SystemExit("--sizes: give observation counts of at least 10")
    settings = Settings(sizes, args.repeats or (1 if args.quick else 3), args.cap,
                        args.repeat_budget, 60 * args.budget,
                        None if args.blas_threads == "default" else args.blas_threads,
                        Path(args.out), args.quick)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # clean up the data on kill
    clock = Clock(settings.budget)
    given = argv if argv is not None else sys.argv[1:]
    command = ("make bench" if not given else
               "python benchmarks/run.py " + " ".join(given))
    report: dict[str, Any] = {
        "command": command,
        "date": datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z"),
        "machine": machine(), "load_start": load_average(), "code_start": code_state(),
    }
    say(f"symcal benchmarks: N = {', '.join(fmt_n(n) for n in sizes)}; "
        f"machine: {report['machine']['CPU']}; load {report['load_start']}")
    report["residual_check"] = check_residuals()
    say(f"peer residuals vs symcal: {report['residual_check']}")
    if max(report["residual_check"].values()) > 1e-12:
        raise SystemExit("the numpy residuals of benchmarks/peers.py disagree with symcal's")
    with tempfile.TemporaryDirectory(prefix="symcal-bench-") as tmp:
        workdir = Path(tmp)
        files = make_data(workdir, sizes)
        compute_starts(settings, files, report)
        run_extras(settings, files, workdir, report)
        run_benchmarks(settings, files, report, clock)
    report["load_end"] = load_average()
    report["code_end"] = code_state()
    report["elapsed"] = clock.elapsed()
    if report["code_end"]["hash"] != report["code_start"]["hash"]:
        say("WARNING: symcal's source changed during the run; the results mix versions")
    say("\n== fitted exponent of time vs N (all sizes; N >= 1e4; time per pass, N >= 1e4):")
    for (problem, method), (a_all, a_big, a_pass) in exponents(report["rows"]).items():
        say(f"  {problem:6s} {LABELS[method]:44s} {_show(a_all):>5}  {_show(a_big):>5}  "
            f"{_show(a_pass):>5}")
    say("\n== targets:")
    for t in targets(report, settings):
        say(f"  {t['target']}: {t['measured']} -> {t['verdict']}")
    atomic_write(settings.out, render(report, settings))
    if args.json:
        atomic_write(Path(args.json), json.dumps(_plain(report), indent=1, default=str))
    say(f"\nwrote {settings.out} ({report['elapsed'] / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
