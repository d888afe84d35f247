"""The model ladder presented: a table with one column per model revision, and one figure
of every residual's spread across the revisions."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from symcal.base.files import atomic_write_bytes
from symcal.base.units import symbol
from symcal.revise.ladder import Rung


def ladder_report(rungs: Sequence[Rung]) -> str:
    """The ladder as a table: one column per model revision; each residual's standard
    deviation and, where its mean is no arbitrary zero and the two differ as shown, its
    RMS (what ``symcal improve`` judges a held-out residual by: an offset moves the mean
    alone)."""
    keys: list[tuple[str, str]] = []
    for r in rungs:
        keys += [k for k in r.spreads if k not in keys]
    header = ["", *[r.title for r in rungs]]
    rows = [header,
            ["identifiable / free parameters", *[f"{r.identifiable} / {r.free}" for r in rungs]],
            ["AIC (calibration)", *[f"{r.aic:.1f}" for r in rungs]],
            ["BIC (calibration)", *[f"{r.bic:.1f}" for r in rungs]]]
    for key in keys:
        unit = next(r.spreads[key][1] for r in rungs if key in r.spreads)
        rows.append([f"{key[0]} {key[1]} std ({symbol(unit)})",
                     *[f"{r.spreads[key][0]:.4g}" if key in r.spreads else "—"
                       for r in rungs]])
        if any(key in r.sizes and key in r.spreads and not r.sizes[key][1]
               and f"{r.sizes[key][0]:.4g}" != f"{r.spreads[key][0]:.4g}" for r in rungs):
            rows.append([f"{key[0]} {key[1]} RMS ({symbol(unit)})",
                         *[f"{r.sizes[key][0]:.4g}" if key in r.sizes else "—"
                           for r in rungs]])
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    lines = ["symcal compare: model revisions on the same data (lower is better; a lower "
             "AIC/BIC says the added parameters pay for themselves)", ""]
    for row in rows:
        lines.append("  " + "  ".join(c.ljust(w) if i == 0 else c.rjust(w)
                                      for i, (c, w) in enumerate(zip(row, widths,
                                                                     strict=True))))
    failed = [r.title for r in rungs if not r.success]
    if failed:
        lines += ["", f"  failed: {', '.join(failed)} (see symcal solve for the reason)"]
    return "\n".join(lines) + "\n"


def save_ladder_plot(rungs: Sequence[Rung], outdir: str | Path,
                     formats: Sequence[str] = ("png",)) -> list[Path]:
    """One figure: every residual's std across the revisions (log scale)."""
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure


    keys: list[tuple[str, str]] = []
    for r in rungs:
        keys += [k for k in r.spreads if k not in keys]
    fig = Figure(figsize=(9, 4.5), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    x = np.arange(len(rungs))
    for key in keys:
        values = [r.spreads[key][0] if key in r.spreads else np.nan for r in rungs]
        unit = next(r.spreads[key][1] for r in rungs if key in r.spreads)
        ax.plot(x, values, marker="o", label=f"{key[0]} {key[1]} ({symbol(unit)})")
    ax.set_xticks(x, [r.title for r in rungs], rotation=15, ha="right")
    ax.set_yscale("log")
    ax.set_ylabel("std after calibration")
    ax.set_title("model ladder")
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5))
    fig.tight_layout()
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for fmt in formats:
        buf = io.BytesIO()
        fig.savefig(buf, format=fmt)
        path = out / f"ladder.{fmt}"
        atomic_write_bytes(path, buf.getvalue())
        written.append(path)
    return written
