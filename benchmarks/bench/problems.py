"""The two problems: simulated data files, their numpy residuals and symcal's problems."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from . import peers
from .config import PROBLEMS, ROOT, SEED, Files

Columns = Mapping[str, np.ndarray]


def load_columns(path: str) -> dict[str, np.ndarray]:
    """The columns of an NPZ data file, as float arrays."""
    with np.load(path, allow_pickle=False) as npz:
        return {k: np.asarray(npz[k], dtype=float) for k in npz.files}


def residual(problem: str) -> Callable[[np.ndarray, Columns], np.ndarray]:
    """The hand-written numpy residual of ``problem`` (``bench.peers``)."""
    return peers.platen_residual if problem == "linear" else peers.dual_residual


def cost(problem: str, theta: np.ndarray, cols: Columns) -> float:
    """J = Σ g² at ``theta``, with the numpy residual: how every method's result is scored."""
    r = residual(problem)(theta, cols)
    return float(r @ r)


def single_stage_problem(problem: str) -> Any:
    """The problem file with one stage over every parameter and all constraints, and
    equal weights: the cost every method minimises."""
    from symcal.language.problem_file import load_problem_spec
    from symcal.problem.build import build_problem

    spec = load_problem_spec(ROOT / PROBLEMS[problem]["path"])
    study = dataclasses.replace(spec.study, stages=())
    return build_problem(dataclasses.replace(spec, study=study)).with_weighting("equal")


def make_data(workdir: Path, sizes: tuple[int, ...]) -> Files:
    """Simulate every (problem, N) once; the same file feeds every method."""
    from symcal.data.dataset import write_table
    from symcal.simulation import load_scenario, simulate_run

    files: Files = {}
    for problem, info in PROBLEMS.items():
        scenario = load_scenario(ROOT / info["scenario"])
        for n in sizes:
            path = workdir / f"{problem}_{n}.npz"
            write_table(path, simulate_run(scenario, "calibration", seed=SEED, n=n))
            files[(problem, n)] = {"data": str(path),
                                   "start": str(workdir / f"{problem}_{n}_start.npy")}
    return files


def check_residuals() -> dict[str, float]:
    """Largest |peer residual − symcal residual| at a perturbed test point, per problem."""
    import casadi as ca

    import symcal
    from symcal.simulation import load_scenario, simulate_run

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
        theirs = residual(problem)(theta, cols).reshape(len(prob.constraints), -1)
        out[problem] = float(np.abs(ours - theirs).max())
    return out
