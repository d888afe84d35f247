"""From the rows to conclusions: fitted exponents of time against N, and the targets."""

from __future__ import annotations

from typing import Any

import numpy as np

from .config import PROBLEMS, Settings

Row = dict[str, Any]


def exponent(points: list[tuple[int, float]]) -> float | None:
    """Slope of log(time) against log(N), least squares (None below two points)."""
    if len(points) < 2:
        return None
    x = np.log([p[0] for p in points])
    y = np.log([p[1] for p in points])
    return float(np.polyfit(x, y, 1)[0])


def measured(rows: list[Row], problem: str, method: str,
             finished: bool = False) -> dict[int, Row]:
    """Rows of one method that ran, by N (``finished``: not stopped at the cap)."""
    return {r["n"]: r for r in rows if r["problem"] == problem and r["method"] == method
            and "seconds" in r and not (finished and r.get("stopped"))}


def exponents(rows: list[Row]) -> dict[tuple[str, str], tuple[float | None, ...]]:
    """Per (problem, method): the exponent of time over all sizes, over N >= 1e4, and of
    time per pass over the data over N >= 1e4 (what is left once iteration counts that
    differ between sizes are divided out)."""
    out: dict[tuple[str, str], tuple[float | None, ...]] = {}
    for problem, info in PROBLEMS.items():
        for method in info["methods"]:
            got = measured(rows, problem, method, finished=True)
            if not got:
                continue
            pts = sorted((n, r["seconds"]) for n, r in got.items())
            per_pass = sorted((n, r["seconds"] / r["evaluations"]) for n, r in got.items()
                              if n >= 10_000 and r.get("evaluations"))
            out[(problem, method)] = (exponent(pts), exponent([p for p in pts if p[0] >= 10_000]),
                                      exponent(per_pass))
    return out


def _speed_targets(sym: dict[int, Row], peers: dict[str, dict[int, Row]],
                   n0: int) -> list[dict[str, str]]:
    """Dual problem at the smallest N: symcal's speed-up over the peers, and equal cost."""
    out: list[dict[str, str]] = []
    s = sym[n0]
    out.append({"target": f"dual, N = {n0}: symcal ≤ 20 ms (issue 16)",
                "measured": f"{s['seconds'] * 1e3:.1f} ms",
                "verdict": "met" if s["seconds"] <= 0.020 else
                f"missed by {s['seconds'] / 0.020:.2f}×"})
    for name, want in (("least_squares", 30.0), ("BFGS", 200.0)):
        peer = peers[name]
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
    return out


def _data_targets(report: dict[str, Any], sym: dict[int, Row],
                  nb: int) -> list[dict[str, str]]:
    """Assembly time, simulation time and reading time."""
    out: list[dict[str, str]] = []
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


def targets(report: dict[str, Any], settings: Settings) -> list[dict[str, str]]:
    """The issue's targets: measured value, met or missed, and by how much."""
    rows = report.get("rows", [])
    out: list[dict[str, str]] = []
    sym = measured(rows, "dual", "symcal")
    n0, nb = min(settings.sizes), max(settings.sizes)
    if n0 in sym:
        out += _speed_targets(sym, {"least_squares": measured(rows, "dual", "least_squares"),
                                    "BFGS": measured(rows, "dual", "bfgs")}, n0)
    lin, floor = measured(rows, "linear", "symcal"), measured(rows, "linear", "floor")
    if n0 in lin and n0 in floor and n0 != nb:
        ratio = lin[n0]["seconds"] / floor[n0]["seconds"]
        out.append({"target": f"linear, N = {n0}: symcal within 1.5× of the numpy floor "
                              "(issue 16)",
                    "measured": f"{ratio:.2f}× ({lin[n0]['seconds'] * 1e3:.2f} ms vs "
                                f"{floor[n0]['seconds'] * 1e3:.2f} ms)",
                    "verdict": "met" if ratio <= 1.5 else f"missed by {ratio / 1.5:.2f}×"})
    if nb in lin and nb in floor:
        ratio = lin[nb]["seconds"] / floor[nb]["seconds"]
        out.append({"target": f"linear, N = {nb}: symcal within 1.5× of the numpy floor",
                    "measured": f"{ratio:.2f}× ({lin[nb]['seconds']:.2f} s vs "
                                f"{floor[nb]['seconds']:.2f} s)",
                    "verdict": "met" if ratio <= 1.5 else f"missed by {ratio / 1.5:.2f}×"})
    if nb in sym:
        t, mem = sym[nb]["seconds"], sym[nb]["peak_mib"]
        out.append({"target": f"dual, N = {nb}: solved in ≤ 10 s on this 2-core machine "
                              "(issue 16)",
                    "measured": f"{t:.1f} s",
                    "verdict": "met" if t <= 10 else f"missed by {t / 10:.2f}×"})
        out.append({"target": f"dual, N = {nb}: peak memory ≤ 1 GiB (issue 16)",
                    "measured": f"{mem:.0f} MiB peak RSS of the whole process",
                    "verdict": "met" if mem <= 1024 else f"missed by {mem / 1024:.2f}×"})
    return out + _data_targets(report, sym, nb) + _startup_targets(report)


def _startup_targets(report: dict[str, Any]) -> list[dict[str, str]]:
    """``symcal --help`` and ``symcal solve`` of the §3.1 problem, whole commands."""
    r = report.get("startup")
    if not r:
        return []
    out = []
    for key, label, limit in (("help", "`symcal --help`", 0.2),
                              ("solve", "`symcal solve` of the bundled §3.1 problem", 0.6)):
        t = r[key]["seconds"]
        out.append({"target": f"{label} ≤ {limit:g} s wall (issue 16)",
                    "measured": f"{t:.2f} s (median, fresh processes)",
                    "verdict": "met" if t <= limit else f"missed by {t / limit:.2f}×"})
    return out
