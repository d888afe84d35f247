"""The model's own approximation as a candidate: implicit variants of a problem.

An explicit model evaluates a sensor's error at the raw reading (the paper's eq. 3,
``p_hat = p + e(u)`` with ``u = p``); its implicit variant evaluates it where it arises
(``u = p + e(u) - k0``, solved by fixed-point steps).  Where the errors are not small
against the period, the explicit form leaves a structured residual of order e'·e that
looks like many missing harmonics.  This module finds the implicit variants a user has
beside their files:

- a *problem variant*: a problem file in the same folder that ``extends`` this one and
  declares ``implicit:`` definitions (e.g. ``dual_sensor_calibration_implicit.yaml``);
- *model variants*: for each instance, a model file beside its model that ``extends`` it
  and declares ``implicit:`` definitions (e.g. ``platen_segment_implicit.yaml``).

A variant counts only when it has exactly the parameters of the problem, so that it is
the same model evaluated differently, not a model with more terms.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from symcal.base.errors import SymcalError
from symcal.language.model_file import ModelSpec, load_model
from symcal.language.yamlio import YMap, dump_yaml, load_yaml, parse_yaml, yaml_scalar
from symcal.problem.build import load_problem, with_instance
from symcal.problem.symbolic import Problem


@dataclass(frozen=True)
class Variant:
    """An implicit variant of a problem and the overlay that switches to it.

    ``models`` maps instance name → the implicit model file it switches to (empty for a
    problem variant); ``problem_file`` is the variant problem file (None for model
    variants, which are applied with :func:`~symcal.problem.build.with_instance`).  ``rebased`` are
    model files to create (name → text): a model that extends one with an implicit
    variant (e.g. a term added by symcal) gets the same additions on top of the variant.
    """

    problem: Problem
    description: str
    models: dict[str, Path]
    problem_file: Path | None
    rebased: dict[str, str] = field(default_factory=dict)

    def model_path(self, instance: str, directory: Path) -> Path:
        """Where instance's implicit model is once the variant is written to
        ``directory`` (rebased models go to ``directory/models``)."""
        path = self.models[instance]
        return directory / "models" / path.name if path.name in self.rebased else path

    def files(self, directory: Path) -> dict[Path, str]:
        """The rebased model files to write for an overlay in ``directory``, by path."""
        out = {}
        for file_name, text in self.rebased.items():   # their extends: are absolute
            target = directory / "models" / file_name
            out[target] = _rebase_text(text, target.parent, target.parent)
        return out

    def overlay(self, base: Path, name: str, directory: Path) -> str:
        """The YAML of a problem file in ``directory`` that switches ``base`` to this
        variant (``extends:`` either the base with the models swapped, or the variant)."""
        def rel(path: Path) -> str:
            return Path(os.path.relpath(path.resolve(), directory.resolve())).as_posix()

        if self.problem_file is not None:
            return dump_yaml({"problem": name, "extends": rel(self.problem_file),
                              "doc": self.description})
        return dump_yaml({"problem": name, "extends": rel(base), "doc": self.description,
                          "instances": {inst: {"model": rel(self.model_path(inst, directory))}
                                        for inst in self.models}})


def _extends_target(path: Path, what: str) -> tuple[Path | None, YMap | None]:
    """The resolved file ``path`` extends and its document, or (None, None)."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None, None
    if "extends:" not in text or "implicit:" not in text:
        return None, None
    try:
        doc, _ = load_yaml(path, what)
    except SymcalError:
        return None, None
    target = doc.get("extends")
    if not isinstance(target, str) or "implicit" not in doc:
        return None, None
    return (path.parent / target).resolve(), doc


def _set_key(text: str, key: str, value: str) -> str:
    """``text`` with its top-level ``key: ...`` line (a scalar on one line) set to
    ``value``, written by the YAML emitter."""
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if line.startswith(f"{key}:"):
            lines[i] = f"{key}: {yaml_scalar(value)}"
            return "\n".join(lines) + "\n"
    return f"{key}: {yaml_scalar(value)}\n" + text


def _rebase_text(text: str, origin: Path, target: Path) -> str:
    """A rebased model's text (its ``extends:`` relative to ``origin``) for ``target``."""
    for line in text.splitlines():
        if line.startswith("extends:"):
            base = (origin / str(parse_yaml(line)["extends"])).resolve()
            return _set_key(text, "extends",
                            Path(os.path.relpath(base, target.resolve())).as_posix())
    return text


def _rebased(model: ModelSpec, parent_variant: Path, folder: Path) -> tuple[Path, str]:
    """``model`` (which extends a model whose implicit variant is ``parent_variant``)
    written in ``folder`` on top of that variant: its file and text."""
    text = model.path.read_text(encoding="utf-8")
    name = f"{model.name}_implicit"
    text = _set_key(text, "model", name)
    text = _set_key(text, "extends", Path(os.path.relpath(parent_variant,
                                                          folder.resolve())).as_posix())
    return folder / f"{model.path.stem}_implicit.yaml", text


def _model_variant(model: ModelSpec) -> Path | None:
    """A model file beside ``model`` that extends it and declares implicit definitions."""
    if model.implicit:
        return None
    for path in sorted(model.path.parent.glob("*.yaml")):
        target, _ = _extends_target(path, "model")
        if target == model.path.resolve():
            try:
                variant = load_model(path)
            except SymcalError:
                continue
            if set(variant.parameters) == set(model.parameters) and variant.implicit:
                return path.resolve()
    return None


def implicit_variant(problem: Problem) -> Variant | None:
    """The implicit variant of ``problem`` beside its files, or None when it has none (or
    is implicit already)."""
    if problem.implicit:
        return None
    here = Path(problem.path).resolve()
    for path in sorted(here.parent.glob("*.yaml")):
        target, doc = _extends_target(path, "problem")
        if target == here and doc is not None:
            try:
                variant = load_problem(path)
            except SymcalError:
                continue
            if variant.parameter_names == problem.parameter_names:
                return Variant(variant, f"{problem.name} with every error evaluated where "
                               f"it arises (the implicit form, {path.name})", {},
                               path.resolve())
    models: dict[str, Path] = {}
    rebased: dict[str, str] = {}
    with tempfile.TemporaryDirectory(prefix="symcal-variant-") as tmp:
        for name, inst in problem.instances.items():
            found = _model_variant(inst.model)
            if found is None and inst.model.extends is not None:
                parent = _model_variant(inst.model.extends)
                if parent is not None:
                    found, text = _rebased(inst.model, parent, Path(tmp))
                    found.write_text(text, encoding="utf-8")
                    rebased[found.name] = _set_key(text, "extends", parent.as_posix())
            if found is not None:
                models[name] = found
        if not models:
            return None
        variant = problem
        try:
            for name, path in models.items():
                variant = with_instance(variant, name, load_model(path))
        except SymcalError:
            return None
    if variant.parameter_names != problem.parameter_names:
        return None
    shown = ", ".join(sorted({p.name for p in models.values()}))
    return Variant(variant, f"{problem.name} with the errors of {', '.join(models)} "
                            f"evaluated at the corrected reading (the implicit models "
                            f"{shown})", models, None, rebased)
