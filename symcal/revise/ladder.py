"""The model ladder: model revisions solved on the same data, side by side.

Each rung reports the spread of every residual on every dataset (the calibration set and
held-out validation sets), the reference errors, the number of identifiable parameters,
and AIC and BIC of the calibration fit, so the user sees the error fall with each added
effect and sees when an addition only overfits (its held-out error does not fall and the
information criteria rise).

Revisions are labelled by file (``problem_revised.yaml``; with as many parent folders as
it takes when two file names are equal), since revisions of one problem often keep its
name.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from symcal.base.files import atomic_write_bytes
from symcal.base.units import symbol
from symcal.calibrate.result import Result


def revision_labels(paths: Sequence[str | Path]) -> list[str]:
    """A short label for each problem file: its name, with parent folders added where
    two names are equal (``a/problem.yaml``, ``b/problem.yaml``), and a number where the
    same file comes twice.

    Parameters
    ----------
    paths
        The problem files, in ladder order.

    Returns
    -------
    list of str
        One label per path, distinct.
    """
    full = [Path(p).resolve().parts for p in paths]
    depth = [1] * len(full)

    def labels() -> list[str]:
        return ["/".join(f[-d:]) for f, d in zip(full, depth, strict=True)]

    changed = True
    while changed:
        changed = False
        shown = labels()
        for i, label in enumerate(shown):
            if depth[i] < len(full[i]) and any(
                    other == label and full[j] != full[i] for j, other in enumerate(shown)):
                depth[i] += 1
                changed = True
    shown = labels()
    out = []
    for i, label in enumerate(shown):
        if shown.count(label) > 1:
            label = f"{label} ({shown[:i + 1].count(label)})"
        out.append(label)
    return out


@dataclass(frozen=True)
class Rung:
    """One model revision's fit; ``label`` names it in tables and figures (its file)."""

    name: str
    path: str
    success: bool
    identifiable: int
    free: int
    rows: int
    rss: float
    aic: float
    bic: float
    spreads: dict[tuple[str, str], tuple[float, str]]   # (dataset, quantity) -> (std, unit)
    label: str = ""

    @property
    def title(self) -> str:
        """What tables and figures call the revision: its label, else its problem name."""
        return self.label or self.name

    @classmethod
    def of(cls, result: Result, label: str | None = None) -> Rung:
        """The rung of one calibration result (labelled by its file name by default)."""
        spreads = {(s.dataset, s.name): (s.shown("after").std, s.unit or "(internal)")
                   for s in result.statistics}
        return cls(result.name, result.problem_path, result.success,
                   result.identifiability.rank, len(result.stages[-1].free), result.rows,
                   result.rss, result.aic, result.bic, spreads,
                   label if label is not None else Path(result.problem.path).name)

    def to_dict(self) -> dict:
        """Plain-data form (units as declared)."""
        return {"name": self.name, "label": self.title, "path": self.path,
                "success": self.success,
                "identifiable_parameters": self.identifiable, "free_parameters": self.free,
                "rows": self.rows, "rss": self.rss, "aic": self.aic, "bic": self.bic,
                "spreads": [{"dataset": d, "quantity": q, "std": s, "unit": u}
                            for (d, q), (s, u) in self.spreads.items()]}


def compare(results: Sequence[Result]) -> tuple[Rung, ...]:
    """Summarise calibrations of model revisions (solved on the same data, simplest
    first) as the rungs of a ladder, labelled by file (:func:`revision_labels`); nothing
    is solved again."""
    labels = revision_labels([r.problem.path for r in results])
    return tuple(Rung.of(r, label) for r, label in zip(results, labels, strict=True))


def ladder_report(rungs: Sequence[Rung]) -> str:
    """The ladder as a table: one column per model revision."""
    keys: list[tuple[str, str]] = []
    for r in rungs:
        keys += [k for k in r.spreads if k not in keys]
    header = ["", *[r.title for r in rungs]]
    rows = [header,
            ["identifiable / free parameters", *[f"{r.identifiable} / {r.free}" for r in rungs]],
            ["AIC (calibration)", *[f"{r.aic:.1f}" for r in rungs]],
            ["BIC (calibration)", *[f"{r.bic:.1f}" for r in rungs]]]
    for dataset, quantity in keys:
        unit = next(r.spreads[(dataset, quantity)][1] for r in rungs
                    if (dataset, quantity) in r.spreads)
        label = f"{dataset} {quantity} std ({symbol(unit)})"
        rows.append([label, *[f"{r.spreads[(dataset, quantity)][0]:.4g}"
                              if (dataset, quantity) in r.spreads else "—" for r in rungs]])
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
