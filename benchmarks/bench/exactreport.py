"""RESULTS.md's comparison with the exact-Jacobian peers (issue 26): ratios, memory and
targets, for the public ``symcal.solve`` and for the solver stage."""

from __future__ import annotations

from typing import Any

from .analysis import Row, measured
from .config import EXACT_PEERS, LABELS, PROBLEMS, Settings
from .fmt import fmt_n, fmt_time

#: Issue 26's targets.
SPEEDUP = 3.0
MEMORY = 10.0
BIG_SECONDS = 5.0
#: A peer reached the minimum when its J is within this fraction of the lowest at that N.
SAME_J = 1e-10


def _best_peer(rows: list[Row], problem: str, n: int) -> tuple[str, Row] | None:
    """The fastest exact-Jacobian peer (warm) that reached the minimum at N = n."""
    best: tuple[str, Row] | None = None
    lowest = min((r["cost"] for r in rows if r["problem"] == problem and r["n"] == n
                  and "cost" in r), default=None)
    for name in EXACT_PEERS:
        r = measured(rows, problem, name, finished=True).get(n)
        if r is None or lowest is None or (r["cost"] - lowest) > SAME_J * lowest:
            continue
        if best is None or r["seconds"] < best[1]["seconds"]:
            best = (name, r)
    return best


def _ratio(a: float, b: float) -> str:
    return f"{a / b:.1f}×" if b > 0 else "—"


def exact_section(report: dict[str, Any], settings: Settings) -> list[str]:
    """The section: every peer's warm and cold time, its ratio to the public solve and
    to the stage, its peak memory and symcal's share of it, and whether it reached the
    minimum."""
    rows = report.get("rows", [])
    if not any(r["method"] in EXACT_PEERS for r in rows):
        return []
    lines = [
        "## Exact-Jacobian peers (issue 26)", "",
        "What a competent user writes with an exact Jacobian (`bench/exact.py`): the "
        "residuals in JAX (Jacobian by `jax.jacfwd`) or in CasADi (one observation's "
        "residual and Jacobian by CasADi's AD, mapped over the N observations), solved by "
        "scipy `least_squares` (trf with `tr_solver='exact'`, and MINPACK's lm), Ceres "
        "through pyceres (Levenberg–Marquardt, dense QR) and optimistix's "
        "Levenberg–Marquardt (one `jax.jit` program), tolerances 1e-8 (scipy's "
        "defaults; tighter ones only add iterations here), from the same start as every "
        "row.  They form the whole Jacobian in memory; symcal never does.  "
        "*public* is `symcal.solve` of the single-stage problem (gauges before the solve, "
        "the solve, the stage's analysis, the result's statistics: what a user's call "
        "costs); *stage* is the solver stage alone (the default-path row).  Warm: median "
        "of the calls after the first in a fresh process (symcal with its compiled twins "
        "in the cache); cold: the first call in a fresh process (symcal with an empty "
        "compile cache; a JAX peer compiling its XLA program).  Ratios are warm over "
        "warm; memory is the peak RSS of the whole process (interpreter, libraries and "
        "data included).  A peer that did not reach the lowest J at that N (to 1e-10) is "
        "shown but not counted as the best.  J differences of 1e-13 to 1e-11 are the "
        "rounding of the cost where a solver drifted along the problem's gauges (MINPACK's "
        "lm moved the dual problem's offsets by thousands of mm: the cost, computed there, "
        "rounds lower; at symcal's point its Gauss–Newton step promises 1e-24 of the cost, "
        "at MINPACK's 4e-17).  *CPU ÷ public* is the same ratio of CPU time (the "
        "process's, all its threads; median of the warm calls): on a machine shared with "
        "other work it moves less than the wall time does.", ""]
    for problem, info in PROBLEMS.items():
        lines += [f"**{info['title'].split(':')[0]}**", "",
                  "| N | peer | warm | cold | ÷ public | ÷ stage | CPU (warm) | CPU ÷ public "
                  "| peak RSS | public's share of its memory | rel. J | iterations |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for n in settings.sizes:
            here = [r for r in rows if r["problem"] == problem and r["n"] == n]
            public = next((r for r in here if r["method"] == "symcal_public"
                           and "seconds" in r), None)
            stage = next((r for r in here if r["method"] == "symcal" and "seconds" in r),
                         None)
            lowest = min((r["cost"] for r in here if "cost" in r), default=float("nan"))
            for who in ("symcal_public", "symcal"):
                r = public if who == "symcal_public" else stage
                if r is not None:
                    cold = fmt_time(r.get("cold", r["first"]))
                    lines.append(f"| {fmt_n(n)} | **{LABELS[who]}** | "
                                 f"{fmt_time(r['seconds'])} | {cold} "
                                 f"| 1 | — | {_cpu(r)} | 1 | {r['peak_mib']:.0f} MiB | — | "
                                 f"{(r['cost'] - lowest) / lowest:.1e} | {r['iterations']} |")
            for name in EXACT_PEERS:
                r = next((x for x in here if x["method"] == name), None)
                if r is None:
                    continue
                if "seconds" not in r:
                    lines.append(f"| {fmt_n(n)} | {LABELS[name]} | — | — | — | — | — | — | — "
                                 f"| — | — | skipped: {r.get('skipped') or r.get('error')} |")
                    continue
                lines.append(
                    f"| {fmt_n(n)} | {LABELS[name]} | {fmt_time(r['seconds'])} | "
                    f"{fmt_time(r.get('cold', r['first']))} | "
                    f"{_ratio(r['seconds'], public['seconds']) if public else '—'} | "
                    f"{_ratio(r['seconds'], stage['seconds']) if stage else '—'} | "
                    f"{_cpu(r)} | {_cpu_ratio(r, public)} | "
                    f"{r['peak_mib']:.0f} MiB | "
                    f"{'1/' + format(r['peak_mib'] / public['peak_mib'], '.1f') if public else '—'}"
                    f" | {(r['cost'] - lowest) / lowest:.1e} | {r['iterations']} |")
        lines.append("")
    return lines


def _cpu(r: dict[str, Any]) -> str:
    """A row's warm CPU time, or — (runs from before it was measured)."""
    return fmt_time(r["cpu_seconds"]) if "cpu_seconds" in r else "—"


def _cpu_ratio(r: dict[str, Any], public: dict[str, Any] | None) -> str:
    """A peer's CPU time over the public solve's."""
    if public is None or "cpu_seconds" not in r or "cpu_seconds" not in public:
        return "—"
    return _ratio(r["cpu_seconds"], public["cpu_seconds"])


def exact_targets(report: dict[str, Any], settings: Settings) -> list[dict[str, str]]:
    """Issue 26's targets: the public solve ≥ 3× the best exact-Jacobian peer at every N,
    its memory ≤ 1/10 of theirs, the dual problem at N = 1e6 ≤ 5 s."""
    rows = report.get("rows", [])
    if not any(r["method"] in EXACT_PEERS for r in rows):
        return []
    out: list[dict[str, str]] = []
    for problem in PROBLEMS:
        public = measured(rows, problem, "symcal_public")
        stage = measured(rows, problem, "symcal")
        for n in settings.sizes:
            best = _best_peer(rows, problem, n)
            if best is None or n not in public:
                out.append({"target": f"{problem}, N = {fmt_n(n)}: public solve ≥ "
                                      f"{SPEEDUP:g}× the best exact-Jacobian peer",
                            "measured": "no peer finished at this N" if best is None
                            else "public solve not measured", "verdict": "not measured"})
                continue
            name, peer = best
            ratio = peer["seconds"] / public[n]["seconds"]
            stage_ratio = (f"; the stage {peer['seconds'] / stage[n]['seconds']:.1f}×"
                           if n in stage else "")
            out.append({
                "target": f"{problem}, N = {fmt_n(n)}: public solve ≥ {SPEEDUP:g}× the best "
                          "exact-Jacobian peer",
                "measured": f"{ratio:.1f}× ({LABELS[name]} {fmt_time(peer['seconds'])}, "
                            f"public {fmt_time(public[n]['seconds'])}{stage_ratio})",
                "verdict": "met" if ratio >= SPEEDUP else
                f"missed: {ratio:.1f}× ({SPEEDUP / ratio:.1f}× short)"})
            peaks = [r["peak_mib"] for nm in EXACT_PEERS
                     if (r := measured(rows, problem, nm).get(n)) is not None]
            share = public[n]["peak_mib"] / min(peaks)
            out.append({
                "target": f"{problem}, N = {fmt_n(n)}: public solve's peak memory ≤ "
                          f"1/{MEMORY:g} of the exact-Jacobian peers'",
                "measured": f"{public[n]['peak_mib']:.0f} MiB against {min(peaks):.0f} to "
                            f"{max(peaks):.0f} MiB: 1/{1 / share:.1f} of the leanest",
                "verdict": "met" if share <= 1 / MEMORY else
                f"missed: 1/{1 / share:.1f}"})
    dual = measured(rows, "dual", "symcal_public")
    nb = max(settings.sizes)
    if nb >= 1_000_000 and nb in dual:
        t = dual[nb]["seconds"]
        stage_t = measured(rows, "dual", "symcal").get(nb, {}).get("seconds", float("nan"))
        out.append({"target": f"dual, N = {fmt_n(nb)}: public solve ≤ {BIG_SECONDS:g} s on "
                              "2 cores",
                    "measured": f"{t:.2f} s (the stage {stage_t:.2f} s)",
                    "verdict": "met" if t <= BIG_SECONDS else f"missed by {t / BIG_SECONDS:.2f}×"})
    return out
