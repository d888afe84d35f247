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
from dataclasses import dataclass, field
from pathlib import Path

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
    # (dataset, quantity) -> (RMS, whether the mean is an arbitrary zero): symcal improve
    # judges a held-out residual by its RMS, by its std where the mean is arbitrary
    sizes: dict[tuple[str, str], tuple[float, bool]] = field(default_factory=dict)

    @property
    def title(self) -> str:
        """What tables and figures call the revision: its label, else its problem name."""
        return self.label or self.name

    @classmethod
    def of(cls, result: Result, label: str | None = None) -> Rung:
        """The rung of one calibration result (labelled by its file name by default)."""
        spreads = {(s.dataset, s.name): (s.shown("after").std, s.unit or "(internal)")
                   for s in result.statistics}
        sizes = {(s.dataset, s.name): (s.shown("after").rms, s.remove_mean)
                 for s in result.statistics}
        return cls(result.name, result.problem_path, result.success,
                   result.identifiability.rank, len(result.stages[-1].free), result.rows,
                   result.rss, result.aic, result.bic, spreads,
                   label if label is not None else Path(result.problem.path).name, sizes)

    def to_dict(self) -> dict:
        """Plain-data form (units as declared)."""
        return {"name": self.name, "label": self.title, "path": self.path,
                "success": self.success,
                "identifiable_parameters": self.identifiable, "free_parameters": self.free,
                "rows": self.rows, "rss": self.rss, "aic": self.aic, "bic": self.bic,
                "spreads": [{"dataset": d, "quantity": q, "std": s,
                             "rms": self.sizes[(d, q)][0] if (d, q) in self.sizes else None,
                             "unit": u}
                            for (d, q), (s, u) in self.spreads.items()]}


def compare(results: Sequence[Result]) -> tuple[Rung, ...]:
    """Summarise calibrations of model revisions (solved on the same data, simplest
    first) as the rungs of a ladder, labelled by file (:func:`revision_labels`); nothing
    is solved again."""
    labels = revision_labels([r.problem.path for r in results])
    return tuple(Rung.of(r, label) for r, label in zip(results, labels, strict=True))
