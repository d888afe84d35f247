"""The CasADi functions of one observation and the C code CasADi writes for them.

Every target wraps the same code: ``residual(u) -> (g, dg_dtheta_t)`` and, per sensor
instance with outputs, ``outputs(u) -> (y...)`` (θ first when it is not baked), in
symcal's internal units; the wrapper converts at its boundary (:attr:`CName.scale`).
"""

from __future__ import annotations

import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import casadi as ca

from symcal.base.files import STAGING_PREFIX, clean_stale
from symcal.export.plan import Plan, check_function
from symcal.problem.symbolic import Problem

__all__ = ["CasadiCode", "Work", "casadi_code", "casadi_functions"]


def casadi_functions(problem: Problem, p: Plan) -> tuple[ca.Function, tuple[ca.Function, ...]]:
    """The CasADi functions of one observation that the C code is generated from.

    Parameters
    ----------
    problem
        The problem exported.
    p
        Its plan (:func:`~symcal.export.plan.plan`).

    Returns
    -------
    residual, outputs
        ``residual(u) -> (g, dg_dtheta_t)`` and, per instance of ``p.instances``,
        ``outputs(u) -> (y...)``; when the parameters are not baked, θ is the first
        argument.  ``dg_dtheta_t`` is ∂g/∂θ transposed (dense), so that CasADi's
        column-major storage is ∂g/∂θ row by row.  Values are in internal units.

    Raises
    ------
    SymcalError
        An operation without a C translation, or a non-finite constant, in the
        Jacobian or the outputs.
    """
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
        check_function(what, fn)
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
class Work:
    """One CasADi function as a wrapper calls it: its C name, the sizes of its work
    arrays, and the local array of each result (name, size); every size at least 1 (C
    has no empty arrays)."""

    name: str
    arg: int
    res: int
    iw: int
    w: int
    results: tuple[tuple[str, int], ...]

    @property
    def stack(self) -> int:
        """Bytes of the work arrays and result arrays of one call."""
        return 8 * (self.arg + self.res + self.iw + self.w + sum(n for _, n in self.results))


@dataclass(frozen=True)
class CasadiCode:
    """CasADi's generated source and header, and what the wrapper needs to know of them.

    Attributes
    ----------
    source, header
        The text of ``<prefix>_casadi.c`` and ``<prefix>_casadi.h``.
    residual
        The residual function's call.
    outputs
        Each instance's output function's call, in the plan's order.
    scalars
        Most local scalars of one of CasADi's functions (their stack, 8 bytes each).
    """

    source: str
    header: str
    residual: Work
    outputs: tuple[Work, ...]
    scalars: int


def _work(fn: ca.Function, header: str, locals_: tuple[str, ...]) -> Work:
    """The call of ``fn`` with its results in local arrays named ``locals_``: the sizes
    of the generated ``<name>_work`` query (its ``_SZ_*`` macros), CasADi's own upper
    bounds where absent."""
    sizes = {}
    for key, fallback in (("arg", fn.sz_arg()), ("res", fn.sz_res()), ("iw", fn.sz_iw()),
                          ("w", fn.sz_w())):
        found = re.search(rf"^#define {fn.name()}_SZ_{key.upper()} (\d+)$", header,
                          re.MULTILINE)
        sizes[key] = max(1, int(found.group(1)) if found else fallback)
    results = tuple((name, max(1, fn.nnz_out(i))) for i, name in enumerate(locals_))
    return Work(fn.name(), sizes["arg"], sizes["res"], sizes["iw"], sizes["w"], results)


def casadi_code(p: Plan, residual: ca.Function, outputs: tuple[ca.Function, ...]
                ) -> CasadiCode:
    """CasADi's C source and header for the functions of :func:`casadi_functions`.

    Parameters
    ----------
    p
        The plan.
    residual, outputs
        The functions.

    Returns
    -------
    CasadiCode
    """
    base = f"{p.prefix}_casadi"
    opts: dict[str, Any] = {"with_header": True, "casadi_real": "double",
                            "casadi_int": "long long int", "main": False, "mex": False,
                            "cpp": False, "with_mem": False, "verbose": True}
    clean_stale(tempfile.gettempdir())
    with tempfile.TemporaryDirectory(prefix=f"{STAGING_PREFIX}{os.getpid()}-codegen-") as tmp:
        cg = ca.CodeGenerator(f"{base}.c", opts)
        for fn in (residual, *outputs):
            cg.add(fn)
        cg.generate(tmp + "/")
        source = (Path(tmp) / f"{base}.c").read_text(encoding="utf-8")
        header = (Path(tmp) / f"{base}.h").read_text(encoding="utf-8")
    scalars = max((m.group(1).count(",") + 1 for m in _LOCALS.finditer(source)), default=0)
    note = (f"/* symcal: generated by CasADi for problem '{p.problem}'; symcal added\n"
            f" * (void) casts of unused parameters.  Use it through {p.prefix}.h. */\n")
    calls = tuple(_work(fn, header, tuple(f"y{i}" for i in range(fn.n_out())))
                  for fn in outputs)
    return CasadiCode(note + _quiet_unused(source), note + header,
                      _work(residual, header, ("g", "jac")), calls, scalars)
