"""The previous run of ``symcal improve`` in an output folder, removed before a new one
writes there: its ``final.yaml`` and ladder, its revisions of the same problem and the
model files only they use.  Otherwise an interrupted run, or one keeping fewer rounds,
leaves a folder mixing two runs (an old ``PROBLEM_round2.yaml`` extending the new
``PROBLEM_round1.yaml``).  Only files symcal wrote and nobody changed since are removed;
anything else stays where it is."""

from __future__ import annotations

import re
from pathlib import Path

from symcal.base.files import written_by_symcal

#: What one run writes beside its revisions.
SUMMARY = ("final.yaml", "ladder.txt", "ladder.json", "ladder.png")
#: A reference to a model file in ``models/``: from the folder, and from ``models/``
#: itself (a model extending another one there, named without a folder).
_FROM_FOLDER = re.compile(r"(?<![\w./-])models/([\w.-]+\.yaml)")
_FROM_MODELS = re.compile(r"(?<![\w./-])([\w.-]+\.yaml)")


def clear_previous(directory: Path, stem: str) -> list[Path]:
    """Remove the previous run's files from ``directory`` (module doc); return them."""
    own = rf"{re.escape(stem)}_(round\d+(_alt\d+)?(_try\d+|_all)?|try\d+|all)"
    revisions = [p for p in directory.glob(f"{stem}_*.yaml") if re.fullmatch(own, p.stem)]
    gone = [p for p in [*(directory / n for n in SUMMARY), *revisions]
            if p.is_file() and written_by_symcal(p)]
    models = directory / "models"
    kept = [p for p in directory.glob("*.yaml") if p not in gone]
    used = _models_used(kept, models)
    candidates = _models_used(gone, models) - used
    gone += sorted(p for p in candidates if written_by_symcal(p))
    for path in gone:
        path.unlink(missing_ok=True)
    return gone


def _models_used(files: list[Path], models: Path) -> set[Path]:
    """The model files in ``models`` that ``files`` refer to, and those they refer to in
    turn."""
    found: set[Path] = set()
    todo = list(files)
    while todo:
        path = todo.pop()
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError):
            continue
        pattern = _FROM_MODELS if path.parent == models else _FROM_FOLDER
        for name in pattern.findall(text):
            model = models / name
            if model not in found and model.is_file():
                found.add(model)
                todo.append(model)
    return found
