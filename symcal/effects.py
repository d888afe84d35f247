"""The YAML that adds a candidate effect to a model: a new model that ``extends`` the
instance's model with the missing term, and the instance line that uses it.  The new
model goes in a ``models/`` folder beside the problem file (the user's own models)."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from symcal.analysis.discovery import Candidate
from symcal.files import atomic_write_text
from symcal.language.model import load_model
from symcal.problem import Problem

_TAGS = {"harmonic": "h", "linear": "lin", "quadratic": "quad", "drift": "drift",
         "angle_harmonic": "ah"}


def _ident(text: str) -> str:
    return re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9_]", "_", text)).strip("_")


def _in_model(problem: Problem, instance: str, variable: str) -> str | None:
    """The instance's own input that ``variable`` is (its name in the model), if any."""
    for name, text in problem.instances[instance].bindings.items():
        if variable in (f"{instance}.{name}", text):
            return name
    return None


@dataclass(frozen=True)
class Suggestion:
    """A candidate effect as a model that extends the instance's model, and the instance's
    new bindings (inputs the new model adds)."""

    instance: str
    output: str
    model_name: str
    body: tuple[str, ...]
    new_inputs: dict[str, str]

    def model_text(self, extends: str) -> str:
        """The new model file, extending ``extends`` (a path as written in the file)."""
        lines = [f"model: {self.model_name}", f"extends: {extends}", *self.body]
        return "\n".join(lines) + "\n"


def suggestion(problem: Problem, cand: Candidate) -> Suggestion:
    """The model extension that adds ``cand``'s term to its output."""
    instance, output = cand.output.split(".", 1)
    model = problem.instances[instance].model
    basis = cand.basis
    new_inputs: dict[str, str] = {}

    def symbol(variable: str) -> str:
        own = _in_model(problem, instance, variable)
        if own is not None:
            return own
        name = "v_" + _ident(variable)
        new_inputs[name] = variable
        return name

    v = symbol(basis.variable)
    a = symbol(basis.angle) if basis.angle else ""
    n = re.search(r"harmonic (\d+)", basis.description)
    tag = _TAGS[basis.kind] + (n.group(1) if n is not None and basis.kind == "harmonic" else "")
    tag += "_" + _ident(basis.variable.replace(f"{instance}.", ""))
    params = [f"{col}_{_ident(basis.variable.replace(f'{instance}.', ''))}"
              for col in basis.columns]
    terms = [t.format(v=v, a=a) for t in basis.terms]
    out_unit = model.outputs[output].unit if output in model.outputs else ""
    body = [f"doc: {model.name} plus {basis.description} on {output} (found by symcal "
            "diagnose)"]
    if new_inputs:
        body.append("inputs:")
        body += [f"  {k}: {{doc: bound to {val} in the problem}}" for k, val in new_inputs.items()]
    body.append("parameters:")
    body += [f"  {p}: {{value: 0, unit: {out_unit or '1'}, scale: 0.001}}" for p in params]
    body.append("outputs:")
    terms_text = " + ".join(f"{p}*{t}" for p, t in zip(params, terms, strict=True))
    body.append(f"  {output}: base.{output} + {terms_text}")
    return Suggestion(instance, output, f"{model.name}_{tag}", tuple(body), new_inputs)


def effect_yaml(problem: Problem, cand: Candidate) -> str:
    """YAML text (a new model file and the instance line) that adds ``cand``'s term.

    Parameters
    ----------
    problem
        The problem the candidate was found in.
    cand
        The candidate: ``output`` (``instance.output``) and its basis.
    """
    sug = suggestion(problem, cand)
    inst = problem.instances[sug.instance]
    home = problem.path.parent / "models"   # the user's own models, beside the problem
    extends = Path(os.path.relpath(inst.model.path, home)).as_posix()
    lines = [f"# models/{sug.model_name}.yaml (beside {problem.path.name})",
             sug.model_text(extends).rstrip("\n")]
    bindings = dict(inst.bindings)
    bindings.update(sug.new_inputs)
    shown = ", ".join(f"{k}: {val}" for k, val in bindings.items())
    lines += ["", f"# in {problem.path.name}, instance {sug.instance}:",
              f"  {sug.instance}: {{model: models/{sug.model_name}.yaml, inputs: {{{shown}}}}}"]
    return "\n".join(lines) + "\n"


def revised_problem(problem: Problem, cand: Candidate, directory: str | Path) -> Problem:
    """The problem with ``cand``'s term added as :func:`effect_yaml` suggests.

    The suggested model file is written to ``directory`` (extending the instance's model
    by absolute path) and loaded like any model; the instance is rebound to it.

    Returns
    -------
    Problem
        A new problem; ``problem`` is not modified.
    """
    sug = suggestion(problem, cand)
    base = problem.instances[sug.instance].model.path
    path = Path(directory) / f"{sug.model_name}.yaml"
    atomic_write_text(path, sug.model_text(base.as_posix()))
    return problem.with_instance(sug.instance, load_model(path), sug.new_inputs)
