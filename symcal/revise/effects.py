"""A candidate effect as files that load: a model that ``extends`` the instance's model
with the missing term and/or a problem overlay (``extends:``) that uses it.

**Terms** (harmonic, linear, quadratic, drift, angle_harmonic, product, gain, coupling)
go where the physics is: into the model's error expression when the output is
``reading + error`` (so that in an implicit model it is inside the fixed-point
definition), else onto the output itself (``c_y: base.c_y + ...``, which keeps the
output's declared unit; a gain is ``I: base.I + gain_T*base.I*(v_T - c_gain_T)``, a
dimensionless rate per unit of the variable; a coupling ``Bx: base.Bx + cpl_By*By``,
another output of the same model by name); a harmonic of
the sensor's own reading is evaluated where the model evaluates its error (``u``: the raw
reading in the explicit model, the true position in the implicit one).  A new model
input is bound to what the variable is in the problem (a data column or an expression of
columns), never to another instance's input, so no binding between instances, and no
cycle, is created; the instance's own outputs and expressions are used by name.

**Units a person reads.**  Each coefficient's unit is the output's declared unit over
the unit of what it multiplies, in the variable's declared unit (angles in rad),
simplified by pint (``m/s^2/K``, ``mm/rad``, none for a plain ratio); its ``scale`` is
:attr:`~symcal.analysis.discovery.Basis.scales` (internal units) written in that unit,
within symcal's range of magnitudes.  A number with a unit in the term (the period of a
harmonic, the centre of a linear term) is a constant in the variable's unit.

**Other kinds** are overlays only: ``constant`` makes one or more constants one
parameter started at their value (a problem constant is re-declared as a parameter of
the same name; instances bind their model's constant to it: ``constants: {rho: rho}``);
``fixed`` frees a fixed parameter (``fixed: false``); ``latency`` makes an instance read
its columns late by one delay ``tau`` (``c + tau*c_rate``, with ``c_rate`` a derived
column ``rate_of: c``).

**Files.**  Every candidate has its own file names (kind, order, variable and output in
them), and a file is never written over another candidate's: where a file of that name
holds something else, the new one gets another name.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from symcal.analysis.discovery import Candidate
from symcal.base.errors import escape_controls
from symcal.base.files import write_output
from symcal.base.units import internal_of, is_angle, parse_unit, registry, size, text_of
from symcal.language import expr
from symcal.language.common import MAGNITUDE
from symcal.language.yamlio import dump_yaml
from symcal.problem.build import load_problem
from symcal.problem.symbolic import Problem

_TAGS = {"harmonic": "h", "linear": "lin", "quadratic": "quad", "cubic": "cub",
         "drift": "drift",
         "angle_harmonic": "ah", "product": "prod", "power": "pow", "gain": "gain",
         "coupling": "cpl"}
#: Kinds written as a term added to one output (a model extension).
TERMS = tuple(_TAGS)
#: Names of the constants a term's placeholders stand for, by placeholder.
_CONSTANTS = {"period": "P", "centre": "c", "other_centre": "d"}


def _ident(text: str) -> str:
    return re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9_]", "_", text)).strip("_")


def coefficient_names(cand: Candidate) -> tuple[tuple[str, ...], ...]:
    """The names a revision gives the coefficients of ``cand``'s term, without the
    instance (``("prod_gyro_T",)``), for each order a product's variables can be written
    in: a candidate whose names its sensor already has is a term an earlier round added,
    tested again.  Empty for kinds that are not a term."""
    basis = cand.basis
    if basis.kind not in TERMS:
        return ()
    instance = cand.output.split(".", 1)[0]
    names = [_ident(v.replace(f"{instance}.", "")) for v in (basis.variable, basis.other)
             if v]
    orders = [names] if len(names) < 2 else [names, names[::-1]]
    return tuple(tuple(f"{col}_{'_'.join(order)}" for col in basis.columns)
                 for order in orders)


def _coefficient_name(name: str, output: str, taken: set[str]) -> str:
    """A coefficient's name, ``name`` where the model has no such name yet (``taken``),
    else named after its output too (``cpl_By_Bz`` where an earlier round gave ``Bx`` its
    ``cpl_By``: one name would make the two terms share one coefficient)."""
    if name not in taken:
        return name
    name = f"{name}_{output}"
    while name in taken:
        name += "_"
    return name


def _rel(path: Path, start: Path) -> str:
    return Path(os.path.relpath(Path(path).resolve(), Path(start).resolve())).as_posix()


def _short(value: float, digits: int = 6) -> float:
    return float(f"{value:.{digits}g}")


# --------------------------------------------------------------------------- units


def written_unit(unit: str) -> str:
    """The unit a variable is written in: as declared, an angle in rad."""
    return "rad" if unit and is_angle(unit) else unit


def per(numerator: str, *denominators: tuple[str, int]) -> str:
    """``numerator`` over each ``(unit, power)``, as a person reads it: the declared units
    with what cancels cancelled (``m/s**2`` over ``K`` is ``m/K/s^2``, ``m/s`` over
    ``rad/s`` is ``m/rad``), ``""`` for a plain ratio (``m/s**2`` over ``m/s**2``, ``um``
    over ``mm``); two different units of one dimension left are reduced to one of them
    (``um*s/mm`` is ``s``; a load cell's ``kN`` over ``mV/V`` over ``delta_degC`` is
    ``kN/Δ°C``, where internal units read ``g*mm/s^2/K``): the value is written in that
    unit, whatever factor it differs from the first by."""
    unit = parse_unit(numerator or "1")
    whole = unit
    for den, power in denominators:
        whole = whole / parse_unit(den or "1") ** power
    if numerator and unit.dimensionless and not is_angle(numerator) and \
            abs(size(numerator) - 1.0) > 1e-12 and dict(whole._units):
        # a ratio the user chose to read in (ns/s, ppm as um/m) is kept whole: reduced
        # with the rest it was 1/h, a clock's aging written as 2.5e-10 1/h
        rest = per("", *denominators)
        return (text_of(unit).replace("µ", "u") + rest[1:] if rest.startswith("1/") else
                "*".join(x for x in (text_of(unit).replace("µ", "u"), rest) if x))
    for den, power in denominators:
        unit = unit / parse_unit(den or "1") ** power
    if not internal_of(unit):
        return ""
    reg = registry()
    signatures = [frozenset(reg.Quantity(1.0, name).to_root_units().unit_items())
                  for name, _ in reg.Quantity(1.0, unit).unit_items()]
    named = [s for s in signatures if s]
    if len(set(named)) < len(named):
        unit = reg.Quantity(1.0, unit).to_reduced_units().units
    return text_of(unit).replace("µ", "u")


#: The doc of a term's centre (:func:`_centre_doc`; :func:`centre_variable` reads it).
CENTRE_DOC = ("reference {} of the other parameters (the term is zero there; set a "
              "datasheet value to have them hold at it)")


def _centre_doc(key: str, basis: Any) -> dict[str, str]:
    """The doc of a term's centre: where the parameters already there now hold (a
    sensitivity at the run's mean temperature, where the term is written about it, not
    at a datasheet's 25 degC)."""
    if key not in ("centre", "other_centre"):
        return {}
    variable = basis.variable if key == "centre" else basis.other
    return {"doc": CENTRE_DOC.format(variable)}


def centre_variable(doc: str) -> str | None:
    """The variable a constant is the centre of, where its doc is a term's centre as
    :func:`suggestion` writes it (:data:`CENTRE_DOC`), else None."""
    head, tail = CENTRE_DOC.split("{}")
    if doc.startswith(head) and doc.endswith(tail) and len(doc) > len(head) + len(tail):
        return doc[len(head):len(doc) - len(tail)]
    return None


def scale_in(value: float, unit: str) -> float:
    """A coefficient's scale given in internal units, in ``unit``, within the magnitudes
    symcal accepts (:data:`~symcal.language.common.MAGNITUDE`)."""
    shown = abs(value) / size(unit)
    if not math.isfinite(shown) or shown <= 0:
        shown = 1.0
    return _short(min(max(shown, 1.0 / MAGNITUDE), MAGNITUDE), 3)


def _unit_key(unit: str) -> dict[str, str]:
    """``{unit: U}`` for a declaration in unit ``U`` (nothing for none)."""
    return {"unit": unit} if unit else {}


# --------------------------------------------------------------------------- terms


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


@dataclass(frozen=True)
class Suggestion:
    """A candidate term as a model extension and the instance's new bindings.

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
    tag: str = ""

    def model_text(self, extends: str, name: str | None = None) -> str:
        """The new model file, extending ``extends`` (a path as written in the file)."""
        return dump_yaml({"model": name or self.model_name, "extends": extends, **self.body})

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
    """The model extension that adds ``cand``'s term to its output's model.

    Raises
    ------
    ValueError
        For a kind that is not a term on one output (``constant``, ``fixed``,
        ``latency``: see :func:`revision`), or a term on an output in that output itself.
    """
    basis = cand.basis
    if basis.kind not in TERMS:
        raise ValueError(f"a '{basis.kind}' candidate is not a term on one output: "
                         "see revision()")
    instance, output = cand.output.split(".", 1)
    model = problem.instances[instance].model
    new_inputs: dict[str, str] = {}
    input_units: dict[str, str] = {}

    def symbol(variable: str, unit: str, harmonic: bool = False) -> str:
        own = _in_model(problem, instance, variable)
        if own is not None:
            point = model.evaluation_point(own) if harmonic else None
            return point or own
        inst, _, local = variable.partition(".")
        if inst == instance and local in model.expressions:   # its own expression
            return local
        if inst == instance and local in model.outputs:      # another of its outputs
            if local == output:
                raise ValueError(f"a term in {cand.output} cannot depend on "
                                 f"{cand.output} itself")
            return local
        bound = _binding(problem, variable)
        for key, text in problem.instances[instance].bindings.items():
            if text == bound:                     # an input already bound to it
                return key
        name = "v_" + _ident(variable)
        while name in model.inputs or name in model.expressions or name in model.parameters \
                or name in model.constants or name in model.outputs:
            name += "_"
        new_inputs[name] = bound
        input_units[name] = written_unit(unit)
        return name

    v = symbol(basis.variable, basis.unit, basis.kind == "harmonic")
    a = symbol(basis.angle, basis.angle_unit) if basis.angle else ""
    w = symbol(basis.other, basis.other_unit) if basis.other else ""
    local = _ident(basis.variable.replace(f"{instance}.", ""))
    if basis.other:
        local += "_" + _ident(basis.other.replace(f"{instance}.", ""))
    tag = _TAGS[basis.kind] + (str(basis.order) if basis.kind == "harmonic" or (
        basis.kind == "angle_harmonic" and basis.order > 1) else "")
    if basis.angle:
        tag += "_" + _ident(basis.angle.replace(f"{instance}.", ""))
    tag += "_" + local
    taken = {*model.constants, *model.inputs, *model.parameters, *model.expressions,
             *model.outputs}
    params = [_coefficient_name(f"{col}_{local}", _ident(output), taken)
              for col in basis.columns]
    text = "".join(basis.terms)
    var_unit, other_unit = written_unit(basis.unit), written_unit(basis.other_unit)
    # numbers with a unit (a period, centres) are constants in their variable's unit
    numbers = {"period": (basis.period, var_unit, 12), "centre": (basis.centre, var_unit, 6),
               "other_centre": (basis.other_centre, other_unit, 6)}
    constants: dict[str, tuple[str, float, str]] = {}
    taken |= {*new_inputs, *params}
    for key, (value, unit, digits) in numbers.items():
        if "{" + key + "}" not in text:
            continue
        name = f"{_CONSTANTS[key]}_{tag}"
        while name in taken:
            name += "_"
        taken.add(name)
        constants[key] = (name, _short(value / size(unit), digits), unit)
    terms = [t.format(v=v, a=a, w=w, o=f"base.{output}",
                      **{k: n for k, (n, _, _) in constants.items()})
             for t in basis.terms]
    signal = next((q for q in problem.signals if q.name == cand.output), None)
    out_unit = (signal.unit if signal is not None else
                model.outputs[output].unit if output in model.outputs else "")
    angle_unit = written_unit(basis.angle_unit)
    units = {"harmonic": [per(out_unit)] * 2,
             "linear": [per(out_unit, (var_unit, 1))],
             "drift": [per(out_unit, (var_unit, 1))],
             "quadratic": [per(out_unit, (var_unit, 1)), per(out_unit, (var_unit, 2))],
             "cubic": [per(out_unit, (var_unit, 3))],
             "angle_harmonic": [per(out_unit, (angle_unit, 1))] * 2,
             "product": [per(out_unit, (var_unit, 1), (other_unit, 1))] * len(params),
             "power": [per(out_unit, (var_unit, 2),
                           (other_unit, -1 if basis.terms[0].endswith("/{w}") else 1))],
             "gain": [per("", (var_unit, 1))],
             "coupling": [per(out_unit, (var_unit, 1))],
             }[basis.kind]
    if basis.kind == "quadratic" and len(basis.columns) == 1:   # one part left (the
        units = units[1:] if basis.columns == ("quad",) else units[:1]   # other redundant)
    if len(units) != len(params):
        raise ValueError(f"a '{basis.kind}' term has {len(units)} coefficients, the "
                         f"candidate names {len(params)}")
    body: dict[str, Any] = {"doc": f"{model.name} plus {basis.description} on {output} "
                                   "(found by symcal diagnose)"}
    if constants:
        body["constants"] = {n: {"value": val, **_unit_key(u), **_centre_doc(key, basis)}
                             for key, (n, val, u) in constants.items()}
    if new_inputs:
        body["inputs"] = {k: {"doc": f"bound to {val} in the problem",
                              **_unit_key(input_units[k])} for k, val in new_inputs.items()}
    scales = basis.scales if len(basis.scales) == len(params) else (None,) * len(params)
    body["parameters"] = {
        p: {"value": 0, **_unit_key(u), **({"scale": scale_in(s, u)} if s else {})}
        for p, u, s in zip(params, units, scales, strict=True)}
    terms_text = " + ".join(f"{p}*{t}" for p, t in zip(params, terms, strict=True))
    error = model.error_expression(output)
    if error is not None and "{o}" not in text:   # a gain multiplies the output itself
        body["expressions"] = {error: f"base.{error} + {terms_text}"}
    else:
        body["outputs"] = {output: f"base.{output} + {terms_text}"}
    return Suggestion(instance, output, f"{model.name}_{_ident(output)}_{tag}", body,
                      new_inputs, tag)


# --------------------------------------------------------------------------- overlays


@dataclass(frozen=True)
class Revision:
    """What a candidate changes: model extensions (:class:`Suggestion`, each for one
    instance) and the problem overlay's sections (``parameters``, ``constants``,
    ``expressions``, ``columns``, ``instances``), and the overlay's name by default."""

    name: str
    models: tuple[Suggestion, ...] = ()
    sections: dict[str, dict[str, Any]] = field(default_factory=dict)


def _free(problem: Problem, name: str) -> str:
    """``name``, or ``name_2``, ... where the problem already uses it."""
    spec = problem.spec.system
    taken = {*spec.constants, *spec.parameters, *spec.columns, *spec.instances,
             *spec.expressions, *spec.constraints, "pi"}
    out, k = name, 1
    while out in taken:
        k += 1
        out = f"{name}_{k}"
    return out


def _constant(problem: Problem, cand: Candidate) -> Revision:
    """Constants (keys of ``Problem.constants``) made one parameter at their value."""
    infos = {c.key: c for c in problem.constants}
    missing = [k for k in cand.basis.targets if k not in infos]
    if missing or not cand.basis.targets:
        raise ValueError(f"no constant {', '.join(missing) or '(none named)'} in problem "
                         f"'{problem.name}'; it has: {', '.join(infos)}")
    targets = [infos[k] for k in cand.basis.targets]
    first = targets[0]
    internal = [c.value * size(c.unit) for c in targets]
    if any(abs(x - internal[0]) > 1e-12 * max(abs(internal[0]), 1e-300) for x in internal):
        raise ValueError(f"the constants {', '.join(cand.basis.targets)} have different "
                         "values: one parameter cannot start at all of them")
    tops = [c for c in targets if c.instance is None]
    name = tops[0].key if tops else _free(problem, first.name)
    param: dict[str, Any] = {"value": first.value, **_unit_key(first.unit)}
    if not 1.0 / MAGNITUDE < abs(first.value) < MAGNITUDE:
        scale = cand.basis.scales[0] if cand.basis.scales else size(first.unit)
        param["scale"] = scale_in(scale, first.unit)
    param["doc"] = f"{first.doc or first.name} (was a constant)"
    sections: dict[str, dict[str, Any]] = {"parameters": {name: param}}
    for c in tops[1:]:                     # other problem constants: the same parameter
        sections.setdefault("constants", {})[c.key] = None
        sections.setdefault("expressions", {})[c.key] = {"expr": name, **_unit_key(c.unit),
                                                         "doc": c.doc or c.key}
    for c in targets:
        if c.instance is not None:
            entry = sections.setdefault("instances", {}).setdefault(c.instance, {})
            entry.setdefault("constants", {})[c.name] = name
    sections.update(_candidates_without(problem, "constants", set(cand.basis.targets)))
    return Revision(f"{problem.name}_const_{_ident(name)}", (), sections)


def _candidates_without(problem: Problem, kind: str, gone: set[str]) -> dict[str, Any]:
    """The problem's ``candidates:`` list of ``kind`` (``constants`` or ``fixed``)
    restated without ``gone``, where the problem restricts it and lists one of them: a
    constant made a parameter, or a parameter freed, is no longer one to test, and the
    inherited list would name what the revision no longer has (improve stopped on an
    internal error: "'pyr.eps' matches no constant")."""
    lists = {k: list(getattr(problem.candidates, k)) for k in ("constants", "fixed")}
    if problem.candidates.where is None or not gone & set(lists[kind]):
        return {}
    lists[kind] = [n for n in lists[kind] if n not in gone]
    # the section replaces the base's whole: both lists, as the problem resolved them
    return {"candidates": {k: v or False for k, v in lists.items()}}


def _fixed(problem: Problem, cand: Candidate) -> Revision:
    """The fixed parameter ``targets[0]`` freed."""
    if not cand.basis.targets or cand.basis.targets[0] not in problem.index:
        raise ValueError(f"no parameter {cand.basis.targets[:1]} in problem '{problem.name}'")
    pname = cand.basis.targets[0]
    p = problem.parameters[problem.index[pname]]
    bounds = {k: v for k, v in (("lower", p.lower), ("upper", p.upper)) if math.isfinite(v)}
    inst, _, local = pname.partition(".")
    sections: dict[str, Any]
    if local and inst in problem.instances:
        entry = {"value": p.value, **bounds, "scale": p.scale, "fixed": False}
        sections = {"instances": {inst: {"parameters": {local: entry}}}}
    else:
        sections = {"parameters": {pname: {"value": p.value, **_unit_key(p.unit), **bounds,
                                           "scale": p.scale, "fixed": False,
                                           **({"doc": p.doc} if p.doc else {})}}}
    sections.update(_candidates_without(problem, "fixed", {pname}))
    return Revision(f"{problem.name}_free_{_ident(pname)}", (), sections)


def _substituted(node: expr.Node, names: Mapping[str, expr.Node]) -> expr.Node:
    """``node`` with every name in ``names`` replaced by its expression."""
    if isinstance(node, expr.Name) and node.name in names:
        return names[node.name]
    if isinstance(node, expr.Unary):
        return expr.Unary(node.op, _substituted(node.operand, names))
    if isinstance(node, expr.Binary):
        return expr.Binary(node.op, _substituted(node.left, names),
                           _substituted(node.right, names))
    if isinstance(node, expr.Call):
        return expr.Call(node.func, tuple(_substituted(a, names) for a in node.args))
    return node


def _late(node: expr.Node, rates: Mapping[str, str], tau: str) -> expr.Node:
    """``node`` with every column ``c`` of ``rates`` read as ``c + tau*c_rate``."""
    return _substituted(node, {c: expr.Binary("+", expr.Name(c), expr.Binary(
        "*", expr.Name(tau), expr.Name(rate))) for c, rate in rates.items()})


def _noise_text(value: float, unit: str) -> str:
    """A noise of ``value`` (internal units) as a column declares it: ``3.54 deg/s^2``."""
    return f"{value / size(unit or '1'):.3g} {unit}".strip()


def _latency(problem: Problem, cand: Candidate) -> Revision:
    """Instance ``variable`` reads its columns ``targets`` late by one delay ``tau``."""
    inst = cand.basis.variable
    if inst not in problem.instances:
        raise ValueError(f"no instance '{inst}' in problem '{problem.name}'")
    specs = problem.column_specs
    time = next((c for c in specs.values() if c.role == "time"), None)
    if time is None:
        raise ValueError(f"problem '{problem.name}' declares no time column (role: time): "
                         "a latency needs the readings' rates")
    tau = _free(problem, f"tau_{_ident(inst)}")
    rates: dict[str, str] = {}
    columns: dict[str, Any] = {}
    left = dict(zip(cand.basis.targets, cand.basis.rate_noise, strict=False))
    for col in cand.basis.targets:
        if col not in specs:
            raise ValueError(f"'{col}' is not a column of problem '{problem.name}'")
        existing = next((k for k, c in specs.items() if c.rate_of == col), None)
        if existing is not None:
            rates[col] = existing
            continue
        rates[col] = _free(problem, f"{col}_rate")
        unit = per(specs[col].unit, (time.unit, 1))
        noisy = left.get(col, 0.0)
        columns[rates[col]] = {"rate_of": col, **_unit_key(unit),
                               "noise": _noise_text(noisy, unit) if noisy > 0 else 0,
                               "doc": (f"rate of {col}; its noise is what {col}'s declared "
                                       "noise leaves in a rate at the fitted data's "
                                       "sampling" if noisy > 0 else
                                       f"rate of {col} (its noise, times the delay {tau}, "
                                       "is neglected)")}
    inputs: dict[str, str] = {}
    for key, text in problem.instances[inst].bindings.items():
        node = expr.parse(text)
        if any(n.name in rates for n in expr.names(node)):
            inputs[key] = expr.render(_late(node, rates, tau))
    if not inputs:
        raise ValueError(f"instance '{inst}' reads none of {', '.join(cand.basis.targets)} "
                         "in its input bindings")
    scale = scale_in(cand.basis.scales[0], "s") if cand.basis.scales else 1e-3
    sections: dict[str, dict[str, Any]] = {
        "parameters": {tau: {"value": 0, "unit": "s", "scale": scale,
                             "doc": f"delay of {inst}'s readings of "
                                    f"{', '.join(cand.basis.targets)} (latency)"}},
        "instances": {inst: {"inputs": inputs}}}
    if columns:
        sections["columns"] = columns
    return Revision(f"{problem.name}_{_ident(inst)}_latency", (), sections)


def _zero(problem: Problem, cand: Candidate) -> Revision:
    """Column ``variable`` read with its zero off: every instance of ``targets`` that
    reads it reads ``c + zero_c`` instead (``zero_c`` a new parameter, minus the zero's
    offset)."""
    col = cand.basis.variable
    spec = problem.column_specs.get(col)
    if spec is None:
        raise ValueError(f"'{col}' is not a column of problem '{problem.name}'")
    name = _free(problem, f"zero_{_ident(col)}")
    shifted = {col: expr.Binary("+", expr.Name(col), expr.Name(name))}
    instances: dict[str, Any] = {}
    for inst in cand.basis.targets:
        if inst not in problem.instances:
            raise ValueError(f"no instance '{inst}' in problem '{problem.name}'")
        inputs = {}
        for key, text in problem.instances[inst].bindings.items():
            node = expr.parse(text)
            if any(n.name == col for n in expr.names(node)):
                inputs[key] = expr.render(_substituted(node, shifted))
        if inputs:
            instances[inst] = {"inputs": inputs}
    if not instances:
        raise ValueError(f"none of {', '.join(cand.basis.targets)} reads '{col}' in its "
                         "input bindings")
    param: dict[str, Any] = {"value": 0, **_unit_key(spec.unit),
                             "doc": f"added to every reading of {col}: minus the offset of "
                                    "its zero"}
    if cand.basis.scales:
        param["scale"] = scale_in(cand.basis.scales[0], spec.unit)
    return Revision(f"{problem.name}_{_ident(col)}_zero", (),
                    {"parameters": {name: param}, "instances": instances})


def revision(problem: Problem, cand: Candidate) -> Revision:
    """What adding ``cand`` changes, as a model extension and/or overlay sections."""
    kind = cand.basis.kind
    if kind in TERMS:
        sug = suggestion(problem, cand)
        inputs = {"inputs": dict(sug.new_inputs)} if sug.new_inputs else {}
        return Revision(f"{problem.name}_{sug.instance}_{_ident(sug.output)}_{sug.tag}",
                        (sug,), {"instances": {sug.instance: inputs}})
    makers = {"constant": _constant, "fixed": _fixed, "latency": _latency, "zero": _zero}
    if kind not in makers:
        raise ValueError(f"a '{kind}' candidate has no revision here"
                         + (": the model's own approximation is a variant of its files"
                            if kind == "approximation" else ""))
    return makers[kind](problem, cand)


def _merge(into: dict[str, Any], more: Mapping[str, Any], path: str = "") -> None:
    """Merge overlay sections, refusing two different values for one key."""
    for key, value in more.items():
        if key in into and isinstance(into[key], dict) and isinstance(value, dict):
            _merge(into[key], value, f"{path}{key}.")
        elif key in into and into[key] != value:
            raise ValueError(f"two candidates of one revision set {path}{key} differently")
        else:
            into[key] = value


def _combined(problem: Problem, cands: tuple[Candidate, ...]) -> tuple[Revision, ...]:
    revs = tuple(revision(problem, c) for c in cands)
    owners = [s.instance for r in revs for s in r.models]
    if len(set(owners)) != len(owners):
        raise ValueError("one candidate per instance in a revision")
    return revs


def _overlay(problem: Problem, revs: tuple[Revision, ...], name: str, base: str, doc: str,
             models: Mapping[str, str]) -> dict[str, Any]:
    """The overlay document: ``models`` maps an instance to its new model file."""
    sections: dict[str, Any] = {}
    for rev in revs:
        _merge(sections, rev.sections)
    instances = sections.pop("instances", {})
    for inst, path in models.items():
        instances[inst] = {"model": path, **instances.get(inst, {})}
    doc_: dict[str, Any] = {"problem": name, "extends": base, "doc": doc}
    for key in ("constants", "parameters", "columns", "expressions", "candidates"):
        if key in sections:
            doc_[key] = sections[key]
    if instances:
        doc_["instances"] = {k: v for k, v in instances.items() if v}
    return doc_


def effect_yaml(problem: Problem, cand: Candidate) -> str:
    """The files that add ``cand``, as text: the new model (in ``models/`` beside the
    problem file), if the candidate is a term, and the problem overlay that uses it
    (beside the problem file)."""
    rev = revision(problem, cand)
    home = Path(problem.path).parent
    beside = escape_controls(Path(problem.path).name)
    lines: list[str] = []
    models: dict[str, str] = {}
    for sug in rev.models:
        inst = problem.instances[sug.instance]
        lines += [f"# models/{sug.model_name}.yaml (beside {beside})",
                  sug.model_text(_rel(inst.model.path, home / "models")).rstrip("\n"), ""]
        models[sug.instance] = f"models/{sug.model_name}.yaml"
    overlay = _overlay(problem, (rev,), rev.name, Path(problem.path).name,
                       f"{problem.name} plus {cand.label}", models)
    lines += [f"# {rev.name}.yaml (beside {beside}): the problem with it",
              dump_yaml(overlay).rstrip("\n")]
    return "\n".join(lines) + "\n"


def write_revision(problem: Problem, cand: Candidate, directory: str | Path,
                   name: str | None = None, also: tuple[Candidate, ...] = ()) -> Path:
    """Write ``cand``'s files into ``directory`` (models in ``directory/models``): the
    model extension of a term, and a problem overlay that uses it; return the overlay's
    path.  ``also``: candidates added by the same overlay (the same effect in sibling
    instances, each with its own model).  A file is never written over another
    candidate's: where a file of the name holds something else, the file gets another
    name (``NAME_2.yaml``); the overlay's ``problem:`` is always its file's stem."""
    directory = Path(directory)
    revs = _combined(problem, (cand, *also))
    models: dict[str, str] = {}
    for rev in revs:
        for sug in rev.models:
            inst = problem.instances[sug.instance]
            path, k = directory / "models" / f"{sug.model_name}.yaml", 1
            while True:   # the model's name follows its file's
                stem = sug.model_name if k == 1 else f"{sug.model_name}_{k}"
                path = path.with_name(f"{stem}.yaml")
                text = sug.model_text(_rel(inst.model.path, path.parent), stem)
                if not path.exists() or path.read_text(encoding="utf-8") == text:
                    break
                k += 1
            if not path.exists():
                write_output(path, text)
            models[sug.instance] = _rel(path, directory)
    labels = "; ".join(c.label for c in (cand, *also))
    stem, k = name or revs[0].name, 1
    while True:
        current = stem if k == 1 else f"{stem}_{k}"
        overlay = directory / f"{current}.yaml"
        text = dump_yaml(_overlay(problem, revs, current, _rel(Path(problem.path), directory),
                                  f"{problem.name} plus {labels}", models))
        if not overlay.exists() or overlay.read_text(encoding="utf-8") == text:
            break
        k += 1
    if not overlay.exists():
        write_output(overlay, text)
    return overlay


def revised_problem(problem: Problem, cand: Candidate, directory: str | Path) -> Problem:
    """The problem with ``cand`` added as :func:`effect_yaml` suggests, loaded from the
    files :func:`write_revision` writes into ``directory``; ``problem`` is unchanged."""
    return load_problem(write_revision(problem, cand, directory))

