"""RESULTS.md's "Where symcal's time goes": the misses explained with this run's numbers."""

from __future__ import annotations

import math
from typing import Any

from .analysis import Row, measured
from .config import Settings
from .fmt import fmt_n, fmt_time

Record = dict[str, Any]


def _estimate(counts: dict[str, int], prof: Record, chunks: int) -> float:
    """Time of symcal's passes: calls of each evaluator × its measured time per chunk."""
    return chunks * sum(counts.get(k, 0) * prof.get(k, 0.0)
                        for k in ("normal_equations", "accumulate_r", "cost"))


def _by(counts: dict[str, int]) -> str:
    return ", ".join(f"{v} × `{k}`" for k, v in sorted(counts.items(), key=lambda kv: -kv[1]))


def _work(r: Record) -> str:
    return "—" if r.get("work_mib") is None else f"{r['work_mib']:.0f} MiB"


def _one_pass(d: Record, lin: Record) -> list[str]:
    n = d["n"]
    return [
        "### 1. One pass over the data",
        "",
        f"symcal evaluates its one-observation CasADi functions over chunks of up to {n} "
        "observations (`symcal.base.numeric.Mapped`, `CHUNK`).  Per chunk of "
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
        f"| … work vector of the mapped function | {_work(d)} | {_work(lin)} |",
        f"| `Objective.normal_equations` (residual, Jᵀg, JᵀJ) | "
        f"{fmt_time(d['normal_equations'])} | {fmt_time(lin['normal_equations'])} |",
        f"| `Objective.accumulate_r` (TSQR) | {fmt_time(d['accumulate_r'])} | "
        f"{fmt_time(lin['accumulate_r'])} |",
        f"| `Objective.cost` (residual only) | {fmt_time(d['cost'])} | "
        f"{fmt_time(lin['cost'])} |",
        "",
    ]


def _largest(rows: list[Row], d: Record, lin: Record, nb: int) -> list[str]:
    sym_dual, sym_lin = measured(rows, "dual", "symcal"), measured(rows, "linear", "symcal")
    floor = measured(rows, "linear", "floor")
    chunks_big = math.ceil(nb / d["n"])
    lines = []
    if nb in sym_dual and sym_dual[nb].get("passes_by"):
        t = sym_dual[nb]
        est = _estimate(t["passes_by"], d, chunks_big)
        lines.append(
            f"- Dual, N = {fmt_n(nb)}: {t['seconds']:.1f} s for {t['iterations']} `lm` "
            f"trial steps and {t['evaluations']} passes ({_by(t['passes_by'])}).  Those "
            f"passes at the per-chunk times above (one thread), × {chunks_big} chunks, come "
            f"to {est:.1f} s of work, shared by the passes' threads (one per core, "
            "`symcal.solvers.executor`); the rest is the solver itself and the "
            "reductions.")
    if nb in sym_lin and nb in floor:
        lines.append(
            f"- Linear, N = {fmt_n(nb)}: symcal {sym_lin[nb]['seconds']:.2f} s (one "
            f"`accumulate_r` pass: {chunks_big} chunks × {fmt_time(lin['accumulate_r'])}), "
            f"the numpy floor {floor[nb]['seconds']:.2f} s (building Γ, N × 36, in memory, "
            "then one SVD-based `lstsq`).")
    return lines


def _smallest(rows: list[Row], ds: Record, n0: int) -> list[str]:
    sym_dual, ls = measured(rows, "dual", "symcal"), measured(rows, "dual", "least_squares")
    if not (n0 in sym_dual and n0 in ls and sym_dual[n0].get("passes_by") and "cost" in ds):
        return []
    t, peer = sym_dual[n0], ls[n0]
    est = _estimate(t["passes_by"], ds, 1)
    ratio = peer["seconds"] / t["seconds"]
    lines = [
        "",
        f"### 2. The dual problem at N = {fmt_n(n0)}",
        "",
        f"symcal took {fmt_time(t['seconds'])}: {t['evaluations']} passes "
        f"({_by(t['passes_by'])}) at {fmt_time(ds['normal_equations'])} per "
        f"`normal_equations`, {fmt_time(ds['cost'])} per `cost` and "
        f"{fmt_time(ds['accumulate_r'])} per `accumulate_r` make {fmt_time(est)}.  The "
        f"remaining {fmt_time(max(t['seconds'] - est, 0.0))} is the solver's own work "
        "(SVDs of R, trust-region steps) and the first evaluation of the run (first "
        f"`normal_equations` call: {fmt_time(ds['normal_equations_first'])}; an "
        "objective's functions are built once per process and problem, and repeated "
        f"solves reuse them).  least_squares took {fmt_time(peer['seconds'])} for "
        f"{peer['evaluations']} numpy residual evaluations "
        f"({fmt_time(peer['seconds'] / peer['evaluations'])} each), i.e. "
        f"{ratio:.1f}× symcal's time.",
    ]
    if ratio < 30:
        lines.append(
            f"\nReaching 30× needs symcal at ≤ {fmt_time(peer['seconds'] / 30)}.  Its "
            "passes are already one per accepted step (a first trial is evaluated with "
            "its derivatives); what is left is the solver's own work per step.")
    return lines


def _stalls(rows: list[Row]) -> list[str]:
    its = sorted(measured(rows, "dual", "symcal").items())
    lines = ["", "### 3. Iterating on rounding noise", ""]
    lines.append("symcal's dual solve by N: " + "; ".join(
        f"N = {fmt_n(k)}: {r['iterations']} iterations, {r['evaluations']} passes, "
        f"{fmt_time(r['seconds'])}" for k, r in its) + ".")
    stalled = [(k, r) for k, r in its
               if sum(1e-14 <= v < 1e-12 for v in (r.get("decrements") or [])) >= 2]
    if not stalled:
        lines.append("\nNo size stalled above the 1e-14 decrement in this run.")
        return lines
    k, r = max(stalled, key=lambda kr: kr[1]["evaluations"])
    lines += [
        "",
        f"At N = {fmt_n(k)}, the solver tested the Gauss-Newton decrement after every "
        "accepted step; the decrement went "
        + ", ".join(f"{v:.3g}" for v in r["decrements"]) + ".  "
        "Near 1e-14 the cost is flat to rounding: trial steps find no decrease that "
        "the cost can resolve, and each costs a residual-only pass "
        f"({r['evaluations']} passes for {r['iterations']} steps here, against "
        f"{its[0][1]['evaluations']} for {its[0][1]['iterations']} at "
        f"N = {fmt_n(its[0][0])}).  1e-14 is at the level of the rounding error of a "
        "sum of 3N squares (`lm` stops at 64 machine epsilons, then takes the last "
        "Gauss-Newton step from R).  Whether the decrement lingers there depends on "
        "the data and on the order of summation, so symcal's time at one N can be "
        "several times that of its neighbours.  That is also why its fitted exponent "
        "over N ≥ 1e4 can be "
        "below 1; time per pass is the fairer measure of growth.",
    ]
    return lines


def _assembly(report: dict[str, Any], d: Record, ds: Record) -> list[str]:
    asm = {k: r for k, r in report.get("assemble", {}).items() if "total" in r}
    if not asm:
        return []
    (wp, wn), worst = max(asm.items(), key=lambda kv: kv[1]["total"])
    return [
        "", "### 4. Building the mapped functions (load + assemble)", "",
        f"The slowest load + assemble was {fmt_time(worst['total'])} ({wp}, "
        f"N = {fmt_n(wn)}, chunk lengths {worst['chunks']}), of which "
        f"{fmt_time(worst['assemble'])} is making the objectives and their mapped "
        "functions: one per stage for the residual and one for the residual + "
        "Jacobian, evaluated once on each chunk length.  The first call of a mapped "
        f"function on {d['n']} observations (dual residual + Jacobian) took "
        f"{fmt_time(d['chunk_first'])} against {fmt_time(d['chunk'])} for a repeated "
        f"call, and on {ds.get('n', '?')} observations the first `normal_equations` "
        f"took {fmt_time(ds.get('normal_equations_first', float('nan')))} against "
        f"{fmt_time(ds.get('normal_equations', float('nan')))}.  A mapped function is "
        "a plain serial `map` (a loop over the one-observation code, built in "
        "microseconds); a first call allocates the thread's buffers and loads the "
        "compiled twin from the cache (`symcal.base.jit`)."]


def _blas(report: dict[str, Any], n0: int) -> list[str]:
    blas = report.get("blas", {})
    one = blas.get(("1 thread", "dual", "symcal", n0), {})
    dflt = blas.get(("BLAS default", "dual", "symcal", n0), {})
    if "seconds" not in one or "seconds" not in dflt:
        return []
    return ["", "### 5. BLAS threads", "",
            f"symcal's dual solve at N = {fmt_n(n0)} took {fmt_time(one['seconds'])} "
            f"with one BLAS thread and {fmt_time(dflt['seconds'])} with OpenBLAS's "
            f"default of one thread per core ({dflt['seconds'] / one['seconds']:.1f}×) "
            "in this run.  symcal reduces every chunk with BLAS on tall, thin matrices "
            "(`jac.T @ jac` in `Objective.normal_equations`, LAPACK `dgeqrt` in "
            "`Objective.accumulate_r`).  How much the default threads cost depends on "
            "what else is running on the two cores.  The harness pins every timed "
            "process, peers included, to one BLAS thread; the last table shows both "
            "settings."]


def _issue16(report: dict[str, Any], nb: int, n0: int) -> list[str]:
    """Both cores, compiled functions and start-up: the issue-16 targets explained."""
    rows = report["rows"]
    fast, slow = measured(rows, "dual", "symcal"), measured(rows, "dual", "symcal_serial")
    lines = ["", "### 6. Both cores, compiled functions, start-up (issue 16)", ""]
    if nb in fast and nb in slow:
        f, s = fast[nb], slow[nb]
        lines.append(
            f"Dual, N = {fmt_n(nb)}: {f['seconds']:.1f} s on one thread per core with the "
            f"compiled functions, {s['seconds']:.1f} s on one thread interpreted "
            f"({s['seconds'] / f['seconds']:.1f}×), {f['evaluations']} passes "
            f"({_by(f.get('passes_by') or {})}).  The 10 s target needs the second core "
            "free: on a machine where other work holds a core, the threads share one.")
    if n0 in fast:
        t = fast[n0]
        lines.append(
            f"\nDual, N = {fmt_n(n0)}: {fmt_time(t['seconds'])} for {t['iterations']} "
            f"iterations and {t['evaluations']} passes.  Below 32768 observations a pass is "
            "one chunk on one thread; the compiled functions make a pass about 3× cheaper, "
            "and what is left at this size is the solver's own work per step (an SVD of "
            "the 49 × 49 factor R, the trust-region step) in Python.")
    start = report.get("startup", {})
    parts = start.get("parts", {})
    if start and parts:
        lines.append(
            f"\n`symcal solve` of the §3.1 problem took {start['solve']['seconds']:.2f} s.  "
            "Of a fresh process: " + ", ".join(f"{k} {v:.2f} s" for k, v in parts.items())
            + ".  The unit registry (pint, issue 15: units are checked when a problem "
            "loads) is built in every process; YAML parsing (pure-Python PyYAML, keeping "
            "every key's line) and the simulated datasets of the problem file come on top.  "
            f"`symcal --help` ({start['help']['seconds']:.2f} s) imports neither CasADi "
            "nor SciPy.")
    return lines


def why_section(report: dict[str, Any], settings: Settings) -> list[str]:
    """Where symcal's time goes, from measurements of this run."""
    prof = report.get("profile", {})
    d, lin = prof.get("dual/chunk", {}), prof.get("linear/chunk", {})
    ds = prof.get("dual/small", {})
    if "chunk" not in d or "chunk" not in lin:
        return ["## Where symcal's time goes", "", f"(profile failed: {prof})"]
    rows = report["rows"]
    nb, n0 = max(settings.sizes), min(settings.sizes)
    return (["## Where symcal's time goes", ""] + _one_pass(d, lin)
            + _largest(rows, d, lin, nb) + _smallest(rows, ds, n0) + _stalls(rows)
            + _assembly(report, d, ds) + _blas(report, n0) + _issue16(report, nb, n0))
