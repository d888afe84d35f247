"""The fleet summary as text and as a figure (:func:`fleet_text`, :func:`fleet_figure`).

Both read only the plain-data summary of :func:`symcal.calibrate.fleet_summary.summarise` (what
``symcal solve --fleet DIR --json`` prints under ``"summary"``).  matplotlib is imported
inside :func:`fleet_figure` only, and the figure is drawn on an Agg canvas, never pyplot.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from symcal.base.units import symbol
from symcal.calibrate.fleet_summary import OUTLIER_SCORE

if TYPE_CHECKING:
    from matplotlib.figure import Figure

Summary = Mapping[str, Any]
#: At most this many outlier units are named in the figure.
MAX_NAMED = 12
DPI = 110
#: Ticks of the score axes (symmetric-logarithmic beyond the outlier band).
SCORE_TICKS = (-1000, -100, -20, -5, 0, 5, 20, 100, 1000)


def _num(x: float | None) -> str:
    if x is None or not math.isfinite(x):
        return "—"
    return format(x, ".4g")


def _table(rows: list[list[str]], align: str) -> list[str]:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return ["  " + "  ".join(c.ljust(w) if a == "l" else c.rjust(w)
                             for c, w, a in zip(r, widths, align, strict=True)).rstrip()
            for r in rows]


def _outlier_names(summary: Summary) -> dict[tuple[str, str | None], list[str]]:
    """(quantity, dataset) → the outlier units flagged on it."""
    out: dict[tuple[str, str | None], list[str]] = {}
    for unit, findings in summary["outliers"].items():
        for f in findings:
            out.setdefault((f["name"], f["dataset"]), []).append(unit)
    return out


def fleet_text(summary: Summary, title: str = "") -> str:
    """The fleet summary a person reads: counts, failed units, outlier units with their
    reasons, then each parameter's and each residual's distribution over the fleet.

    Parameters
    ----------
    summary
        :func:`symcal.calibrate.fleet_summary.summarise`'s document.
    title
        Shown after the problem's name (e.g. the fleet folder).
    """
    c = summary["counts"]
    head = f"symcal fleet: {summary['problem'] or '(no problem)'}" + (f" ({title})" if title
                                                                     else "")
    lines = [head, "", "Verdict",
             f"  {c['units']} unit(s): {c['solved']} solved, {c['failed']} failed, "
             f"{c['outliers']} outlier(s) among the solved"]
    if summary["failed"]:
        lines += ["", "Failed units (no estimate, or a failed solve)"]
        lines += _table([[u, r] for u, r in summary["failed"].items()], "ll")
    lines += ["", f"Outlier units ({summary['rules']})"]
    if summary["outliers"]:
        for unit, findings in summary["outliers"].items():
            for i, f in enumerate(findings):
                lines.append(f"  {unit if i == 0 else ' ' * len(unit)}  {f['reason']}")
    else:
        lines.append("  none")
    flagged = _outlier_names(summary)
    if summary["parameters"]:
        lines += ["", f"Parameters over the {c['solved']} solved unit(s): median, robust "
                  "spread (1.4826 × median absolute deviation), range"]
        rows = [["parameter", "unit", "median", "spread", "min", "max", "outliers / note"]]
        for name, d in summary["parameters"].items():
            note = ", ".join(flagged.get((name, None), [])) or (d.get("note") or "")
            rows.append([name, symbol(d["unit"]) if d["unit"] else "", _num(d["median"]),
                         _num(d["spread"]), _num(d["min"]), _num(d["max"]), note])
        lines += _table(rows, "llrrrrl")
    if summary["residuals"]:
        lines += ["", "Residuals: RMS after calibration over the solved units"]
        rows = [["residual", "dataset", "unit", "median", "spread", "min", "max", "outliers"]]
        for d in summary["residuals"].values():
            rows.append([d["name"], d["dataset"], symbol(d["unit"]) if d["unit"] else "",
                         _num(d["median"]), _num(d["spread"]), _num(d["min"]),
                         _num(d["max"]),
                         ", ".join(flagged.get((d["name"], d["dataset"]), []))])
        lines += _table(rows, "lllrrrrl")
    return "\n".join(lines) + "\n"


def _scores(dist: Mapping[str, Any]) -> dict[str, float]:
    """Each unit's robust score on one distribution (0 where it is not tested)."""
    spread = dist.get("test_spread") or 0.0
    if not dist.get("tested") or spread <= 0:
        return {}
    median = dist["test_median"]
    return {u: (v - median) / spread for u, v in dist["values"].items()}


def fleet_figure(summary: Summary) -> Figure:
    """The fleet at a glance: every unit's robust score on every tested parameter (top)
    and on every residual's RMS (bottom), the outlier band shaded, outliers named.

    Parameters
    ----------
    summary
        :func:`symcal.calibrate.fleet_summary.summarise`'s document.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    groups = [("parameter", {n: d for n, d in summary["parameters"].items() if d.get("tested")}),
              ("residual RMS", {k: d for k, d in summary["residuals"].items()
                                if d.get("tested")})]
    width = max(6.0, 0.28 * max(len(g) for _, g in groups) + 2.5)
    fig = Figure(figsize=(width, 7.0), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 1, squeeze=False).ravel()
    outliers = set(summary["outliers"])
    c = summary["counts"]
    fig.suptitle(f"{summary['problem']}: {c['solved']} of {c['units']} units solved, "
                 f"{c['outliers']} outlier(s), {c['failed']} failed", fontsize=10)
    for ax, (what, dists) in zip(axes, groups, strict=True):
        ax.axhspan(-OUTLIER_SCORE, OUTLIER_SCORE, color="0.92", zorder=0)
        ax.set_ylabel(f"{what}: robust score")
        if not dists:
            ax.text(0.5, 0.5, "no test (too few solved units, or nothing identifiable)",
                    ha="center", va="center", transform=ax.transAxes, color="0.4")
            ax.set_xticks([])
            continue
        points: dict[bool, tuple[list[int], list[float]]] = {False: ([], []),
                                                               True: ([], [])}
        named = 0
        for x, dist in enumerate(dists.values()):
            for unit, score in _scores(dist).items():
                odd = unit in outliers and abs(score) > OUTLIER_SCORE
                points[odd][0].append(x)
                points[odd][1].append(score)
                if odd and named < MAX_NAMED:
                    ax.annotate(unit, (x, score), xytext=(4, 2), textcoords="offset points",
                                fontsize=7, color="tab:red")
                    named += 1
        for odd, (xs, ys) in points.items():   # one artist per kind, not one per point
            if xs:
                ax.plot(xs, ys, "o", ms=4 if odd else 3, alpha=0.9 if odd else 0.5,
                        color="tab:red" if odd else "tab:blue", zorder=3 if odd else 2)
        ax.set_yscale("symlog", linthresh=OUTLIER_SCORE)
        low, high = ax.get_ylim()
        ticks = [t for t in SCORE_TICKS if low <= t <= high]
        ax.set_yticks(ticks, [f"{t:g}" for t in ticks])
        ax.set_xticks(range(len(dists)), list(dists), rotation=90 if len(dists) > 6 else 0,
                      fontsize=7)
        ax.set_xlim(-0.7, len(dists) - 0.3)
        ax.grid(axis="y", color="0.85", lw=0.5)
    return fig


def fleet_png(summary: Summary) -> bytes:
    """:func:`fleet_figure` as PNG bytes (no timestamp: the same summary gives the same
    bytes)."""
    fig = fleet_figure(summary)
    try:
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=DPI)
        return buf.getvalue()
    finally:
        fig.clear()
