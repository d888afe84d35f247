"""Simulating a scenario: the states of each run, the readings, their noise, the truth.

:func:`simulate_run` draws a run's states (:func:`run_states`), evaluates every column's
reading over all samples through the scenario's CasADi graph (:mod:`symcal.simulation.graph`;
``solve`` columns by Newton's method, row by row, on the exact Jacobian), then adds each
column's noise, rounds it to its quantization and adds the slips of active effects.  The
random streams are those of the module docstring of :mod:`symcal.simulation.scenario`.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import casadi as ca
import numpy as np

from symcal.base import jit
from symcal.base.errors import SpecError
from symcal.base.numeric import mapped
from symcal.base.units import size
from symcal.simulation.graph import graph, series_function
from symcal.simulation.scenario import (
    DWELL_STREAM,
    POSE_STREAM,
    SLIP_STREAM,
    Dwells,
    Line,
    Run,
    Scatter,
    Scenario,
    Series,
)

_TOLERANCE = 1e-13
_MAX_ITERATIONS = 60


def stream(seed: int, run_index: int, key: int) -> np.random.Generator:
    """The random generator of stream ``key`` of one run."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(run_index, key)))


def noise_streams(scenario: Scenario) -> list[tuple[int, str, tuple[str, ...]]]:
    """``(key, stream, columns)`` of every noise stream, in the order streams first appear
    among the columns; keys 1, 2, 3, 6, 7, ... (0, 4 and 5 draw states, dwells, slips)."""
    order: dict[str, list[str]] = {}
    for column in scenario.columns:
        if column.stream:
            order.setdefault(column.stream, []).append(column.name)
    keys = [k for k in range(1, len(order) + 4) if k not in (POSE_STREAM, DWELL_STREAM,
                                                            SLIP_STREAM)]
    return [(keys[i], name, tuple(cols)) for i, (name, cols) in enumerate(order.items())]


def _check_counts(seed: int, n: int | None) -> None:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a whole number of at least 0, found {seed!r}")
    if n is not None and (isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1):
        raise ValueError(f"n must be a whole number of at least 1, found {n!r}")


# --------------------------------------------------------------------------- states


def run_count(run: Run, n: int | None = None) -> int:
    """Samples of ``run`` (``n`` overrides the run's own count)."""
    return run.motion.n if n is None else int(n)


def run_states(scenario: Scenario, run: Run, seed: int, n: int | None = None,
               run_index: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The time (s) and the states (``k × n``, internal units) of ``run``'s samples.

    Parameters
    ----------
    scenario, run
        The scenario and one of its runs (or a changed copy of one).
    seed
        Base seed.
    n
        Samples (default: the run's own count).
    run_index
        Position that seeds the streams (default: the run's position by name).
    """
    index = scenario.run_index(run.name) if run_index is None else run_index
    count = run_count(run, n)
    motion = run.motion
    names = [s.name for s in scenario.states]
    values: dict[str, np.ndarray] = {}
    t = run.t0 + run.dt * np.arange(count, dtype=float)
    rng = stream(seed, index, POSE_STREAM)
    if isinstance(motion, Scatter):
        _uniform(values, motion.ranges, rng, count)
        if motion.dwell > 0.0 and motion.dwell_at:
            ends = stream(seed, index, DWELL_STREAM).uniform(size=(count,
                                                                   1 + len(motion.dwell_at)))
            at_end = ends[:, 0] < motion.dwell
            ranges = dict(motion.ranges)
            for j, name in enumerate(motion.dwell_at):
                lo, hi = ranges[name]
                values[name][at_end] = np.where(ends[at_end, 1 + j] < 0.5, lo, hi)
        for name, v in motion.held:
            values[name] = np.full(count, v)
    elif isinstance(motion, Dwells):
        points = math.ceil(count / motion.samples)
        drawn: dict[str, np.ndarray] = {}
        _uniform(drawn, motion.ranges, rng, points)
        for name, column in drawn.items():
            values[name] = np.repeat(column, motion.samples)[:count]
        for name, v in motion.held:
            values[name] = np.full(count, v)
    elif isinstance(motion, Line):
        frac = np.linspace(0.0, 1.0, count) if count > 1 else np.zeros(1)
        end = dict(motion.end)
        for name, a in motion.start:
            values[name] = a + frac * (end[name] - a)
        for name, sigma in motion.jitter:
            if sigma > 0.0:
                values[name] = values[name] + sigma * rng.standard_normal(count)
    else:
        assert isinstance(motion, Series)
        fn = series_function(scenario, motion.exprs)
        got = mapped(ca.SX.sym("none", 1), fn.sx_in(0),
                     [fn(fn.sx_in(0))], "series")(np.zeros(1), t[None, :])[0]
        for j, (name, _) in enumerate(motion.exprs):
            values[name] = got[:, j].copy()
    return t, np.array([values[name] for name in names], dtype=float).reshape(len(names),
                                                                              count)


def _uniform(values: dict[str, np.ndarray], ranges: tuple[tuple[str, tuple[float, float]], ...],
             rng: np.random.Generator, count: int) -> None:
    if not ranges:
        return
    low = tuple(r[0] for _, r in ranges)
    high = tuple(r[1] for _, r in ranges)
    draws = rng.uniform(low, high, size=(count, len(ranges)))
    for j, (name, _) in enumerate(ranges):
        values[name] = draws[:, j].copy()


# --------------------------------------------------------------------------- readings


def _functions(scenario: Scenario) -> dict[str, Any]:
    got = getattr(scenario, "_functions", None)
    if got is not None:
        return got
    g = graph(scenario)
    dummy = ca.SX.sym("none", 1)
    u = ca.vertcat(g.states, g.t, g.unknowns)
    outs = [g.columns[c.name] for c in scenario.columns]
    fns: dict[str, Any] = {"columns": mapped(dummy, u, outs, "scenario_columns")}
    if g.implicit:
        fns["start"] = mapped(dummy, ca.vertcat(g.states, g.t), [g.starts], "scenario_start")
        fns["newton"] = mapped(dummy, u, [g.equations, ca.jacobian(g.equations, g.unknowns)],
                               "scenario_newton")
    object.__setattr__(scenario, "_functions", fns)
    return fns


def _fast(fns: dict[str, Any], samples: int) -> dict[str, Any]:
    """The functions, compiled for a run of many samples as the solvers' passes are
    (:mod:`symcal.base.jit`: the same IEEE operations, so the same readings)."""
    return {k: jit.select(f, samples) for k, f in fns.items()}


def noiseless(scenario: Scenario, t: np.ndarray, states: np.ndarray) -> dict[str, np.ndarray]:
    """Every column's reading, without noise, in its declared unit.

    Raises
    ------
    SpecError
        When the ``solve`` columns do not converge (named, at the first of them).
    """
    fns = _fast(_functions(scenario), t.size)
    base = np.vstack([states, t[None, :]])
    zero = np.zeros(1)
    if "start" in fns:
        z = _solve(scenario, fns, base)
        u = np.vstack([base, z])
    else:
        u = base
    values = fns["columns"](zero, u)
    out = {}
    for j, column in enumerate(scenario.columns):
        factor = size(column.unit)
        v = values[j][:, 0]
        out[column.name] = v if factor == 1.0 else v / factor
    return out


def _solve(scenario: Scenario, fns: dict[str, Any], base: np.ndarray) -> np.ndarray:
    """The ``solve`` columns' readings (``m × n``, internal units), by Newton's method."""
    zero = np.zeros(1)
    z = fns["start"](zero, base)[0]            # n × m
    m = z.shape[1]
    eps = 8.0 * float(np.finfo(float).eps)
    scale = float(np.max(np.abs(z), initial=0.0))
    rows = np.arange(z.shape[0])
    for _ in range(_MAX_ITERATIONS):
        current = z[rows]
        f, jac = fns["newton"](zero, np.vstack([base[:, rows], current.T]))
        jac = jac.reshape(-1, m, m).transpose(0, 2, 1)
        worst = np.max(np.abs(f), axis=1, initial=0.0)
        if not np.all(np.isfinite(worst)):
            break
        # an equation's rounding is of the size of its terms, in its own unit: the
        # readings' part of it, |∂f/∂z|·|z|, at least (a flow in L/min is 1.7e4 mm³/s
        # internally: the absolute tolerance alone was never met, even by a linear one)
        terms = np.max(np.abs(jac) @ np.abs(current)[..., None], axis=(1, 2), initial=0.0)
        open_rows = worst > _TOLERANCE + eps * np.maximum(terms, scale)
        if not np.any(open_rows):
            return z.T
        rows = rows[open_rows]
        try:
            step = np.linalg.solve(jac[open_rows], f[open_rows][..., None])[..., 0]
        except np.linalg.LinAlgError:
            break
        z[rows] = current[open_rows] - step
    first = next(c for c in scenario.columns if c.solve is not None)
    names = ", ".join(c.name for c in scenario.columns if c.solve is not None)
    assert first.solve is not None
    raise SpecError(first.solve.where,
                    f"the readings {names} did not converge: their equations have no single "
                    "root near the start on some samples (a reading must be a monotonic "
                    "function of the state: the equations' derivative by the readings must "
                    "not vanish)")


def slips(scenario: Scenario, count: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """The slips of ``count`` samples by column (its unit): ``+-size`` where a reading
    slipped; draws are row-wise (a prefix for a smaller ``count``)."""
    entries = [(s.column, s.fraction, s.size) for e in scenario.active_effects for s in e.slips]
    order = {c: i for i, c in enumerate(scenario.column_names)}
    entries.sort(key=lambda e: order[e[0]])
    out: dict[str, np.ndarray] = {}
    if not entries:
        return out
    draws = rng.uniform(size=(count, len(entries), 2))
    for i, (column, fraction, amount) in enumerate(entries):
        hit = draws[:, i, 0] < fraction
        jump = out.setdefault(column, np.zeros(count))
        jump[hit] += np.where(draws[hit, i, 1] < 0.5, -amount, amount)
    return out


def simulate_run(scenario: Scenario, run: str, seed: int = 0, n: int | None = None
                 ) -> dict[str, np.ndarray]:
    """Simulate one run of a scenario.

    Parameters
    ----------
    scenario
        The scenario (from :func:`symcal.simulation.load_scenario`).
    run
        Name of the run.
    seed
        Base seed (>= 0); each run and each stream gets its own generator.
    n
        Number of samples, overriding the run's own.

    Returns
    -------
    dict of str to numpy.ndarray
        Every column, in file order, each a 1-D float64 array in the column's unit.

    Raises
    ------
    SpecError
        If there is no such run, or the ``solve`` columns do not converge.
    ValueError
        If ``seed`` or ``n`` is not a valid count.
    """
    _check_counts(seed, n)
    index = scenario.run_index(run)
    t, states = run_states(scenario, scenario.runs[index], seed, n, index)
    count = t.size
    out = noiseless(scenario, t, states)
    columns = {c.name: c for c in scenario.columns}
    for key, _, names in noise_streams(scenario):
        sigmas = [columns[c].noise for c in names]
        if any(s > 0.0 for s in sigmas):
            z = stream(seed, index, key).standard_normal((count, len(names)))
            for j, name in enumerate(names):
                if sigmas[j] > 0.0:
                    out[name] = out[name] + sigmas[j] * z[:, j]
    for column in scenario.columns:
        if column.quantization > 0.0:
            out[column.name] = np.round(out[column.name] / column.quantization) \
                * column.quantization
    for name, jump in slips(scenario, count, stream(seed, index, SLIP_STREAM)).items():
        out[name] = out[name] + jump
    return {c.name: np.ascontiguousarray(out[c.name], dtype=np.float64)
            for c in scenario.columns}


def simulate(scenario: Scenario, seed: int = 0, n: int | None = None
             ) -> dict[str, dict[str, np.ndarray]]:
    """Simulate every run: ``{run: columns}`` (see :func:`simulate_run`)."""
    return {name: simulate_run(scenario, name, seed, n) for name in scenario.run_names}


def slipped_rows(scenario: Scenario, run: str, seed: int = 0, n: int | None = None
                 ) -> dict[str, list[int]]:
    """The rows (from 0) of each slipping column whose reading slipped in one run.

    Parameters
    ----------
    scenario, run, seed, n
        As for :func:`simulate_run`.

    Returns
    -------
    dict
        Column → sorted rows, for every column an active effect slips.
    """
    _check_counts(seed, n)
    index = scenario.run_index(run)
    count = run_count(scenario.runs[index], n)
    jumps = slips(scenario, count, stream(seed, index, SLIP_STREAM))
    return {name: [int(r) for r in np.flatnonzero(jump)] for name, jump in jumps.items()}


# --------------------------------------------------------------------------- truth, noise


def true_values(scenario: Scenario) -> dict[str, tuple[float, str]]:
    """Every true value: the ``truth`` and the values of active effects, as declared
    (value, unit)."""
    out = {v.name: (v.value, v.unit) for v in scenario.truth}
    for effect in scenario.active_effects:
        for v in effect.values:
            out[v.name] = (v.value, v.unit)
    return out


def truth(scenario: Scenario, seed: int | None = None, n: int | None = None) -> dict:
    """The truth of a scenario, as a plain YAML-able dict.

    Parameters
    ----------
    scenario
        The scenario.
    seed, n
        With a seed (and the ``n`` that overrides each run's count), every effect that
        slips lists its slipped rows per run (``rows``).

    Returns
    -------
    dict
        ``scenario`` (name); ``parameters``, the true values of the models' parameters
        (the ``truth`` section) and of every active effect, as declared; ``units`` of
        those that declare one; ``constants``; ``effects``, each with ``on``, ``doc``,
        ``values``, the terms it ``adds`` and its ``slips``; ``noise`` and
        ``quantization`` of every column that has some (its unit).
    """
    values = true_values(scenario)
    effects: dict[str, dict] = {}
    for e in scenario.effects:
        entry: dict[str, Any] = {"on": e.on, "doc": e.doc,
                                 "values": {v.name: v.value for v in e.values},
                                 "adds": {target: spec.text for target, spec in e.add}}
        if e.slips:
            entry["slips"] = {s.column: {"fraction": s.fraction, "size": s.size}
                              for s in e.slips}
            if seed is not None and e.on:
                entry["rows"] = {run: {col: rows for col, rows in
                                       slipped_rows(scenario, run, seed, n).items()
                                       if col in entry["slips"]}
                                 for run in scenario.run_names}
        effects[e.name] = entry
    return {
        "scenario": scenario.name,
        "parameters": {name: float(v) for name, (v, _) in values.items()},
        "units": {name: unit for name, (_, unit) in values.items() if unit},
        "constants": {c.name: c.value for c in scenario.constants},
        "effects": effects,
        "noise": {c.name: c.noise for c in scenario.columns if c.noise > 0},
        "quantization": {c.name: c.quantization for c in scenario.columns
                         if c.quantization > 0},
    }


def input_noise(scenario: Scenario) -> dict[str, float]:
    """Standard deviation of each column's noise (its unit): Gaussian and quantization
    (``sqrt(sigma^2 + q^2 / 12)``); columns' noises are independent of each other."""
    return {c.name: c.sigma for c in scenario.columns}


def quiet(scenario: Scenario) -> Scenario:
    """The scenario without noise or quantization on any column (its random streams as
    they were).  A change made in Python: :meth:`Scenario.overlay` of the result starts
    again from the file's document, noise included."""
    columns = tuple(replace(c, noise=0.0, quantization=0.0) for c in scenario.columns)
    return replace(scenario, columns=columns)
