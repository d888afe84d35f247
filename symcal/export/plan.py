"""What an export holds, as plain data: C names, units and the values baked in.

:func:`plan` turns a problem (and a result) into a :class:`Plan`: every data column read,
parameter, residual and sensor output with its YAML name, C identifier, unit and meaning,
the parameter values, and a hash of the YAML files.  It refuses what cannot be exported
with a message that names the part and why.  A plan holds no CasADi object and no
problem: the templates of every target read it as it is.

**Units.**  Every value crosses the boundary of the generated code in the unit the YAML
states for it: a data column in its column's unit, a parameter in its declared unit (both
enter symcal's expressions that way already), a sensor output in the unit its model
declares, a residual in its constraint's unit.  symcal computes outputs and residuals in
internal units (mm, rad, s); :attr:`CName.scale` is what the generated code divides them
by, the size of the field's unit in internal units.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import casadi as ca

from symcal.base.errors import SymcalError
from symcal.base.units import UnitError, internal_unit, size
from symcal.export.baked import ResultLike, baked_values
from symcal.export.names import Namespace, c_identifier, c_prefix
from symcal.problem.symbolic import Problem, Quantity

__all__ = ["FORMAT", "HASH_CHARS", "CName", "InstancePlan", "Plan", "check_function", "plan"]

#: Version of the generated layout; part of the hash.  2: outputs and residuals in their
#: declared units (1: in internal units).
FORMAT = 2
#: Characters of the sha256 hex digest embedded in the code.
HASH_CHARS = 16

#: CasADi operations with a C99 translation (the others are refused, named).
_EXPORTABLE_OPS = frozenset(
    getattr(ca, f"OP_{n}") for n in """
    ASSIGN ADD SUB MUL DIV NEG EXP LOG POW CONSTPOW SQRT SQ TWICE SIN COS TAN ASIN ACOS
    ATAN LT LE EQ NE NOT AND OR FLOOR CEIL FMOD FABS SIGN COPYSIGN IF_ELSE_ZERO ERF FMIN
    FMAX INV SINH COSH TANH ASINH ACOSH ATANH ATAN2 CONST INPUT OUTPUT PARAMETER LOG1P
    EXPM1 HYPOT REMAINDER
    """.split())
_OP_NAMES = {getattr(ca, n): n[3:].lower() for n in dir(ca) if n.startswith("OP_")}


@dataclass(frozen=True)
class CName:
    """One exported scalar.

    Attributes
    ----------
    name
        Its name in the YAML files (``s1.k3``).
    c
        Its C identifier (``s1_k3``).
    unit
        The unit the generated code takes or returns it in (``""``: none).
    doc
        What it is.
    scale
        What symcal's value of it is divided by at the boundary of the generated code:
        the size of ``unit`` in internal units for outputs and residuals, 1 for inputs and
        parameters (they enter symcal's expressions in their own units).
    internal
        The internal unit symcal computes it in (``mm/s^2`` for ``m/s**2``), for outputs
        and residuals.
    """

    name: str
    c: str
    unit: str
    doc: str
    scale: float = 1.0
    internal: str = ""


@dataclass(frozen=True)
class InstancePlan:
    """One sensor instance's outputs: ``symcal_<P>_eval_outputs_<c>(...)``."""

    name: str
    c: str
    outputs: tuple[CName, ...]
    reads: tuple[str, ...]
    doc: str


@dataclass(frozen=True)
class Plan:
    """What an export writes for a problem: C names, units, values and the hash.

    Attributes
    ----------
    problem
        The problem's name.
    doc
        The problem's description.
    prefix
        Lower-case prefix of every C identifier (``symcal_<problem>``).
    macro
        Upper-case prefix of macros and index constants (``SYMCAL_<PROBLEM>``).
    inputs
        Data columns read by the residuals or the outputs, in the problem's column order:
        the fields of ``<prefix>_input``.
    params
        Every parameter, in the order of θ (the columns of ``dg_dtheta``).
    residuals
        The constraints, in order (the rows of ``dg_dtheta``).
    instances
        Instances with outputs, in the problem's order.
    initial
        The problem's initial parameter values, in θ order.
    values
        Parameter values baked into the code, or None when they are an argument.
    source
        Where the baked values came from (the result), or None.
    hash
        The first :data:`HASH_CHARS` hex digits of the sha256 of the YAML files, the
        format version and the baked values.
    files
        The YAML files the hash covers: the problem, then its models and their bases.
    """

    problem: str
    doc: str
    prefix: str
    macro: str
    inputs: tuple[CName, ...]
    params: tuple[CName, ...]
    residuals: tuple[CName, ...]
    instances: tuple[InstancePlan, ...]
    initial: tuple[float, ...]
    values: tuple[float, ...] | None
    source: str | None
    hash: str
    files: tuple[Path, ...]

    @property
    def baked(self) -> bool:
        """Whether the parameters are baked into the code."""
        return self.values is not None


def _hash(problem: Problem, files: Iterable[Path], values: tuple[float, ...] | None) -> str:
    digest = hashlib.sha256(f"symcal-codegen {FORMAT}\n".encode())
    for path in files:
        try:
            content = Path(path).read_bytes()
        except OSError as exc:
            raise SymcalError(f"cannot read {path} to hash the model: {exc.strerror}") from None
        digest.update(f"file {len(content)}\n".encode() + content)
    if values is not None:
        for p, v in zip(problem.parameters, values, strict=True):
            digest.update(f"{p.name}={v!r}\n".encode())
    return digest.hexdigest()[:HASH_CHARS]


def check_function(what: str, fn: ca.Function) -> None:
    """Refuse an SX function with an operation that has no C translation, or inf/NaN.

    Raises
    ------
    SymcalError
        Naming ``what`` and the operation or constant.
    """
    for k in range(fn.n_instructions()):
        op = fn.instruction_id(k)
        if op not in _EXPORTABLE_OPS:
            raise SymcalError(f"cannot export {what}: it uses the function "
                              f"'{_OP_NAMES.get(op, op)}' which has no C translation")
        if op == ca.OP_CONST and not math.isfinite(fn.instruction_constant(k)):
            raise SymcalError(f"cannot export {what}: it contains the non-finite constant "
                              f"{fn.instruction_constant(k)}")


def _check_exportable(what: str, sx: ca.SX, symbols: list[ca.SX]) -> None:
    check_function(what, ca.Function("check", symbols, [ca.vec(sx)]))


def _outputs(problem: Problem) -> list[tuple[str, list[tuple[str, Quantity]]]]:
    """Per instance with outputs: its name and its (output name, Quantity) pairs."""
    signals = {s.name: s for s in problem.signals}
    out = []
    for inst_name, inst in problem.instances.items():
        items = [(o, signals[f"{inst_name}.{o}"]) for o in inst.model.outputs
                 if f"{inst_name}.{o}" in signals]
        if items:
            out.append((inst_name, items))
    return out


def _scale(what: str, unit: str) -> float:
    """The size of ``unit`` in internal units: what symcal's value of ``what`` is divided
    by to be in ``unit``."""
    try:
        factor = size(unit)
    except UnitError as exc:
        raise SymcalError(f"cannot export {what}: {exc.message}") from None
    if not (math.isfinite(factor) and factor > 0):
        raise SymcalError(f"cannot export {what}: its unit '{unit}' has no finite size")
    return factor


def plan(problem: Problem, result: ResultLike | None = None) -> Plan:
    """Decide the C names, units and values of a problem's export, or refuse it.

    Parameters
    ----------
    problem
        The problem (``symcal.load_problem``).
    result
        A :class:`~symcal.calibrate.result.Result`, a result file (``symcal solve --out DIR``
        writes ``DIR/result.json``), its dict (``Result.to_dict()``), or None to take the
        parameters as an argument.

    Returns
    -------
    Plan

    Raises
    ------
    SymcalError
        A result refused by :func:`~symcal.export.baked.baked_values`; two YAML names that
        become the same C identifier; an expression that cannot be written in C.  The
        message names the part and why.
    """
    values, source = (None, None) if result is None else baked_values(result, problem)
    for par in problem.parameters if values is None else ():
        if not math.isfinite(par.value):
            raise SymcalError(f"cannot export parameter '{par.name}': its initial value "
                              f"{par.value} is not finite (give a result file)")
    prefix = c_prefix(problem.name)
    symbols = [problem.theta, problem.u]
    for q in problem.constraints:
        _check_exportable(f"constraint '{q.name}'", q.sx, symbols)
    per_instance = _outputs(problem)
    for _, items in per_instance:
        for _, q in items:
            _check_exportable(f"output '{q.name}'", q.sx, symbols)

    spec_columns = problem.column_specs
    used: set[str] = set()
    for q in problem.constraints:
        used.update(problem.columns_of(q.sx))
    for _, items in per_instance:
        for _, q in items:
            used.update(problem.columns_of(q.sx))
    if not used:
        raise SymcalError(f"cannot export problem '{problem.name}': its constraints and "
                          "outputs read no data column, so there is nothing to evaluate per "
                          "observation")
    fields = Namespace()
    inputs = tuple(
        CName(c, fields.claim(c), spec_columns[c].unit if c in spec_columns else "",
              spec_columns[c].doc if c in spec_columns else "")
        for c in problem.columns if c in used)
    fields = Namespace()
    params = tuple(CName(p.name, fields.claim(p.name), p.unit,
                         p.doc + (" (fixed)" if p.fixed else ""))
                   for p in problem.parameters)
    fields = Namespace({"dg_dtheta": "symcal's Jacobian field"})
    residuals = tuple(CName(q.name, fields.claim(q.name), q.unit, q.doc,
                            _scale(f"constraint '{q.name}'", q.unit), internal_unit(q.unit))
                      for q in problem.constraints)
    instances = []
    for inst_name, items in per_instance:
        fields = Namespace()
        outs = tuple(CName(f"{inst_name}.{o}", fields.claim(o), q.unit, q.doc,
                           _scale(f"output '{inst_name}.{o}'", q.unit), internal_unit(q.unit))
                     for o, q in items)
        reads: list[str] = []
        for _, q in items:
            reads += [c for c in problem.columns_of(q.sx) if c not in reads]
        reads = [c for c in problem.columns if c in reads]
        doc = problem.instances[inst_name].doc
        instances.append(InstancePlan(inst_name, c_identifier(inst_name), outs,
                                      tuple(reads), doc))
    files = problem.source_files()
    return Plan(problem.name, problem.doc, prefix, prefix.upper(), inputs, params, residuals,
                tuple(instances), tuple(float(p.value) for p in problem.parameters), values,
                source, _hash(problem, files, values), files)
