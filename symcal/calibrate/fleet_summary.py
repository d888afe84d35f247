"""The summary of a fleet: every parameter's distribution over the units, outlier units
with the reason, failed units with theirs.

Works from the units' result documents (``symcal solve --json``, :meth:`Result.to_dict`)
so that it is the same whether the units were solved here or on a Dask cluster, and
plain data in, plain data out (:func:`summarise`).  ``fleetreport.py`` presents it.

The outlier rule is robust, so that the outliers themselves do not hide each other:
for each quantity, a unit's *score* is its distance from the fleet median divided by a
robust spread, 1.4826 × the median absolute deviation (the standard deviation for
normal data).  A unit is an outlier when ``|score| >`` :data:`OUTLIER_SCORE`.

- **Parameters**: the spread is at least the median of the units' standard errors, so a
  fleet that agrees to within its noise flags nobody; parameters a unit cannot
  determine on their own (no standard error: only in combination) are not tested for
  that unit.
- **Residuals**: the RMS of each constraint on each dataset after calibration; only a
  residual *above* the median is an outlier (a better fit is no fault), and the spread is
  at least :data:`RESIDUAL_FLOOR` × the median (a fleet that fits almost equally well
  flags only a unit clearly worse).

No test is made with fewer than :data:`MIN_UNITS` solved units.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from symcal.base.units import symbol

#: Robust scores beyond this make a unit an outlier.
OUTLIER_SCORE = 5.0
#: 1.4826 × the median absolute deviation estimates the standard deviation (normal data).
MAD_TO_SIGMA = 1.4826
#: Fewest solved units for an outlier test.
MIN_UNITS = 3
#: The spread of a residual's RMS over the fleet is at least this fraction of its median.
RESIDUAL_FLOOR = 0.1

#: How the rules read in a report.
RULES = (f"a unit is an outlier when its distance from the fleet median exceeds "
         f"{OUTLIER_SCORE:g} robust spreads (1.4826 x the median absolute deviation; for a "
         "parameter at least the median standard error, for a residual's RMS at least "
         f"{RESIDUAL_FLOOR:g} x its median, and only above it); tested with at least "
         f"{MIN_UNITS} solved units")


def failure_reason(doc: Mapping[str, Any]) -> str | None:
    """Why a unit failed: its error, or its failed stage's message; None if it solved."""
    if "error" in doc:
        return str(doc["error"])
    if doc.get("solver", {}).get("success", False):
        return None
    for stage in doc.get("stages", []):
        if not stage.get("success", True):
            return f"stage '{stage.get('name')}' failed: {stage.get('message')}"
    for check in doc.get("implicit", []):
        if not check.get("contracts", True):
            return (f"implicit definition '{check.get('name')}' does not contract on dataset "
                    f"'{check.get('dataset')}'")
    return "the solve failed"


def _robust(values: np.ndarray) -> tuple[float, float]:
    """Median and 1.4826 × median absolute deviation."""
    median = float(np.median(values))
    return median, MAD_TO_SIGMA * float(np.median(np.abs(values - median)))


def _distribution(values: Mapping[str, float]) -> dict[str, Any]:
    arr = np.array(list(values.values()), dtype=float)
    median, spread = _robust(arr)
    return {"n": len(arr), "median": median, "spread": spread, "mean": float(arr.mean()),
            "std": float(arr.std(ddof=1)) if len(arr) > 1 else 0.0,
            "min": float(arr.min()), "max": float(arr.max()), "values": dict(values)}


def _fmt(x: float, unit: str) -> str:
    return f"{x:.4g}" + (f" {symbol(unit)}" if unit else "")


def _parameter(name: str, rows: Sequence[tuple[str, Mapping[str, Any]]],
               outliers: dict[str, list[dict[str, Any]]]) -> dict[str, Any] | None:
    """The distribution of one parameter over the solved units, and its outliers."""
    if not rows or rows[0][1].get("fixed"):
        return None
    unit = rows[0][1].get("unit") or ""
    out = _distribution({u: float(p["value"]) for u, p in rows})
    out["unit"] = unit
    tested = [(u, p) for u, p in rows if p.get("se") is not None]
    if len(tested) < MIN_UNITS:
        out["tested"] = False
        out["note"] = ("not tested: determined only in combination"
                       if not tested else f"not tested: determined in {len(tested)} unit(s)")
        return out
    values = np.array([float(p["value"]) for _, p in tested])
    median, mad = _robust(values)
    se = float(np.median([float(p["se"]) for _, p in tested]))
    spread = max(mad, se)
    out.update(tested=True, note=None, test_median=median, test_spread=spread)
    if spread <= 0:
        return out
    for (unit_name, _), value in zip(tested, values, strict=True):
        score = (value - median) / spread
        if abs(score) > OUTLIER_SCORE:
            outliers.setdefault(unit_name, []).append({
                "kind": "parameter", "name": name, "dataset": None, "unit": unit,
                "value": float(value), "median": median, "spread": spread,
                "score": float(score),
                "reason": f"parameter {name} = {_fmt(value, unit)} is {abs(score):.1f} robust "
                          f"spreads {'above' if score > 0 else 'below'} the fleet median "
                          f"{_fmt(median, unit)} (spread {_fmt(spread, unit)})"})
    return out


def _residual(name: str, dataset: str, unit: str, values: Mapping[str, float],
              outliers: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    """The distribution of one residual's RMS over the solved units, and its outliers."""
    out = _distribution(values)
    out.update(name=name, dataset=dataset, unit=unit)
    if len(values) < MIN_UNITS:
        out["tested"] = False
        return out
    median, mad = _robust(np.array(list(values.values())))
    spread = max(mad, RESIDUAL_FLOOR * abs(median))
    out.update(tested=True, test_median=median, test_spread=spread)
    if spread <= 0:
        return out
    for unit_name, value in values.items():
        score = (value - median) / spread
        if score > OUTLIER_SCORE:
            outliers.setdefault(unit_name, []).append({
                "kind": "residual", "name": name, "dataset": dataset, "unit": unit,
                "value": value, "median": median, "spread": spread, "score": float(score),
                "reason": f"residual {name} on '{dataset}': RMS {_fmt(value, unit)} after "
                          f"calibration, {value / median:.3g} x the fleet median "
                          f"{_fmt(median, unit)} ({score:.1f} robust spreads above it)"
                          if median > 0 else
                          f"residual {name} on '{dataset}': RMS {_fmt(value, unit)} after "
                          f"calibration against a fleet median {_fmt(median, unit)}"})
    return out


def summarise(units: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """The fleet summary of unit documents.

    Parameters
    ----------
    units
        Unit name → the unit's result document (:meth:`symcal.calibrate.result.Result.to_dict`, as
        ``symcal solve --json`` prints it) or ``{"error": MESSAGE}``.

    Returns
    -------
    dict
        Plain data: ``problem``; ``counts`` (units, solved, failed, outliers);
        ``failed`` (unit → reason); ``outliers`` (unit → list of findings, each with
        ``kind`` ``"parameter"`` or ``"residual"``, ``name``, ``dataset``, ``value``,
        ``median``, ``spread``, ``score`` and ``reason``); ``parameters`` (name → the
        distribution over the solved units: ``n``, ``median``, ``spread``, ``mean``,
        ``std``, ``min``, ``max``, ``values`` by unit, ``unit``, ``tested``, ``note``);
        ``residuals`` (the same for the RMS of each constraint on each dataset after
        calibration, keyed ``"NAME on DATASET"``); ``rules`` (the outlier rule in words).
    """
    failed = {u: r for u, d in units.items() if (r := failure_reason(d)) is not None}
    solved = [u for u in units if u not in failed]
    outliers: dict[str, list[dict[str, Any]]] = {}
    parameters: dict[str, Any] = {}
    residuals: dict[str, Any] = {}
    if solved:
        first = units[solved[0]]
        for i, p in enumerate(first["parameters"]):
            rows = [(u, units[u]["parameters"][i]) for u in solved]
            dist = _parameter(p["name"], rows, outliers)
            if dist is not None:
                parameters[p["name"]] = dist
        series: dict[tuple[str, str], dict[str, float]] = {}
        shown_unit: dict[tuple[str, str], str] = {}
        for u in solved:
            for s in units[u]["statistics"]:
                if s.get("kind") == "constraint" and s["after"].get("rms") is not None:
                    key = (s["name"], s["dataset"])
                    series.setdefault(key, {})[u] = float(s["after"]["rms"])
                    shown_unit[key] = "" if s["unit"] == "(internal)" else s["unit"]
        for (name, dataset), values in series.items():
            residuals[f"{name} on {dataset}"] = _residual(name, dataset,
                                                          shown_unit[(name, dataset)],
                                                          values, outliers)
    problem = next((str(d["problem"]) for d in units.values() if "problem" in d), None)
    ordered = {u: outliers[u] for u in units if u in outliers}
    return {
        "problem": problem,
        "counts": {"units": len(units), "solved": len(solved), "failed": len(failed),
                   "outliers": len(ordered)},
        "failed": failed,
        "outliers": ordered,
        "parameters": parameters,
        "residuals": residuals,
        "rules": RULES if len(solved) >= MIN_UNITS else
        f"no outlier test: fewer than {MIN_UNITS} units solved",
    }
