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
    from symcal.spec.problem import load_problem_spec

    spec = load_problem_spec(ROOT / PROBLEMS[problem]["path"])
    return build_problem(dataclasses.replace(spec, stages=()))


def _symcal_solver(problem: str, cols: dict[str, np.ndarray]):
    """A function theta0 -> (theta, iterations, message) running symcal's default path
    for the single stage: Objective + closed form (linear) or IPOPT (nonlinear)."""
    from symcal.calibrate import needed_columns
    from symcal.data import make_dataset
    from symcal.solve.linear import solve_linear
    from symcal.solve.nlp import solve_ipopt
    from symcal.solve.objective import Objective

    prob = _single_stage_problem(problem)
    stage = prob.stages[0]
    data = make_dataset("calibration", "benchmark", cols, needed_columns(prob))
    free = np.array([p.name in stage.free for p in prob.parameters])

    def run(theta0: np.ndarray) -> tuple[np.ndarray, int, str]:
        objective = Objective(prob, stage.constraints, free)
        if objective.nonlinear():
            out = solve_ipopt(objective, data, theta0)
        else:
            out = solve_linear(objective, data, theta0)
        return out.theta, out.iterations, f"{out.method}: {out.message}"

    return run


def _symcal_analysis(problem: str, cols: dict[str, np.ndarray]):
    """theta0 -> ... running ``symcal.calibrate.run_stage`` (solver + stage analysis)."""
    from symcal.calibrate import needed_columns, run_stage
    from symcal.data import make_dataset

    prob = _single_stage_problem(problem)
    data = make_dataset("calibration", "benchmark", cols, needed_columns(prob))

    def run(theta0: np.ndarray) -> tuple[np.ndarray, int, str]:
        theta, result = run_stage(prob, prob.stages[0], data, theta0, weighting="equal")
        return theta, result.iterations, f"{result.method}: {result.message}"

    return run


def _peer(problem: str, method: str, cols: dict[str, np.ndarray], cap: float):
    residual = _residual(problem)

    def run(theta0: np.ndarray) -> tuple[np.ndarray, int, str, int]:
        if method == "floor":
            res = peers.numpy_floor(theta0, cols)
        elif method == "least_squares":
            res = peers.least_squares(residual, theta0, cols)
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
    return {
        "times": times, "seconds": statistics.median(times), "iterations": int(iterations),
        "evaluations": int(out[3]) if len(out) > 3 else None, "message": message,
        "cost": _cost(problem, theta, cols), "baseline_mib": baseline,
        "peak_mib": _peak_rss_mib(), "theta": [float(v) for v in theta],
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
    and its mapped per-observation functions for the chunk lengths N needs."""
    start = time.perf_counter()
    import symcal
    from symcal.numeric import CHUNK, chunks
    from symcal.solve.objective import Objective

    imported = time.perf_counter()
    prob = symcal.load_problem(ROOT / PROBLEMS[job["problem"]]["path"])
    loaded = time.perf_counter()
    lengths = sorted({s.stop - s.start for s in chunks(job["n"], CHUNK)})
    for stage in prob.stages:
        free = np.array([p.name in stage.free for p in prob.parameters])
        objective = Objective(prob, stage.constraints, free)
        objective.nonlinear()
        for name, outputs in (("linearised", [objective.g, objective.jac.T]),
                              ("residual", [objective.g])):
            fn = objective._mapped(name, outputs)  # what solve_* build on first use
            for n in lengths:
                fn._map(n)
    done = time.perf_counter()
    return {"import": imported - start, "load": loaded - imported, "assemble": done - loaded,
            "total": done - imported, "stages": len(prob.stages), "chunks": lengths}


def child_profile(job: dict[str, Any]) -> dict[str, Any]:
    """Where symcal's time per chunk goes: CasADi's evaluation of the mapped
    residual+Jacobian, versus symcal's conversion of the result to numpy
    (``symcal.numeric.Mapped.chunk``), versus the same evaluation through
    ``casadi.Function.buffer`` into preallocated numpy arrays."""
    return {problem: _profile_problem(problem, job["data"][problem], job["start"][problem])
            for problem in ("linear", "dual")}


def _profile_problem(problem: str, data_path: str, start_path: str) -> dict[str, Any]:
    import casadi as ca

    from symcal.calibrate import needed_columns
    from symcal.data import make_dataset
    from symcal.solve.objective import Objective

    prob = _single_stage_problem(problem)
    cols = _load_columns(data_path)
    n = len(next(iter(cols.values())))
    data = make_dataset("calibration", "benchmark", cols, needed_columns(prob))
    theta = np.load(start_path)
    stage = prob.stages[0]
    objective = Objective(prob, stage.constraints,
                          np.array([p.name in stage.free for p in prob.parameters]))
    u = data.matrix(prob.columns)
    fn = objective._mapped("linearised", [objective.g, objective.jac.T])
    fn.chunk(theta, u)  # build the map once
    before = _peak_rss_mib()
    rec: dict[str, Any] = {"n": n}
    rec["chunk"] = _best(lambda: fn.chunk(theta, u))
    rec["chunk_peak_mib"] = _peak_rss_mib() - before
    mapped = fn._map(n)
    rec["casadi_call"] = _best(lambda: mapped(theta, u))
    outs = mapped(theta, u)
    rec["to_numpy"] = _best(lambda: [np.asarray(o) for o in outs])
    dense = ca.Function("dense", [prob.theta, prob.u],
                        [objective.g, ca.vec(ca.densify(objective.jac.T))])
    shared = dense.map("shared", "serial", n, [0], [])
    g = np.empty((n, objective.g.shape[0]))
    jt = np.empty((n, objective.jac.numel()))
    ut = np.ascontiguousarray(u.T)
    th = np.ascontiguousarray(theta)

    def by_buffer() -> None:
        buf, evaluate = shared.buffer()
        buf.set_arg(0, memoryview(th))
        buf.set_arg(1, memoryview(ut))
        buf.set_res(0, memoryview(g))
        buf.set_res(1, memoryview(jt))
        evaluate()

    rec["buffer"] = _best(by_buffer)
    ref = fn.chunk(theta, u)
    rec["buffer_agrees"] = float(max(np.abs(ref[0] - g).max(), np.abs(ref[1] - jt).max()))
    res = objective._mapped("residual", [objective.g])
    res.chunk(theta, u)
    rec["residual_chunk"] = _best(lambda: res.chunk(theta, u))
    rec["normal_equations"] = _best(lambda: objective.normal_equations(data, theta))
    rec["accumulate_r"] = _best(lambda: objective.accumulate_r(data, theta))
    rec["cost"] = _best(lambda: objective.cost(data, theta))
    return rec


def _best(fn, repeats: int = 3) -> float:
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
    """Time at ``n`` extrapolated from the measured (N, seconds), at least linearly."""
    if not history:
        return None
    n1, t1 = history[-1]
    slope = 1.0
    if len(history) >= 2:
        n0, t0 = history[-2]
        if t0 > 0 and t1 > 0:
            slope = max(1.0, math.log(t1 / t0) / math.log(n1 / n0))
    return t1 * (n / n1) ** slope


def run_benchmarks(settings: Settings, files: dict, report: dict) -> None:
    rows: list[dict[str, Any]] = []
    report["rows"] = rows
    report["starts"] = {}
    for problem, info in PROBLEMS.items():
        say(f"\n== {info['title']}")
        history: dict[str, list[tuple[int, float]]] = {m: [] for m in info["methods"]}
        dead: dict[str, str] = {}
        for n in settings.sizes:
            job = {"kind": "start", "problem": problem, "data": files[(problem, n)]["data"],
                   "out": files[(problem, n)]["start"]}
            start = run_child(job, settings, timeout=1800)
            if "error" in start:
                raise SystemExit(f"could not compute the start for {problem} N={n}: "
                                 f"{start['error']}")
            report["starts"][(problem, n)] = start
            for method in info["methods"]:
                row = {"problem": problem, "n": n, "method": method}
                guess = projected(history[method], n)
                if method in dead:
                    row["skipped"] = dead[method]
                elif method not in UNCAPPED and guess is not None and guess > settings.cap:
                    row["skipped"] = (f"projected {guess:.0f} s > the {settings.cap:.0f} s "
                                      "cap")
                if "skipped" in row:
                    say(f"  N={n:>8} {method:16s} skipped: {row['skipped']}")
                    rows.append(row)
                    continue
                job = {"kind": "solve", "problem": problem, "method": method,
                       "data": files[(problem, n)]["data"], "start": files[(problem, n)]["start"],
                       "repeats": settings.repeats if n < 1_000_000 else 1,
                       "repeat_budget": settings.repeat_budget, "cap": settings.cap}
                limit = (max(3 * (guess or 0), 600) if method in UNCAPPED
                         else 2 * settings.cap + 120)
                result = run_child(job, settings, timeout=limit)
                row.update(result)
                rows.append(row)
                if "error" in result:
                    dead[method] = f"failed at N = {n}: {result['error']}"
                    say(f"  N={n:>8} {method:16s} ERROR {result['error']}")
                    continue
                history[method].append((n, result["seconds"]))
                if method == "bfgs" and "cap" in result["message"]:
                    dead[method] = f"hit the {settings.cap:.0f} s cap at N = {n}"
                say(f"  N={n:>8} {method:16s} {result['seconds']:9.3f} s "
                    f"(median of {len(result['times'])})  peak {result['peak_mib']:7.0f} MiB"
                    f"  iter {result['iterations']:5d}  J = {result['cost']:.12e}")


def run_extras(settings: Settings, files: dict, workdir: Path, report: dict) -> None:
    """Load+assemble by N, `symcal simulate` and CSV/NPZ reading at the largest N, and
    the profile of symcal's per-chunk evaluation."""
    big = max(settings.sizes)
    assemble = {}
    for problem in PROBLEMS:
        for n in settings.sizes:
            assemble[(problem, n)] = run_child({"kind": "assemble", "problem": problem, "n": n},
                                               settings, timeout=300)
    report["assemble"] = assemble
    say("\n== load + assemble (s): " + ", ".join(
        f"{p} N={n}: {r.get('total', float('nan')):.3f}" for (p, n), r in assemble.items()))

    sim = {}
    for suffix in ("npz", "csv"):
        target = workdir / f"simulated.{suffix}"
        cmd = [sys.executable, "-m", "symcal", "simulate", str(ROOT / PROBLEMS["dual"]["scenario"]),
               "-o", str(target), "-n", str(big), "--run", "calibration", "--seed", str(SEED)]
        start = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT,
                              env=child_env(settings.blas_threads))
        sim[suffix] = {"seconds": time.perf_counter() - start, "ok": proc.returncode == 0,
                       "error": proc.stderr.strip()[-300:], "path": str(target),
                       "bytes": target.stat().st_size if target.exists() else 0}
    report["simulate"] = sim
    say(f"== symcal simulate, N={big}: " + ", ".join(
        f"{k} {v['seconds']:.2f} s" for k, v in sim.items()))
    if sim["csv"]["ok"] and sim["npz"]["ok"]:
        report["read"] = run_child({"kind": "read", "csv": sim["csv"]["path"],
                                    "npz": sim["npz"]["path"]}, settings, timeout=600)
        say(f"== read_table, N={big}: csv {report['read'].get('csv', float('nan')):.2f} s, "
            f"npz {report['read'].get('npz', float('nan')):.3f} s")

    n_prof = min(big, 65_536)
    profile_files = {}
    from symcal.data import write_table
    from symcal.simulate import load_scenario, simulate_run

    for problem, info in PROBLEMS.items():
        path = workdir / f"profile_{problem}.npz"
        write_table(path, simulate_run(load_scenario(ROOT / info["scenario"]), "calibration",
                                       seed=SEED, n=n_prof))
        profile_files[problem] = str(path)
    starts = {p: files[(p, min(settings.sizes))]["start"] for p in PROBLEMS}
    report["profile"] = run_child({"kind": "profile", "data": profile_files, "start": starts},
                                  settings, timeout=600)
    say(f"== profile of one chunk of {n_prof}: {json.dumps(report['profile'])}")

    # BLAS threads: the same jobs pinned to one thread and with the library default.
    n_blas = 10_000 if 10_000 in settings.sizes else min(settings.sizes)
    sens = {}
    for label, threads in (("1 thread", "1"), ("BLAS default", None)):
        for problem, method in (("dual", "symcal"), ("linear", "floor"),
                                ("dual", "least_squares")):
            job = {"kind": "solve", "problem": problem, "method": method,
                   "data": files[(problem, n_blas)]["data"],
                   "start": files[(problem, n_blas)]["start"],
                   "repeats": 3, "repeat_budget": 30, "cap": settings.cap}
            sens[(label, problem, method)] = run_child(job, settings, timeout=600,
                                                       threads=threads)
    report["blas"] = {"n": n_blas, "runs": sens}
    say("== BLAS threads: " + ", ".join(
        f"{lab} {p} {m}: {r.get('seconds', float('nan')):.3f} s"
        for (lab, p, m), r in sens.items()))


# --------------------------------------------------------------------------- analysis


def exponent(points: list[tuple[int, float]]) -> float | None:
    """Slope of log(time) against log(N), least squares."""
    if len(points) < 2:
        return None
    x = np.log([p[0] for p in points])
    y = np.log([p[1] for p in points])
    return float(np.polyfit(x, y, 1)[0])


def measured(rows: list[dict], problem: str, method: str) -> dict[int, dict]:
    return {r["n"]: r for r in rows if r["problem"] == problem and r["method"] == method
            and "seconds" in r}


def exponents(rows: list[dict]) -> dict[tuple[str, str], tuple[float | None, float | None]]:
    out = {}
    for problem, info in PROBLEMS.items():
        for method in info["methods"]:
            got = measured(rows, problem, method)
            pts = sorted((n, r["seconds"]) for n, r in got.items())
            out[(problem, method)] = (exponent(pts), exponent([p for p in pts if p[0] >= 10_000]))
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


def render(report: dict, settings: Settings) -> str:
    rows = report["rows"]
    lines = [
        "# symcal benchmarks",
        "",
        f"Produced by `{report['command']}` on {report['date']} "
        f"in {report['elapsed'] / 60:.1f} min.  Do not edit by hand; see "
        "[README.md](README.md) for what is measured and how.",
        "",
        "## Machine",
        "",
    ]
    lines += [f"- **{k}**: {v}" for k, v in report["machine"].items()]
    lines += [
        f"- **load average** (1, 5, 15 min) at the start: {report['load_start']}; at the end: "
        f"{report['load_end']} (other jobs on the machine inflate every time alike)",
        f"- **BLAS threads in every timed process**: "
        f"{settings.blas_threads or 'library default'} (OPENBLAS_NUM_THREADS, "
        "OMP_NUM_THREADS, MKL_NUM_THREADS); see *BLAS threads* below",
        "",
        "## Settings",
        "",
        f"- sizes N = {', '.join(fmt_n(n) for n in settings.sizes)} observations (simulated "
        f"once per problem and N with seed {SEED}, stored as NPZ; every method reads the "
        "same file)",
        f"- wall time: `time.perf_counter` around the solve only, median of up to "
        f"{settings.repeats} runs (1 at N = 1e6; fewer when a run takes long: repeats stop "
        f"once they would pass {settings.repeat_budget:.0f} s); each (method, N) in a fresh "
        "process",
        "- peak memory: peak resident set size (VmHWM) of that process, Python, libraries "
        "and the data included; Δ is the peak minus the resident size just before the first "
        "timed run",
        f"- cap: a peer is skipped at the sizes where its time, extrapolated from the "
        f"smaller ones (at least linearly), passes {settings.cap:.0f} s; BFGS also stops at "
        f"{settings.cap:.0f} s",
        "- final cost J = Σ g² (mm², equal weights) evaluated with the numpy residual of "
        "peers.py for every method; 'rel.' is (J − J_best)/J_best at that N",
        "- peer residuals vs symcal's at a test point: max |difference| "
        + ", ".join(f"{p} {v:.1e} mm" for p, v in report["residual_check"].items()),
        "",
    ]
    exps = exponents(rows)
    for problem, info in PROBLEMS.items():
        lines += [f"## {info['title']}", ""]
        if problem == "dual":
            lines += [
                "All methods start from the same vector: symcal's first two stages (platen, "
                "then coordination sensor; both closed form, equal weights) on the same data. "
                "They then minimise the same single cost over all 49 parameters.  symcal "
                "(default path) = `Objective` + `solve_ipopt` (IPOPT, Gauss-Newton Hessian, "
                "exact Jacobian), which is what `solve()` runs for its `full` stage; the "
                "`run_stage` row adds that stage's analysis (identifiability, conditioning at "
                "the start and end, sandwich covariance).",
                "",
            ]
        else:
            lines += [
                "All methods start from the problem's initial values (all zero).  symcal "
                "(default path) = `Objective` + `solve_linear` (closed form: chunked TSQR, "
                "minimum-norm step); the `run_stage` row adds the stage's analysis.",
                "",
            ]
        lines += ["| N | method | time (median) | runs | × symcal | peak RSS | Δ RSS | "
                  "iterations | evaluations | final J (mm²) | rel. | note |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for n in settings.sizes:
            here = [r for r in rows if r["problem"] == problem and r["n"] == n]
            ok = [r for r in here if "seconds" in r]
            best = min((r["cost"] for r in ok), default=float("nan"))
            ref = next((r["seconds"] for r in ok if r["method"] == "symcal"), None)
            for r in here:
                label = LABELS[r["method"]]
                if "seconds" not in r:
                    why = r.get("skipped") or r.get("error", "")
                    lines.append(f"| {fmt_n(n)} | {label} | — | — | — | — | — | — | — | — | — | "
                                 f"**skipped**: {why} |")
                    continue
                ratio = f"{r['seconds'] / ref:.1f}×" if ref else "—"
                rel = (r["cost"] - best) / best if best > 0 else 0.0
                note = r["message"]
                if len(note) > 90:
                    note = note[:87] + "..."
                evals = "—" if r.get("evaluations") is None else str(r["evaluations"])
                lines.append(
                    f"| {fmt_n(n)} | {label} | {fmt_time(r['seconds'])} | {len(r['times'])} | "
                    f"{ratio} | {r['peak_mib']:.0f} MiB | {r['peak_mib'] - r['baseline_mib']:.0f}"
                    f" MiB | {r['iterations']} | {evals} | {r['cost']:.12g} | {rel:.1e} | "
                    f"{note.replace('|', '/')} |")
        lines += ["", "Fitted exponent of time against N (time ∝ N^a):", ""]
        lines += ["| method | a, all sizes measured | a, N ≥ 1e4 |", "|---|---|---|"]
        for method in info["methods"]:
            a_all, a_big = exps[(problem, method)]
            lines.append(f"| {LABELS[method]} | {_show(a_all)} | {_show(a_big)} |")
        if problem == "dual":
            lines += ["", "The common start (symcal's stages 1–2, closed form) took: " + ", ".join(
                f"N = {fmt_n(n)}: {fmt_time(s['seconds'])}"
                for (p, n), s in report["starts"].items() if p == "dual") + "."]
        lines.append("")
    lines += ["## Targets", "", "| target | measured | verdict |", "|---|---|---|"]
    lines += [f"| {t['target']} | {t['measured']} | {t['verdict']} |"
              for t in targets(report, settings)]
    lines += ["", *why_section(report, settings), ""]
    lines += extras_section(report, settings)
    return "\n".join(lines) + "\n"


def why_section(report: dict, settings: Settings) -> list[str]:
    """Where the time goes, from the profile measured in this run."""
    prof = report.get("profile", {})
    if "dual" not in prof:
        return []
    d, lin = prof["dual"], prof["linear"]
    n = d["n"]
    rows = report["rows"]
    sym_dual = measured(rows, "dual", "symcal")
    sym_lin = measured(rows, "linear", "symcal")
    floor = measured(rows, "linear", "floor")
    nb = max(settings.sizes)
    chunks_big = math.ceil(nb / n)
    lines = [
        "## Why the missed targets are missed (measured in this run)",
        "",
        f"symcal evaluates its one-observation CasADi functions over chunks of up to "
        f"{n} observations (`symcal.numeric.Mapped.chunk`).  On one chunk of {n} "
        "observations (best of 3):",
        "",
        "| | dual problem | linear problem |",
        "|---|---|---|",
        f"| `Mapped.chunk` of residual + Jacobian (what symcal does) | {fmt_time(d['chunk'])} "
        f"| {fmt_time(lin['chunk'])} |",
        f"| of which the CasADi call `Function.map(n)(θ, u)` (numpy → DM in, DM out) | "
        f"{fmt_time(d['casadi_call'])} | {fmt_time(lin['casadi_call'])} |",
        f"| of which `np.asarray(DM)` of the outputs | {fmt_time(d['to_numpy'])} | "
        f"{fmt_time(lin['to_numpy'])} |",
        f"| the same evaluation through `casadi.Function.buffer` into preallocated numpy "
        f"arrays (θ shared, not repeated) | {fmt_time(d['buffer'])} | "
        f"{fmt_time(lin['buffer'])} |",
        f"| max difference buffer vs `Mapped.chunk` | {d['buffer_agrees']:.1e} | "
        f"{lin['buffer_agrees']:.1e} |",
        f"| transient peak RSS added by one `Mapped.chunk` | {d['chunk_peak_mib']:.0f} MiB | "
        f"{lin['chunk_peak_mib']:.0f} MiB |",
        f"| `Objective.normal_equations` (cost, Jᵀg, JᵀJ) over the {n} | "
        f"{fmt_time(d['normal_equations'])} | {fmt_time(lin['normal_equations'])} |",
        f"| `Objective.accumulate_r` (TSQR) over the {n} | {fmt_time(d['accumulate_r'])} | "
        f"{fmt_time(lin['accumulate_r'])} |",
        f"| `Objective.cost` (residual only) over the {n} | {fmt_time(d['cost'])} | "
        f"{fmt_time(lin['cost'])} |",
        "",
    ]
    conv = d["to_numpy"] / d["chunk"] if d["chunk"] else float("nan")
    lines.append(
        f"- The conversion of CasADi's `DM` results to numpy (`np.asarray` → `DM.full()` → "
        f"`DM.elements()`, a Python list of floats) takes {100 * conv:.0f} % of a dual "
        f"chunk, and the whole `Mapped.chunk` is {d['chunk'] / d['buffer']:.1f}× slower "
        f"than the same numbers evaluated through `Function.buffer` "
        f"({d['chunk'] / d['buffer']:.1f}× on the dual, {lin['chunk'] / lin['buffer']:.1f}× on "
        "the linear problem).  This per-chunk overhead, not the solver, is what makes symcal "
        "scale with a large constant.")
    if nb in sym_dual:
        t = sym_dual[nb]
        lines.append(
            f"- Dual, N = {fmt_n(nb)}: {chunks_big} chunks × {fmt_time(d['normal_equations'])} "
            f"per Jacobian pass ≈ {chunks_big * d['normal_equations']:.0f} s for each of the "
            f"{t['iterations'] + 1}+ Jacobian passes IPOPT needs ({t['iterations']} "
            f"iterations), plus residual-only line-search passes and a final TSQR "
            f"({chunks_big * d['accumulate_r']:.0f} s): measured {t['seconds']:.0f} s.  With "
            f"buffer evaluation the Jacobian part would be ≈ {chunks_big * d['buffer']:.0f} s "
            "per pass (extrapolated, not measured end to end).")
    if nb in sym_lin and nb in floor:
        lines.append(
            f"- Linear, N = {fmt_n(nb)}: symcal {sym_lin[nb]['seconds']:.2f} s against the "
            f"floor's {floor[nb]['seconds']:.2f} s; {chunks_big} chunks × "
            f"{fmt_time(lin['accumulate_r'])} of `accumulate_r`, of which "
            f"{fmt_time(lin['chunk'])} is `Mapped.chunk` (buffer evaluation: "
            f"{fmt_time(lin['buffer'])}).")
    blas = report.get("blas", {}).get("runs", {})
    one = blas.get(("1 thread", "dual", "symcal"), {})
    dflt = blas.get(("BLAS default", "dual", "symcal"), {})
    if "seconds" in one and "seconds" in dflt:
        lines.append(
            f"- BLAS threads: symcal's dual solve at N = {fmt_n(report['blas']['n'])} took "
            f"{fmt_time(one['seconds'])} with one BLAS thread and {fmt_time(dflt['seconds'])} "
            f"with OpenBLAS's default ({dflt['seconds'] / one['seconds']:.1f}×).  symcal "
            "reduces every chunk with BLAS (`jac.T @ jac`, `scipy.linalg.qr`) on tall, thin "
            "matrices; with other processes on the two cores OpenBLAS's threads spin-wait "
            "against them.  See the table below.")
    return lines


def extras_section(report: dict, settings: Settings) -> list[str]:
    lines = ["## Load and assemble (YAML to a ready solver)", "",
             "`load_problem` (parse, validate, build the symbolic problem), then for every "
             "stage its `Objective` and the mapped residual and residual+Jacobian functions "
             "for the chunk lengths N needs.  Fresh process each; `import symcal` is shown "
             "apart.", "",
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
              "| step | time | size |", "|---|---|---|"]
    for kind in ("npz", "csv"):
        if kind in sim:
            s = sim[kind]
            status = "" if s["ok"] else f" (failed: {s['error']})"
            lines.append(f"| `symcal simulate courier_dual.yaml --run calibration -n {big} "
                         f"-o X.{kind}` (whole command){status} | {s['seconds']:.2f} s | "
                         f"{s['bytes'] / 2**20:.0f} MiB |")
    for kind in ("csv", "npz"):
        if kind in read:
            lines.append(f"| `symcal.data.read_table` of that {kind.upper()} "
                         f"({read[f'{kind}_rows']} rows) | {fmt_time(read[kind])} | |")
    blas = report.get("blas", {})
    if blas:
        lines += ["", f"## BLAS threads (N = {fmt_n(blas['n'])})", "",
                  "The same job with OPENBLAS/OMP/MKL_NUM_THREADS=1 and with the library "
                  "default (OpenBLAS: one thread per core).", "",
                  "| problem | method | 1 thread | library default | ratio |",
                  "|---|---|---|---|---|"]
        pairs: dict[tuple[str, str], dict[str, Any]] = {}
        for (label, problem, method), r in blas["runs"].items():
            pairs.setdefault((problem, method), {})[label] = r
        for (problem, method), got in pairs.items():
            a, b = got.get("1 thread", {}), got.get("BLAS default", {})
            if "seconds" in a and "seconds" in b:
                lines.append(f"| {problem} | {LABELS[method]} | {fmt_time(a['seconds'])} | "
                             f"{fmt_time(b['seconds'])} | {b['seconds'] / a['seconds']:.1f}× |")
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
    parser.add_argument("--repeat-budget", type=float, default=40.0,
                        help="stop repeating once the runs would pass this (s, default 40)")
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
                        args.repeat_budget,
                        None if args.blas_threads == "default" else args.blas_threads,
                        Path(args.out), args.quick)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # clean up the data on kill
    started = time.perf_counter()
    given = argv if argv is not None else sys.argv[1:]
    command = ("make bench" if not given else
               "python benchmarks/run.py " + " ".join(given))
    report: dict[str, Any] = {
        "command": command,
        "date": datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z"),
        "machine": machine(), "load_start": load_average(),
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
        run_benchmarks(settings, files, report)
        run_extras(settings, files, workdir, report)
    report["load_end"] = load_average()
    report["elapsed"] = time.perf_counter() - started
    say("\n== fitted exponent of time vs N (all sizes; N >= 1e4):")
    for (problem, method), (a_all, a_big) in exponents(report["rows"]).items():
        say(f"  {problem:6s} {LABELS[method]:44s} {_show(a_all):>5}  {_show(a_big):>5}")
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
