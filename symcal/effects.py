"""The YAML that adds a candidate effect to a model: a new model that ``extends`` the
instance's model with the missing term, and the instance line that uses it.  The new
model goes in a ``models/`` folder beside the problem file (the user's own models)."""

from __future__ import annotations

import os
import re
from dataclasses import replace
from pathlib import Path

import yaml

from symcal.analysis.discovery import Candidate
from symcal.language.common import parse_expr
from symcal.language.model import load_model
from symcal.problem import Problem, build_problem

_TAGS = {"harmonic": "h", "linear": "lin", "quadratic": "quad", "drift": "drift",
         "angle_harmonic": "ah"}


def _ident(text: str) -> str:
    return re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9_]", "_", text)).strip("_")


def _in_model(problem: Problem, instance: str, variable: str) -> str | None:
    """The instance's own input that ``variable`` is (its name in the model), if any."""
    assert problem.spec is not None
    spec = problem.spec.instances[instance]
    for name, binding in spec.bindings.items():
        if variable in (f"{instance}.{name}", binding.text):
            return name
    return None


def effect_yaml(problem: Problem, cand: Candidate) -> str:
    """YAML text (a new model file and the instance line) that adds ``cand``'s term.

    Parameters
    ----------
    problem
        The problem the candidate was found in.
    cand
        The candidate: ``output`` (``instance.output``) and its basis.
    """
    assert problem.spec is not None
    instance, output = cand.output.split(".", 1)
    ispec = problem.spec.instances[instance]
    model = ispec.model
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
    tag = _TAGS[basis.kind] + (n.group(1) if n and basis.kind == "harmonic" else "")
    tag += "_" + _ident(basis.variable.replace(f"{instance}.", ""))
    params = [f"{col}_{_ident(basis.variable.replace(f'{instance}.', ''))}"
              for col in basis.columns]
    terms = [t.format(v=v, a=a) for t in basis.terms]
    out_unit = model.outputs[output].unit if output in model.outputs else ""
    new_name = f"{model.name}_{tag}"
    assert problem.path is not None
    home = problem.path.parent / "models"   # the user's own models, beside the problem
    lines = [f"# models/{new_name}.yaml (beside {problem.path.name})", f"model: {new_name}",
             f"extends: {Path(os.path.relpath(model.path, home)).as_posix()}",
             f"doc: {model.name} plus {basis.description} on {output} (found by symcal "
             "diagnose)"]
    if new_inputs:
        lines.append("inputs:")
        lines += [f"  {k}: {{doc: bound to {val} in the problem}}"
                  for k, val in new_inputs.items()]
    lines.append("parameters:")
    lines += [f"  {p}: {{value: 0, unit: {out_unit or '1'}, scale: 0.001}}" for p in params]
    lines.append("outputs:")
    body = " + ".join(f"{p}*{t}" for p, t in zip(params, terms, strict=True))
    lines.append(f"  {output}: base.{output} + {body}")
    rel = f"models/{new_name}.yaml"
    bindings = {k: b.text for k, b in ispec.bindings.items()}
    bindings.update(new_inputs)
    shown = ", ".join(f"{k}: {val}" for k, val in bindings.items())
    lines += ["", f"# in {problem.path.name}, instance {instance}:",
              f"  {instance}: {{model: {rel}, inputs: {{{shown}}}}}"]
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
    assert problem.spec is not None
    instance = cand.output.split(".", 1)[0]
    text = effect_yaml(problem, cand)
    model_text, _, instance_text = text.partition("\n\n")
    base = problem.spec.instances[instance].model.path
    model_text = re.sub(r"^extends: .*$", f"extends: {base.as_posix()}", model_text,
                        flags=re.MULTILINE)
    name = re.search(r"^model: (\S+)$", model_text, re.MULTILINE).group(1)
    path = Path(directory) / f"{name}.yaml"
    path.write_text(model_text)
    line = yaml.safe_load(instance_text.split("\n", 1)[1])[instance]
    spec = problem.spec
    old = spec.instances[instance]
    bindings = dict(old.bindings)
    for key, value in line["inputs"].items():
        if key not in bindings:
            bindings[key] = parse_expr(str(value), old.where.child("inputs").child(key))
    new = replace(old, model=load_model(path), bindings=bindings)
    instances = {k: (new if k == instance else v) for k, v in spec.instances.items()}
    return build_problem(replace(spec, instances=instances))
