"""A candidate effect as files that load: a model that ``extends`` the instance's model with
the missing term, and a problem overlay (``extends:``) that uses it.

The term goes where the physics is: into the model's error expression when the output is
``reading + error`` (so that in an implicit model it is inside the fixed-point
definition), else onto the output itself; a harmonic of the sensor's own reading is
evaluated where the model evaluates its error (``u``: the raw reading in the explicit
model, the true position in the implicit one).  Each coefficient's unit is the output's
divided by the unit of what it multiplies (mm/s for a drift, mm/rad for an angle gain),
and its scale makes the term about a micrometre; a number with a unit in the term (the
period of a harmonic, the centre of a linear term) is a constant in the variable's
internal unit, so that the extension passes the dimension check.  A new model input is
bound to what the variable is in the problem (a data column or an expression of
columns), never to another instance's input, so no binding between instances, and no
cycle, is created.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from symcal.analysis.discovery import Candidate
from symcal.base.errors import escape_controls
from symcal.base.files import write_output
from symcal.base.units import internal_unit
from symcal.language.yamlio import dump_yaml
from symcal.problem.build import load_problem
from symcal.problem.symbolic import Problem

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
    if "/" in per or "*" in per:
        per = f"({per})"
    return f"{out or '1'}/{per}" + (f"^{power}" if power > 1 else "")


def _unit_key(unit: str) -> dict[str, str]:
    """``{unit: U}`` for a declaration in internal unit ``U`` (nothing for none)."""
    return {"unit": unit} if unit else {}


@dataclass(frozen=True)
class Suggestion:
    """A candidate effect as a model extension and the instance's new bindings.

    ``body`` is the model file's document after ``model`` and ``extends`` (doc,
    constants, inputs, parameters, and expressions or outputs); every file is written by
    the YAML emitter (:func:`~symcal.language.yamlio.dump_yaml`), so any path or text
    reads back as it was.
    """

    instance: str
    output: str
    model_name: str
    body: Mapping[str, Any]
    new_inputs: dict[str, str]

    def model_text(self, extends: str) -> str:
        """The new model file, extending ``extends`` (a path as written in the file)."""
        return dump_yaml({"model": self.model_name, "extends": extends, **self.body})

    def instance_entry(self, model: str) -> dict[str, Any]:
        """The overlay's entry that gives the instance the model file ``model``."""
        entry: dict[str, Any] = {"model": model}
        if self.new_inputs:
            entry["inputs"] = dict(self.new_inputs)
        return {self.instance: entry}

    def overlay_text(self, name: str, base: str, model: str, doc: str) -> str:
        """A problem overlay named ``name`` that extends ``base`` and gives the instance
        the model file ``model`` (paths as written in the overlay)."""
        return dump_yaml({"problem": name, "extends": base, "doc": doc,
                          "instances": self.instance_entry(model)})


def suggestion(problem: Problem, cand: Candidate) -> Suggestion:
    """The model extension that adds ``cand``'s term to its output's model."""
    instance, output = cand.output.split(".", 1)
    model = problem.instances[instance].model
    basis = cand.basis
    new_inputs: dict[str, str] = {}
    input_units: dict[str, str] = {}

    def symbol(variable: str, unit: str) -> str:
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
        input_units[name] = internal_unit(unit)
        return name

    v = symbol(basis.variable, basis.unit)
    a = symbol(basis.angle, basis.angle_unit) if basis.angle else ""
    tag = _TAGS[basis.kind] + (str(basis.order) if basis.kind == "harmonic" else "")
    tag += "_" + _ident(basis.variable.replace(f"{instance}.", ""))
    params = [f"{col}_{_ident(basis.variable.replace(f'{instance}.', ''))}"
              for col in basis.columns]
    # numbers with a unit (a period, a centre) are constants in the variable's internal unit
    constants = {key: (f"{key[0].upper() if key == 'period' else key[0]}_{tag}", value)
                 for key, value in (("period", basis.period), ("centre", basis.centre))
                 if "{" + key + "}" in "".join(basis.terms)}
    for key in list(constants):
        name, value = constants[key]
        while name in model.constants or name in model.inputs or name in model.parameters \
                or name in model.expressions:
            name += "_"
        constants[key] = (name, value)
    terms = [t.format(v=v, a=a, **{k: n for k, (n, _) in constants.items()})
             for t in basis.terms]
    signal = next((q for q in problem.signals if q.name == cand.output), None)
    out_unit = internal_unit(signal.unit if signal is not None else
                             model.outputs[output].unit if output in model.outputs else "")
    units = {"harmonic": [out_unit or "1"] * 2,
             "linear": [_unit(out_unit, basis.unit)], "drift": [_unit(out_unit, basis.unit)],
             "quadratic": [_unit(out_unit, basis.unit), _unit(out_unit, basis.unit, 2)],
             "angle_harmonic": [_unit(out_unit, basis.angle_unit)] * 2}[basis.kind]
    scales = basis.scales or (0.001,) * len(params)
    body: dict[str, Any] = {"doc": f"{model.name} plus {basis.description} on {output} "
                                   "(found by symcal diagnose)"}
    if constants:
        var_unit = internal_unit(basis.unit)
        body["constants"] = {n: {"value": float(f"{val:g}"), **_unit_key(var_unit)}
                             for n, val in constants.values()}
    if new_inputs:
        body["inputs"] = {k: {"doc": f"bound to {val} in the problem",
                              **_unit_key(input_units[k])} for k, val in new_inputs.items()}
    body["parameters"] = {p: {"value": 0, "unit": u, "scale": float(f"{s:.3g}")}
                          for p, u, s in zip(params, units, scales, strict=True)}
    terms_text = " + ".join(f"{p}*{t}" for p, t in zip(params, terms, strict=True))
    error = model.error_expression(output)
    if error is not None:
        body["expressions"] = {error: f"base.{error} + {terms_text}"}
    else:
        body["outputs"] = {output: f"base.{output} + {terms_text}"}
    return Suggestion(instance, output, f"{model.name}_{tag}", body, new_inputs)


def _overlay_name(problem: Problem, sug: Suggestion) -> str:
    return f"{problem.name}_{sug.instance}_{sug.model_name.rsplit('_', 2)[-2]}"


def effect_yaml(problem: Problem, cand: Candidate) -> str:
    """The files that add ``cand``'s term, as text: the new model (in ``models/`` beside
    the problem file) and the problem overlay that uses it (beside the problem file)."""
    sug = suggestion(problem, cand)
    home = Path(problem.path).parent
    inst = problem.instances[sug.instance]
    name = _overlay_name(problem, sug)
    beside = escape_controls(Path(problem.path).name)
    lines = [f"# models/{sug.model_name}.yaml (beside {beside})",
             sug.model_text(_rel(inst.model.path, home / "models")).rstrip("\n"), "",
             f"# {name}.yaml (beside {beside}): the problem with it",
             sug.overlay_text(name, Path(problem.path).name, f"models/{sug.model_name}.yaml",
                              f"{problem.name} plus {cand.label}").rstrip("\n")]
    return "\n".join(lines) + "\n"


def write_revision(problem: Problem, cand: Candidate, directory: str | Path,
                   name: str | None = None, also: tuple[Candidate, ...] = ()) -> Path:
    """Write ``cand``'s model and a problem overlay using it into ``directory`` (models in
    ``directory/models``); return the overlay's path.  ``also``: candidates on other
    instances added by the same overlay (the same effect in sibling instances)."""
    directory = Path(directory)
    sugs = [suggestion(problem, c) for c in (cand, *also)]
    if len({s.instance for s in sugs}) != len(sugs):
        raise ValueError("one candidate per instance in a revision")
    entries: dict[str, Any] = {}
    for sug in sugs:
        model_path = directory / "models" / f"{sug.model_name}.yaml"
        inst = problem.instances[sug.instance]
        write_output(model_path, sug.model_text(_rel(inst.model.path, model_path.parent)))
        entries.update(sug.instance_entry(_rel(model_path, directory)))
    name = name or _overlay_name(problem, sugs[0])
    overlay = directory / f"{name}.yaml"
    labels = "; ".join(c.label for c in (cand, *also))
    write_output(overlay, dump_yaml({
        "problem": name, "extends": _rel(Path(problem.path), directory),
        "doc": f"{problem.name} plus {labels}", "instances": entries}))
    return overlay


def revised_problem(problem: Problem, cand: Candidate, directory: str | Path) -> Problem:
    """The problem with ``cand``'s term added as :func:`effect_yaml` suggests, loaded from
    the files :func:`write_revision` writes into ``directory``; ``problem`` is unchanged."""
    return load_problem(write_revision(problem, cand, directory))
