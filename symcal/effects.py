"""A candidate effect as files that load: a model that ``extends`` the instance's model with
the missing term, and a problem overlay (``extends:``) that uses it.

The term goes where the physics is: into the model's error expression when the output is
``reading + error`` (so that in an implicit model it is inside the fixed-point
definition), else onto the output itself; a harmonic of the sensor's own reading is
evaluated where the model evaluates its error (``u``: the raw reading in the explicit
model, the true position in the implicit one).  Each coefficient's unit is the output's
divided by the unit of what it multiplies (mm/s for a drift, mm/rad for an angle gain),
and its scale makes the term about a micrometre.  A new model input is bound to what the
variable is in the problem (a data column or an expression of columns), never to another
instance's input, so no binding between instances, and no cycle, is created.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from symcal.analysis.discovery import Candidate
from symcal.files import write_output
from symcal.problem import Problem, load_problem
from symcal.units import internal_unit

_TAGS = {"harmonic": "h", "linear": "lin", "quadratic": "quad", "drift": "drift",
         "angle_harmonic": "ah"}


def _ident(text: str) -> str:
    return re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9_]", "_", text)).strip("_")


def _rel(path: Path, start: Path) -> str:
    return Path(os.path.relpath(Path(path).resolve(), Path(start).resolve())).as_posix()


def _in_model(problem: Problem, instance: str, variable: str) -> str | None:
    """The instance's own input that ``variable`` is (its name in the model), if any."""
    for name, text in problem.instances[instance].bindings.items():
        if variable in (f"{instance}.{name}", text):
            return name
    return None


def _binding(problem: Problem, variable: str) -> str:
    """What ``variable`` is in the problem's own scope: another instance's input (or the
    point where it evaluates its error) becomes that input's binding (a column or an
    expression of columns), so that no instance is bound to another."""
    if "." in variable:
        inst, _, name = variable.partition(".")
        if inst in problem.instances:
            instance = problem.instances[inst]
            if name in instance.bindings:
                return instance.bindings[name]
            for input_name in instance.model.inputs:   # an evaluation point: its reading
                if instance.model.evaluation_point(input_name) == name:
                    return instance.bindings[input_name]
    return variable


def _unit(out: str, per: str, power: int = 1) -> str:
    per = internal_unit(per)
    if not per:
        return out or "1"
    return f"{out or '1'}/{per}" + (f"^{power}" if power > 1 else "")


@dataclass(frozen=True)
class Suggestion:
    """A candidate effect as a model extension and the instance's new bindings."""

    instance: str
    output: str
    model_name: str
    body: tuple[str, ...]
    new_inputs: dict[str, str]

    def model_text(self, extends: str) -> str:
        """The new model file, extending ``extends`` (a path as written in the file)."""
        lines = [f"model: {self.model_name}", f"extends: {extends}", *self.body]
        return "\n".join(lines) + "\n"

    def overlay_text(self, name: str, base: str, model: str, doc: str) -> str:
        """A problem overlay named ``name`` that extends ``base`` and gives the instance
        the model file ``model`` (paths as written in the overlay)."""
        inputs = ", ".join(f"{k}: {v}" for k, v in self.new_inputs.items())
        entry = f"{{model: {model}" + (f", inputs: {{{inputs}}}" if inputs else "") + "}"
        return "\n".join([f"problem: {name}", f"extends: {base}", f"doc: {doc}",
                          "instances:", f"  {self.instance}: {entry}"]) + "\n"


def suggestion(problem: Problem, cand: Candidate) -> Suggestion:
    """The model extension that adds ``cand``'s term to its output's model."""
    instance, output = cand.output.split(".", 1)
    model = problem.instances[instance].model
    basis = cand.basis
    new_inputs: dict[str, str] = {}

    def symbol(variable: str) -> str:
        own = _in_model(problem, instance, variable)
        if own is not None:
            point = model.evaluation_point(own) if basis.kind == "harmonic" else None
            return point or own
        inst, _, local = variable.partition(".")
        if inst == instance and local in model.expressions:   # its evaluation point
            return local
        bound = _binding(problem, variable)
        for key, text in problem.instances[instance].bindings.items():
            if text == bound:                     # an input already bound to it
                return key
        name = "v_" + _ident(variable)
        while name in model.inputs or name in model.expressions or name in model.parameters:
            name += "_"
        new_inputs[name] = bound
        return name

    v = symbol(basis.variable)
    a = symbol(basis.angle) if basis.angle else ""
    tag = _TAGS[basis.kind] + (str(basis.order) if basis.kind == "harmonic" else "")
    tag += "_" + _ident(basis.variable.replace(f"{instance}.", ""))
    params = [f"{col}_{_ident(basis.variable.replace(f'{instance}.', ''))}"
              for col in basis.columns]
    terms = [t.format(v=v, a=a) for t in basis.terms]
    out_unit = internal_unit(model.outputs[output].unit) if output in model.outputs else ""
    units = {"harmonic": [out_unit or "1"] * 2,
             "linear": [_unit(out_unit, basis.unit)], "drift": [_unit(out_unit, basis.unit)],
             "quadratic": [_unit(out_unit, basis.unit), _unit(out_unit, basis.unit, 2)],
             "angle_harmonic": [_unit(out_unit, basis.angle_unit)] * 2}[basis.kind]
    scales = basis.scales or (0.001,) * len(params)
    body = [f"doc: {model.name} plus {basis.description} on {output} (found by symcal "
            "diagnose)"]
    if new_inputs:
        body.append("inputs:")
        body += [f"  {k}: {{doc: bound to {val} in the problem}}" for k, val in new_inputs.items()]
    body.append("parameters:")
    body += [f"  {p}: {{value: 0, unit: {u}, scale: {s:.3g}}}"
             for p, u, s in zip(params, units, scales, strict=True)]
    terms_text = " + ".join(f"{p}*{t}" for p, t in zip(params, terms, strict=True))
    error = model.error_expression(output)
    if error is not None:
        body += ["expressions:", f"  {error}: base.{error} + {terms_text}"]
    else:
        body += ["outputs:", f"  {output}: base.{output} + {terms_text}"]
    return Suggestion(instance, output, f"{model.name}_{tag}", tuple(body), new_inputs)


def _overlay_name(problem: Problem, sug: Suggestion) -> str:
    return f"{problem.name}_{sug.instance}_{sug.model_name.rsplit('_', 2)[-2]}"


def effect_yaml(problem: Problem, cand: Candidate) -> str:
    """The files that add ``cand``'s term, as text: the new model (in ``models/`` beside
    the problem file) and the problem overlay that uses it (beside the problem file)."""
    sug = suggestion(problem, cand)
    home = Path(problem.path).parent
    inst = problem.instances[sug.instance]
    name = _overlay_name(problem, sug)
    lines = [f"# models/{sug.model_name}.yaml (beside {Path(problem.path).name})",
             sug.model_text(_rel(inst.model.path, home / "models")).rstrip("\n"), "",
             f"# {name}.yaml (beside {Path(problem.path).name}): the problem with it",
             sug.overlay_text(name, Path(problem.path).name, f"models/{sug.model_name}.yaml",
                              f"{problem.name} plus {cand.label}").rstrip("\n")]
    return "\n".join(lines) + "\n"


def write_revision(problem: Problem, cand: Candidate, directory: str | Path,
                   name: str | None = None) -> Path:
    """Write ``cand``'s model and a problem overlay using it into ``directory`` (models in
    ``directory/models``); return the overlay's path."""
    directory = Path(directory)
    sug = suggestion(problem, cand)
    inst = problem.instances[sug.instance]
    model_path = directory / "models" / f"{sug.model_name}.yaml"
    write_output(model_path, sug.model_text(_rel(inst.model.path, model_path.parent)))
    name = name or _overlay_name(problem, sug)
    overlay = directory / f"{name}.yaml"
    write_output(overlay, sug.overlay_text(
        name, _rel(Path(problem.path), directory), _rel(model_path, directory),
        f"{problem.name} plus {cand.label}"))
    return overlay


def revised_problem(problem: Problem, cand: Candidate, directory: str | Path) -> Problem:
    """The problem with ``cand``'s term added as :func:`effect_yaml` suggests, loaded from
    the files :func:`write_revision` writes into ``directory``; ``problem`` is unchanged."""
    return load_problem(write_revision(problem, cand, directory))
