"""C export of a calibrated model: residuals, their Jacobian and each instance's outputs.

``generate(problem, outdir, result)`` writes self-contained C99 for firmware and tooling:

- ``symcal_<P>_casadi.c/.h``: CasADi's code of functions of ONE observation, the
  residual vector g(θ, u) with ∂g/∂θ and, per sensor instance, its outputs (``p_hat``);
  with a result, the identified parameters are baked in (the functions take only u);
- ``symcal_<P>.h/.c``: the readable wrapper: named structs with one ``double`` per data
  column, parameter, residual and output, their units and order documented, functions
  that need no allocation and no static mutable state (fixed-size local work arrays),
  and a hash of the YAML files and the baked values;
- ``main.c``: an example that evaluates a sample reading (the first row of the
  calibration dataset) and prints the hash, the outputs and the residuals;
- ``Makefile``: builds ``example`` with ``CFLAGS ?= -std=c99 -O2 -Wall -Wextra``.

The flow is one way: :func:`plan` turns a problem (and a result) into C names, units and
values, refusing what cannot be exported with a message that names the part and why;
:func:`generate` builds the CasADi functions and renders the files.  Inputs and
parameters are in their declared units, residuals and outputs in symcal's internal units
(mm, rad, s); a constraint's display unit (µm) is only noted.
"""

from __future__ import annotations

import hashlib
import math
import os
import re
import tempfile
import textwrap
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import casadi as ca

from symcal.base.errors import SymcalError
from symcal.base.files import STAGING_PREFIX, atomic_write_text, clean_stale
from symcal.base.units import internal_unit
from symcal.calibrate.result import Result, check_result_problem, read_result_document
from symcal.problem.symbolic import Problem

#: A calibration result: the object, its ``result.json`` file, or that file's document.
ResultLike = Result | str | Path | Mapping[str, Any]

__all__ = ["CName", "InstancePlan", "Plan", "c_identifier", "casadi_functions", "generate",
           "plan"]

#: Version of the generated layout; part of the hash.
FORMAT = 1
#: Characters of the sha256 hex digest embedded in the code.
HASH_CHARS = 16

#: C keywords (C99 to C23) and names the standard headers may define as macros; a YAML
#: name equal to one of them gets a trailing underscore.
RESERVED = frozenset("""
auto break case char const continue default do double else enum extern float for goto if
inline int long register restrict return short signed sizeof static struct switch typedef
union unsigned void volatile while _Alignas _Alignof _Atomic _Bool _Complex _Generic
_Imaginary _Noreturn _Static_assert _Thread_local alignas alignof bool constexpr false
nullptr static_assert thread_local true typeof typeof_unqual
NULL EOF errno stdin stdout stderr assert offsetof BUFSIZ FILENAME_MAX INFINITY NAN
HUGE_VAL HUGE_VALF HUGE_VALL complex imaginary I casadi_real casadi_int
""".split())

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
    """One exported scalar: its YAML name, C identifier, unit and description."""

    name: str
    c: str
    unit: str
    doc: str


@dataclass(frozen=True)
class InstancePlan:
    """One sensor instance's outputs: ``symcal_<P>_eval_outputs_<c>(...)``."""

    name: str
    c: str
    outputs: tuple[CName, ...]
    reads: tuple[str, ...]
    doc: str


@dataclass(frozen=True, eq=False)
class Plan:
    """What :func:`generate` writes for a problem: C names, units, values and the hash.

    Attributes
    ----------
    problem
        The problem exported.
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
        The constraints, in order (the rows of ``dg_dtheta``); unit is the internal unit.
    instances
        Instances with outputs, in the problem's order.
    values
        Parameter values baked into the code, or None when they are an argument.
    source
        Where the baked values came from (the result file), or None.
    hash
        The first :data:`HASH_CHARS` hex digits of the sha256 of the YAML files, the
        format version and the baked values.
    files
        The YAML files the hash covers: the problem, then its models and their bases.
    """

    problem: Problem
    prefix: str
    macro: str
    inputs: tuple[CName, ...]
    params: tuple[CName, ...]
    residuals: tuple[CName, ...]
    instances: tuple[InstancePlan, ...]
    values: tuple[float, ...] | None
    source: str | None
    hash: str
    files: tuple[Path, ...]

    @property
    def baked(self) -> bool:
        """Whether the parameters are baked into the code."""
        return self.values is not None


# --------------------------------------------------------------------------- names

def c_identifier(name: str) -> str:
    """A C identifier for a YAML name: ``[A-Za-z0-9_]``, no leading digit, no keyword.

    Other characters (the ``.`` of ``s1.k3``) become ``_``; a leading digit gets a
    leading ``_``; a C keyword or standard macro name gets a trailing ``_``.
    """
    text = re.sub(r"[^A-Za-z0-9_]", "_", name) or "_"
    if text[0].isdigit():
        text = "_" + text
    return text + "_" if text in RESERVED else text


def c_prefix(problem: str) -> str:
    """``symcal_<problem>``: the prefix of every C identifier of a problem's export.

    Runs of underscores become one and none ends the name, as CasADi requires of the
    function names built from it (``symcal_toy_cg_residual``): ``my__toy``, ``_toy`` and
    ``toy_`` all give ``symcal_toy``-like prefixes, ``int`` gives ``symcal_int``.
    """
    core = re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9_]", "_", problem)).strip("_")
    return f"symcal_{core}" if core else "symcal_problem"


class _Namespace:
    """C names of one scope (a struct's fields, or a set of identifiers): no two alike."""

    def __init__(self, reserved: Mapping[str, str] | None = None) -> None:
        self.owner: dict[str, str] = dict(reserved or {})

    def claim(self, name: str) -> str:
        c = c_identifier(name)
        if c in self.owner:
            raise SymcalError(f"cannot export: {self.owner[c]} and '{name}' both become the "
                              f"C name '{c}'")
        self.owner[c] = f"'{name}'"
        return c


# ------------------------------------------------------------------------ results

def _load_result(result: ResultLike, problem: Problem) -> tuple[tuple[float, ...], str]:
    """The parameter values of a result (object, file or dict), in θ order, and its label."""
    if isinstance(result, Result):
        if not result.success:
            raise SymcalError(f"the result of '{result.name}' is from a failed solve; symcal "
                              "exports only a successful calibration")
        if result.problem.parameter_names != problem.parameter_names:
            raise SymcalError(f"the result is for problem '{result.name}', whose parameters "
                              f"are not those of '{problem.name}'")
        return tuple(float(v) for v in result.theta), f"the result of '{result.name}'"
    try:
        doc, label = read_result_document(result)
    except RecursionError:
        raise SymcalError(f"result file {result} is nested too deeply to be a symcal "
                          "result") from None
    check_result_problem(doc, label, problem)
    solver = doc.get("solver")
    if not isinstance(solver, Mapping) or not isinstance(solver.get("success"), bool):
        raise SymcalError(f"{label} does not record whether its solve succeeded (no "
                          "'solver': {'success': ...}); symcal exports only a successful "
                          "calibration: solve again")
    if solver["success"] is False:
        raise SymcalError(f"{label} is from a failed solve; symcal exports only a "
                          "successful calibration (or none: omit --result to pass the "
                          "parameters at run time)")
    _check_data(doc, label)
    entries = doc.get("parameters")
    if not isinstance(entries, list):
        raise SymcalError(f"{label} has no 'parameters' list")
    given: dict[str, Any] = {}
    for entry in entries:
        if not isinstance(entry, Mapping) or "name" not in entry or "value" not in entry:
            raise SymcalError(f"{label}: every entry of 'parameters' needs a 'name' and a "
                              f"'value', found {entry!r}")
        name = str(entry["name"])
        if name in given:
            raise SymcalError(f"{label} lists parameter '{name}' twice")
        given[name] = entry["value"]
    values = []
    for p in problem.parameters:
        if p.name not in given:
            raise SymcalError(f"{label} has no value for parameter '{p.name}'")
        value = given.pop(p.name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(value):
            raise SymcalError(f"{label}: parameter '{p.name}' has the value {value!r}, not a "
                              "finite number")
        values.append(float(value))
    if given:
        extra = next(iter(given))
        raise SymcalError(f"{label} has a value for parameter '{extra}', which problem "
                          f"'{problem.name}' does not have")
    return tuple(values), label


def _check_data(doc: Mapping[str, Any], label: str) -> None:
    """Refuse a result whose data files changed (or vanished) since the solve."""
    from symcal.base.files import display_path

    entries = doc.get("datasets", [])
    if not isinstance(entries, list):
        raise SymcalError(f"{label} has no 'datasets' list")
    for entry in entries:
        if not isinstance(entry, Mapping) or not entry.get("file") or not entry.get("sha256"):
            continue
        path = Path(str(entry["file"]))
        try:
            digest = hashlib.sha256(path.read_bytes()).hexdigest()
        except OSError as exc:
            raise SymcalError(f"{label} was computed on {display_path(path)}, which cannot "
                              f"be read now ({exc.strerror}); solve again") from None
        if digest != entry["sha256"]:
            raise SymcalError(f"{label} was computed on another version of dataset "
                              f"'{entry.get('name')}' ({display_path(path)} changed since the "
                              "solve); solve again")


# --------------------------------------------------------------------------- plan

def _source_files(problem: Problem) -> tuple[Path, ...]:
    return problem.source_files()


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


def _check_exportable(what: str, sx: ca.SX, symbols: list[ca.SX]) -> None:
    """Refuse an expression with an operation that has no C translation, or inf/NaN."""
    _check_function(what, ca.Function("check", symbols, [ca.vec(sx)]))


def _check_function(what: str, fn: ca.Function) -> None:
    """Refuse an SX function with an operation that has no C translation, or inf/NaN."""
    for k in range(fn.n_instructions()):
        op = fn.instruction_id(k)
        if op not in _EXPORTABLE_OPS:
            raise SymcalError(f"cannot export {what}: it uses the function "
                              f"'{_OP_NAMES.get(op, op)}' which has no C translation")
        if op == ca.OP_CONST and not math.isfinite(fn.instruction_constant(k)):
            raise SymcalError(f"cannot export {what}: it contains the non-finite constant "
                              f"{fn.instruction_constant(k)}")


def _outputs(problem: Problem) -> list[tuple[str, list[tuple[str, Any]]]]:
    """Per instance with outputs: its name and its (output name, Quantity) pairs."""
    signals = {s.name: s for s in problem.signals}
    out = []
    for inst_name, inst in problem.instances.items():
        items = [(o, signals[f"{inst_name}.{o}"]) for o in inst.model.outputs
                 if f"{inst_name}.{o}" in signals]
        if items:
            out.append((inst_name, items))
    return out


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
        A result for another problem, or without a value for every parameter; two YAML
        names that become the same C identifier; an expression that cannot be written in
        C.  The message names the part and why.
    """
    values, source = (None, None) if result is None else _load_result(result, problem)
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
    fields = _Namespace()
    inputs = tuple(
        CName(c, fields.claim(c), spec_columns[c].unit if c in spec_columns else "",
              spec_columns[c].doc if c in spec_columns else "")
        for c in problem.columns if c in used)
    fields = _Namespace()
    params = tuple(CName(p.name, fields.claim(p.name), p.unit,
                         p.doc + (" (fixed)" if p.fixed else ""))
                   for p in problem.parameters)
    fields = _Namespace({"dg_dtheta": "symcal's Jacobian field"})
    residuals = []
    for q in problem.constraints:
        unit = internal_unit(q.unit)
        note = f"symcal reports it in {q.unit}" if q.unit and q.unit != unit else ""
        doc = "; ".join(t for t in (q.doc, note) if t)
        residuals.append(CName(q.name, fields.claim(q.name), unit, doc))
    instances = []
    for inst_name, items in per_instance:
        fields = _Namespace()
        outs = tuple(CName(f"{inst_name}.{o}", fields.claim(o),
                           internal_unit(q.unit) or q.unit, q.doc)   # values are internal
                     for o, q in items)
        reads: list[str] = []
        for _, q in items:
            reads += [c for c in problem.columns_of(q.sx) if c not in reads]
        reads = [c for c in problem.columns if c in reads]
        doc = problem.instances[inst_name].doc
        instances.append(InstancePlan(inst_name, c_identifier(inst_name), outs,
                                      tuple(reads), doc))
    files = _source_files(problem)
    return Plan(problem, prefix, prefix.upper(), inputs, params, tuple(residuals),
                tuple(instances), values, source, _hash(problem, files, values), files)


# ---------------------------------------------------------------- CasADi functions

def casadi_functions(p: Plan) -> tuple[ca.Function, tuple[ca.Function, ...]]:
    """The CasADi functions of one observation that the C code is generated from.

    ``residual(u) -> (g, dg_dtheta_t)`` and, per instance, ``outputs(u) -> (y...)``; when
    the parameters are not baked, θ is the first argument.  ``dg_dtheta_t`` is ∂g/∂θ
    transposed (dense), so that CasADi's column-major storage is ∂g/∂θ row by row.
    """
    problem = p.problem
    index = {c: i for i, c in enumerate(problem.columns)}
    u = ca.vertcat(*(problem.u[index[c.name]] for c in p.inputs)) if p.inputs \
        else ca.SX(0, 1)
    g = ca.vertcat(*(q.sx for q in problem.constraints))
    exprs = [ca.densify(g), ca.densify(ca.jacobian(g, problem.theta).T)]
    signals = {s.name: s.sx for s in problem.signals}
    counts = []
    for inst in p.instances:
        exprs += [ca.densify(signals[o.name]) for o in inst.outputs]
        counts.append(len(inst.outputs))
    if p.values is not None:
        exprs = ca.substitute(exprs, [problem.theta], [ca.SX(ca.DM(p.values))])
        args, names = [u], ["u"]
    else:
        args, names = [problem.theta, u], ["theta", "u"]
    residual = ca.Function(f"{p.prefix}_cg_residual", args, exprs[:2], names,
                           ["g", "dg_dtheta_t"])
    outputs, at = [], 2
    for k, (inst, n) in enumerate(zip(p.instances, counts, strict=True)):
        outputs.append(ca.Function(f"{p.prefix}_cg_outputs{k}", args, exprs[at:at + n],
                                   names, [o.c for o in inst.outputs]))
        at += n
    for fn, what in [(residual, "the residuals' Jacobian"),
                     *((f, f"the outputs of instance '{i.name}'")
                       for f, i in zip(outputs, p.instances, strict=True))]:
        _check_function(what, fn)
    return residual, tuple(outputs)


_SIGNATURE = re.compile(r"^(static int casadi_f\d+\(([^)]*)\) \{\n)", re.MULTILINE)
_RELEASE = re.compile(r"^(CASADI_SYMBOL_EXPORT void \w+_release\(int mem\) \{\n)",
                      re.MULTILINE)
_LOCALS = re.compile(r"^\s*casadi_real (a\d+(?:, a\d+)*);", re.MULTILINE)


def _quiet_unused(code: str) -> str:
    """Mark CasADi's unused function parameters as used, so -Wextra stays quiet."""
    def casts(match: re.Match) -> str:
        params = [a.split("*")[-1].split()[-1] for a in match.group(2).split(",")]
        return match.group(1) + "  " + " ".join(f"(void){a};" for a in params) + "\n"

    code = _SIGNATURE.sub(casts, code)
    return _RELEASE.sub(lambda m: m.group(1) + "  (void)mem;\n", code)


@dataclass(frozen=True)
class _Code:
    """CasADi's generated source and header, and what the wrapper needs to know of them."""

    source: str
    header: str
    work: dict[str, dict[str, int]]
    scalars: int


def _casadi_code(p: Plan, functions: list[ca.Function]) -> _Code:
    """CasADi's C source and header for ``functions``, with their work sizes.

    The sizes are those of the generated ``<name>_work`` query (its ``_SZ_*`` macros),
    at least 1 each (C has no empty arrays); CasADi's own upper bounds where absent.
    """
    base = f"{p.prefix}_casadi"
    opts: dict[str, Any] = {"with_header": True, "casadi_real": "double",
                            "casadi_int": "long long int", "main": False, "mex": False,
                            "cpp": False, "with_mem": False, "verbose": True}
    clean_stale(tempfile.gettempdir())
    with tempfile.TemporaryDirectory(prefix=f"{STAGING_PREFIX}{os.getpid()}-codegen-") as tmp:
        cg = ca.CodeGenerator(f"{base}.c", opts)
        for fn in functions:
            cg.add(fn)
        cg.generate(tmp + "/")
        source = (Path(tmp) / f"{base}.c").read_text(encoding="utf-8")
        header = (Path(tmp) / f"{base}.h").read_text(encoding="utf-8")
    work = {}
    for fn in functions:
        sizes = {}
        for key, fallback in (("arg", fn.sz_arg()), ("res", fn.sz_res()),
                              ("iw", fn.sz_iw()), ("w", fn.sz_w())):
            found = re.search(rf"^#define {fn.name()}_SZ_{key.upper()} (\d+)$", header,
                              re.MULTILINE)
            sizes[key] = max(1, int(found.group(1)) if found else fallback)
        work[fn.name()] = sizes
    scalars = max((m.group(1).count(",") + 1 for m in _LOCALS.finditer(source)), default=0)
    note = (f"/* symcal: generated by CasADi for problem '{p.problem.name}'; symcal added\n"
            f" * (void) casts of unused parameters.  Use it through {p.prefix}.h. */\n")
    return _Code(note + _quiet_unused(source), note + header, work, scalars)


# ---------------------------------------------------------------------- rendering

def _comment(text: str) -> str:
    """Text safe inside a C comment: one line, no comment terminator, no trigraphs."""
    text = " ".join(text.split())
    return text.replace("*/", "* /").replace("/*", "/ *").replace("??", "? ?")


def _wrap(text: str, first: str = " * ", rest: str = " * ", width: int = 92) -> list[str]:
    """A comment paragraph, wrapped."""
    return textwrap.wrap(_comment(text), width, initial_indent=first,
                         subsequent_indent=rest, break_on_hyphens=False) or [first.rstrip()]


def _string(text: str) -> str:
    """A C string literal (ASCII; other bytes as octal escapes)."""
    out = []
    for byte in text.encode("utf-8"):
        ch = chr(byte)
        if ch in '"\\?':
            out.append("\\" + ch)
        elif 32 <= byte < 127:
            out.append(ch)
        else:
            out.append(f"\\{byte:03o}")
    return '"' + "".join(out) + '"'


def _number(value: float) -> str:
    """A C double literal that reads back exactly."""
    text = repr(float(value))
    return text if any(c in text for c in ".en") else text + ".0"


def _describe(c: CName, yaml: bool = False) -> str:
    """``unit: doc ('yaml.name')`` for a field's comment."""
    text = f"{c.unit or '1'}: {c.doc}" if c.doc else (c.unit or "1")
    if yaml and c.name != c.c:
        text += f" ('{c.name}')"
    return _comment(text)


def _struct(name: str, doc: str, fields: list[str]) -> list[str]:
    return ["/*", *_wrap(doc), " */", "typedef struct {", *fields, f"}} {name};", ""]


def _field_lines(items: Iterable[CName], yaml: bool = False) -> list[str]:
    return [f"    double {c.c};  /* {_describe(c, yaml)} */" for c in items]


def _names_list(items: Iterable[CName]) -> str:
    return ", ".join(c.name for c in items)


class _Render:
    """Renders the wrapper, the example and the Makefile of one :class:`Plan`."""

    def __init__(self, p: Plan, code: _Code, residual: ca.Function,
                 outputs: tuple[ca.Function, ...], command: str) -> None:
        self.p, self.code, self.command = p, code, command
        self.residual, self.outputs = residual, outputs
        self.params_arg = "" if p.baked else f"const {p.prefix}_params *params, "

    def _stack(self) -> int:
        """Bytes of local arrays of the largest wrapper, plus CasADi's local scalars."""
        p = self.p
        per_call = []
        for fn in (self.residual, *self.outputs):
            w = self.code.work[fn.name()]
            outs = sum(fn.nnz_out(i) for i in range(fn.n_out()))
            per_call.append(8 * (w["arg"] + w["res"] + w["iw"] + w["w"] + outs
                                 + len(p.inputs) + (0 if p.baked else len(p.params))))
        return max(per_call) + 8 * self.code.scalars

    def header(self) -> str:
        p, problem = self.p, self.p.problem
        guard = f"{p.macro}_H"
        if p.baked:
            origin = (f"baked in: the values identified in {p.source} "
                      f"({p.prefix}_param_values lists them).")
        else:
            origin = (f"an argument: every function takes const {p.prefix}_params *params "
                      f"({p.prefix}_params_initial holds the problem's initial values).")
        first = p.instances[0] if p.instances else None
        usage = [" * Usage:", f" *     {p.prefix}_input in;"]
        if not p.baked:
            usage.append(f" *     {p.prefix}_params params;     (every field: your calibration)")
        arg = "&params, " if not p.baked else ""
        usage.append(" *     in.<column> = ...;     (every field of the input)")
        if first is not None:
            usage += [
                f" *     {p.prefix}_outputs_{first.c} y;",
                f" *     if ({p.prefix}_eval_outputs_{first.c}(&in, {arg}&y) == 0) {{",
                f" *         ... y.{first.outputs[0].c} ...",
                " *     }",
            ]
        lines = [
            f"/* {p.prefix}.h: the calibrated model of problem '{problem.name}', in C99.",
            " *",
            *_wrap(f"Generated by symcal codegen; do not edit.  Regenerate with: "
                   f"{self.command}"),
            " *",
            *_wrap(problem.doc),
            " *",
            *_wrap("Sources: " + ", ".join(f.name for f in p.files) + "."),
            *_wrap(f"Parameters: {origin}"),
            *_wrap(f"Model hash {p.hash} ({p.macro}_HASH): the first {HASH_CHARS} hex digits "
                   "of the sha256 of the YAML files"
                   + (" and the baked parameter values." if p.baked else ".")),
            " *",
            *_wrap("Inputs and parameters are in their declared units, residuals and "
                   "outputs in symcal's internal units (mm, rad, s); each field's comment "
                   "gives its unit and meaning.  Every function is allocation-free and "
                   "thread-safe: it uses only its arguments and fixed-size local arrays (at "
                   f"most about {self._stack()} bytes of stack), with no static mutable "
                   "state.  Each returns 0 on success, -1 when a pointer is NULL, or "
                   "CasADi's non-zero status."),
            " *",
            *usage,
            " */",
            f"#ifndef {guard}",
            f"#define {guard}",
            "",
            "#ifdef __cplusplus",
            'extern "C" {',
            "#endif",
            "",
            f"#define {p.macro}_HASH {_string(p.hash)}",
            f"#define {p.macro}_N_INPUTS {len(p.inputs)}",
            f"#define {p.macro}_N_PARAMS {len(p.params)}",
            f"#define {p.macro}_N_RESIDUALS {len(p.residuals)}",
            f"#define {p.macro}_PARAMS_BAKED {1 if p.baked else 0}",
            "",
        ]
        lines += _struct(f"{p.prefix}_input",
                         "One observation: the data columns, in this order: "
                         f"{_names_list(p.inputs)}.", _field_lines(p.inputs))
        if not p.baked:
            lines += _struct(f"{p.prefix}_params",
                             "The parameters theta, in this order (the columns of "
                             f"dg_dtheta): {_names_list(p.params)}.",
                             _field_lines(p.params, yaml=True))
        jac = [f"    double dg_dtheta[{p.macro}_N_RESIDUALS][{p.macro}_N_PARAMS];",
               *_wrap("d residual[i] / d parameter[j]: rows in the order above "
                      f"({p.macro}_RESIDUAL_*), columns in the order of theta "
                      f"({p.macro}_PARAM_*, {p.prefix}_param_names); unit: the residual's "
                      "unit per the parameter's unit.", "        /* ", "         * ")]
        jac[-1] += " */"
        lines += _struct(f"{p.prefix}_residuals",
                         "The residuals g(theta, u) of one observation (zero for consistent "
                         f"measurements), in this order: {_names_list(p.residuals)}, as "
                         "written in the YAML (not divided by their sigma); and their "
                         "Jacobian with respect to theta.",
                         _field_lines(p.residuals, yaml=True) + jac)
        for inst in p.instances:
            lines += _struct(f"{p.prefix}_outputs_{inst.c}",
                             f"The calibrated outputs of sensor instance '{inst.name}'"
                             + (f" ({inst.doc})" if inst.doc else "") + ".",
                             _field_lines(inst.outputs))
        lines += [f"/* Rows of dg_dtheta ({p.prefix}_residual_names order). */", "enum {",
                  *(f"    {p.macro}_RESIDUAL_{c.c} = {i},  /* {c.name} */"
                    for i, c in enumerate(p.residuals)), "};", "",
                  f"/* Columns of dg_dtheta: theta ({p.prefix}_param_names order). */",
                  "enum {",
                  *(f"    {p.macro}_PARAM_{c.c} = {i},  /* {c.name}, {_describe(c)} */"
                    for i, c in enumerate(p.params)), "};", ""]
        lines += [
            "/* Names (as in the YAML files) and units, in the orders above. */",
            f"extern const char *const {p.prefix}_input_names[{p.macro}_N_INPUTS];",
            f"extern const char *const {p.prefix}_input_units[{p.macro}_N_INPUTS];",
            f"extern const char *const {p.prefix}_param_names[{p.macro}_N_PARAMS];",
            f"extern const char *const {p.prefix}_param_units[{p.macro}_N_PARAMS];",
            f"extern const char *const {p.prefix}_residual_names[{p.macro}_N_RESIDUALS];",
            f"extern const char *const {p.prefix}_residual_units[{p.macro}_N_RESIDUALS];",
        ]
        if p.baked:
            lines += ["/* The parameter values baked into the functions, in theta order. */",
                      f"extern const double {p.prefix}_param_values[{p.macro}_N_PARAMS];"]
        else:
            lines += ["/* The problem's initial parameter values (not a calibration). */",
                      f"extern const {p.prefix}_params {p.prefix}_params_initial;"]
        lines += ["", "/*", *_wrap("The residuals and dg_dtheta of one observation (reads "
                                   f"{_names_list(p.inputs) or 'no input'})."), " */",
                  f"int {p.prefix}_eval_residuals(const {p.prefix}_input *in, "
                  f"{self.params_arg}{p.prefix}_residuals *out);", ""]
        for inst in p.instances:
            lines += ["/*", *_wrap(f"The outputs of '{inst.name}' ({_names_list(inst.outputs)})"
                                   f" of one observation (reads "
                                   f"{', '.join(inst.reads) or 'no input'})."), " */",
                      f"int {p.prefix}_eval_outputs_{inst.c}(const {p.prefix}_input *in, "
                      f"{self.params_arg}{p.prefix}_outputs_{inst.c} *out);", ""]
        lines += ["#ifdef __cplusplus", '} /* extern "C" */', "#endif", "",
                  f"#endif /* {guard} */", ""]
        return "\n".join(lines)

    def _call(self, fn: ca.Function, outs: list[tuple[str, int]], copy: list[str]
              ) -> list[str]:
        """A wrapper's body: copy in, call CasADi with local work arrays, copy out."""
        p, w = self.p, self.code.work[fn.name()]
        lines = [f"    casadi_real u[{max(1, len(p.inputs))}];"]
        if not p.baked:
            lines.append(f"    casadi_real theta[{max(1, len(p.params))}];")
        lines += [f"    casadi_real {name}[{max(1, n)}];" for name, n in outs]
        lines += [f"    const casadi_real *arg[{w['arg']}];",
                  f"    casadi_real *res[{w['res']}];",
                  f"    casadi_int iw[{w['iw']}];",
                  f"    casadi_real w[{w['w']}];",
                  "    int status;"]
        if any(name == "jac" for name, _ in outs):
            lines.append("    int i, j;")
        null = "in == NULL || out == NULL" + ("" if p.baked else " || params == NULL")
        lines.append(f"    if ({null}) return -1;")
        lines += [f"    u[{i}] = in->{c.c};" for i, c in enumerate(p.inputs)]
        if not p.inputs:
            lines.append("    u[0] = 0.0;")
        if not p.baked:
            lines += [f"    theta[{i}] = params->{c.c};" for i, c in enumerate(p.params)]
            lines.append("    arg[0] = theta;")
        lines.append(f"    arg[{0 if p.baked else 1}] = u;")
        lines += [f"    res[{i}] = {name};" for i, (name, _) in enumerate(outs)]
        lines += [f"    status = {fn.name()}(arg, res, iw, w, 0);",
                  "    if (status != 0) return status;"]
        return lines + copy + ["    return 0;"]

    def source(self) -> str:
        p = self.p
        lines = [f"/* {p.prefix}.c: the functions declared in {p.prefix}.h, over CasADi's code",
                 f" * in {p.prefix}_casadi.c.  Generated by symcal codegen; do not edit. */",
                 "#include <stddef.h>", "",
                 f'#include "{p.prefix}.h"', f'#include "{p.prefix}_casadi.h"', ""]
        for what, count, items in (("input", "INPUTS", p.inputs), ("param", "PARAMS", p.params),
                                   ("residual", "RESIDUALS", p.residuals)):
            for key in ("names", "units"):
                lines += [f"const char *const {p.prefix}_{what}_{key}[{p.macro}_N_{count}] = {{",
                          *(f"    {_string(c.name if key == 'names' else c.unit)},"
                            for c in items), "};"]
        if p.baked:
            lines += [f"const double {p.prefix}_param_values[{p.macro}_N_PARAMS] = {{",
                      *(f"    {_number(v)},  /* {c.name} */"
                        for c, v in zip(p.params, p.values or (), strict=True)), "};"]
        else:
            lines += [f"const {p.prefix}_params {p.prefix}_params_initial = {{",
                      *(f"    {_number(q.value)},  /* {q.name} */"
                        for q in p.problem.parameters), "};"]
        lines.append("")
        n_res, n_par = len(p.residuals), len(p.params)
        copy = [f"    out->{c.c} = g[{i}];" for i, c in enumerate(p.residuals)]
        copy += ["    /* CasADi stores (dg/dtheta)^T column by column: dg/dtheta row by row */",
                 f"    for (i = 0; i < {n_res}; ++i) {{",
                 f"        for (j = 0; j < {n_par}; ++j) {{",
                 f"            out->dg_dtheta[i][j] = jac[i * {n_par} + j];",
                 "        }", "    }"]
        lines += [f"int {p.prefix}_eval_residuals(const {p.prefix}_input *in, "
                  f"{self.params_arg}{p.prefix}_residuals *out)", "{",
                  *self._call(self.residual, [("g", n_res), ("jac", n_res * n_par)], copy),
                  "}", ""]
        for inst, fn in zip(p.instances, self.outputs, strict=True):
            outs = [(f"y{i}", 1) for i in range(len(inst.outputs))]
            copy = [f"    out->{c.c} = y{i}[0];" for i, c in enumerate(inst.outputs)]
            lines += [f"int {p.prefix}_eval_outputs_{inst.c}(const {p.prefix}_input *in, "
                      f"{self.params_arg}{p.prefix}_outputs_{inst.c} *out)", "{",
                      *self._call(fn, outs, copy), "}", ""]
        return "\n".join(lines)

    def main(self, sample: list[float], note: str) -> str:
        p = self.p
        arg = "" if p.baked else "&params, "
        lines = ["/*", *_wrap(f"Example: the calibrated outputs and the residuals of problem "
                              f"'{p.problem.name}' for one sample reading, {note}.  Build and "
                              "run it with 'make run'.  Generated by symcal codegen."),
                 " */",
                 "#include <stdio.h>", "", f'#include "{p.prefix}.h"', "",
                 "static void show(const char *kind, const char *name, double value, "
                 "const char *unit)", "{",
                 '    printf("%-9s %s = %.17g %s\\n", kind, name, value, unit);', "}", "",
                 "int main(void)", "{", f"    {p.prefix}_input in;",
                 f"    {p.prefix}_residuals r;"]
        if not p.baked:
            lines.append(f"    {p.prefix}_params params = {p.prefix}_params_initial;")
        lines += [f"    {p.prefix}_outputs_{i.c} y_{i.c};" for i in p.instances]
        lines += [f"    in.{c.c} = {_number(v)};" for c, v in zip(p.inputs, sample, strict=True)]
        how = ("baked in" if p.baked
               else "the problem's initial values (no result given: pass your own)")
        lines += [f'    printf("problem %s\\n", {_string(p.problem.name)});',
                  f'    printf("hash %s\\n", {p.macro}_HASH);',
                  f'    printf("parameters %s\\n", {_string(how)});']
        lines += [f'    show("input", {_string(c.name)}, in.{c.c}, {_string(c.unit)});'
                  for c in p.inputs]
        for inst in p.instances:
            call = f"{p.prefix}_eval_outputs_{inst.c}"
            lines += [f"    if ({call}(&in, {arg}&y_{inst.c}) != 0) {{",
                      f'        fprintf(stderr, "{call} failed\\n");', "        return 1;",
                      "    }"]
            lines += [f'    show("output", {_string(c.name)}, y_{inst.c}.{c.c}, '
                      f'{_string(c.unit)});' for c in inst.outputs]
        lines += [f"    if ({p.prefix}_eval_residuals(&in, {arg}&r) != 0) {{",
                  f'        fprintf(stderr, "{p.prefix}_eval_residuals failed\\n");',
                  "        return 1;", "    }"]
        lines += [f'    show("residual", {_string(c.name)}, r.{c.c}, {_string(c.unit)});'
                  for c in p.residuals]
        lines += ["    return 0;", "}", ""]
        return "\n".join(lines)

    def makefile(self) -> str:
        p = self.p
        return "\n".join([
            f"# Builds the example of symcal's C export of problem '{p.problem.name}'.",
            f"# Generated by symcal codegen; regenerate with: {self.command}",
            "CFLAGS ?= -std=c99 -O2 -Wall -Wextra",
            "LDLIBS ?= -lm",
            f"SOURCES = main.c {p.prefix}.c {p.prefix}_casadi.c",
            f"HEADERS = {p.prefix}.h {p.prefix}_casadi.h",
            "",
            ".PHONY: all run clean",
            "all: example",
            "",
            "example: $(SOURCES) $(HEADERS)",
            "\t$(CC) $(CPPFLAGS) $(CFLAGS) $(LDFLAGS) -o $@ $(SOURCES) $(LDLIBS)",
            "",
            "run: example",
            "\t./example",
            "",
            "clean:",
            "\trm -f example",
            "",
        ])


def _sample(p: Plan) -> tuple[list[float], str]:
    """The first observation of the calibration dataset (0 where a column is absent)."""
    from symcal.data.loading import load_datasets

    if not p.inputs:
        return [], "without inputs"
    try:
        fit = p.problem.fit_dataset
        data = load_datasets(p.problem, names=[fit])[fit]
    except SymcalError as exc:
        return [0.0] * len(p.inputs), f"zeros (the calibration dataset cannot be read: {exc})"
    if data.n == 0:
        return [0.0] * len(p.inputs), "zeros (the calibration dataset is empty)"
    row = data.matrix([c.name for c in p.inputs])[:, 0]
    values = [float(v) if math.isfinite(v) else 0.0 for v in row]
    missing = [c.name for c, v in zip(p.inputs, row, strict=True) if not math.isfinite(v)]
    note = f"the first row of dataset '{fit}' ({data.source})"
    if missing:
        note += f", with 0 for {', '.join(missing)} (not in it)"
    return values, note


# ------------------------------------------------------------------------ generate

def _command(problem: Problem, outdir: Path, result: object) -> str:
    from symcal.language.yamlio import display_path

    text = f"symcal codegen {display_path(Path(problem.path))}"
    if isinstance(result, (str, Path)):
        text += f" --result {result}"
    return text + f" -o {outdir}"


def generate(problem: Problem, outdir: str | Path, result: ResultLike | None = None,
             force: bool = False, inputs: Iterable[str | Path] = ()) -> list[Path]:
    """Write the C export of ``problem`` to ``outdir``.

    Parameters
    ----------
    problem
        The problem (``symcal.load_problem``).
    outdir
        The output directory; created if absent.  Files are written atomically.
    result
        A result file written by ``symcal solve --out DIR`` (``DIR/result.json``), the
        dict of ``Result.to_dict()``, or None: the parameters are then an argument of
        every function (``symcal_<P>_params``) instead of baked in.
    force
        Replace files in ``outdir`` that symcal did not write (a ``Makefile`` or
        ``main.c`` of your own); never an input file.
    inputs
        Further files the caller read, which must not be replaced either (the problem's
        own files, its data and the result file always count).

    Returns
    -------
    list of Path
        The files written: CasADi's source and header, the wrapper's header and source,
        the example ``main.c`` and the ``Makefile``.

    Raises
    ------
    SymcalError
        A result for another problem, from a failed solve, or computed from other files
        or data; names that collide in C; a part that cannot be written in C (the message
        names it and why); an output that is an input file, a file symcal did not write
        (unless ``force``), or a folder that cannot be written.
    """
    from symcal.base.files import OutputSet, check_outputs

    p = plan(problem, result)
    outdir = Path(outdir)
    names = [f"{p.prefix}_casadi.c", f"{p.prefix}_casadi.h", f"{p.prefix}.h", f"{p.prefix}.c",
             "main.c", "Makefile"]
    reads = {Path(f).resolve() for f in (*p.files, *inputs)}
    reads |= {Path(d.path).resolve() for d in problem.datasets.values() if d.path is not None}
    if isinstance(result, (str, Path)):
        reads.add(Path(result).resolve())
    option, hint = f"-o {outdir}", " (or pass --force to replace it)"
    check_outputs([outdir / name for name in names], reads, option, force, hint)
    residual, outputs = casadi_functions(p)
    code = _casadi_code(p, [residual, *outputs])
    render = _Render(p, code, residual, outputs, _command(problem, outdir, result))
    texts = {
        f"{p.prefix}_casadi.c": code.source,
        f"{p.prefix}_casadi.h": code.header,
        f"{p.prefix}.h": render.header(),
        f"{p.prefix}.c": render.source(),
        "main.c": render.main(*_sample(p)),
        "Makefile": render.makefile(),
    }
    with OutputSet(outdir, reads, option, force, hint) as stage:
        for name, text in texts.items():
            atomic_write_text(stage / name, text)
    return [outdir / name for name in texts]
