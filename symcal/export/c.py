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

The flow is one way: :func:`~symcal.export.plan.plan` decides the names, units and values
(plain data), :mod:`~symcal.export.casadi_code` writes CasADi's code, and the templates of
a target (:mod:`~symcal.export.render`, ``templates/c/``) write the rest from both.
Every value crosses the boundary in the unit the YAML states for it (inputs in their
column's unit, parameters in theirs, outputs in their model's, residuals in their
constraint's).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from symcal.base.errors import SymcalError
from symcal.base.files import atomic_write_text
from symcal.export.baked import ResultLike
from symcal.export.casadi_code import CasadiCode, casadi_code, casadi_functions
from symcal.export.names import c_identifier
from symcal.export.plan import HASH_CHARS, CName, InstancePlan, Plan, plan
from symcal.export.render import TARGETS, Target, render
from symcal.problem.symbolic import Problem

__all__ = ["CName", "InstancePlan", "Plan", "ResultLike", "c_identifier", "context",
           "generate", "plan"]


def _sample(problem: Problem, p: Plan) -> tuple[list[float], str]:
    """The first observation of the fitted dataset (0 where a column is absent)."""
    from symcal.data.loading import load_datasets

    if not p.inputs:
        return [], "without inputs"
    try:
        fit = problem.fit_dataset
        data = load_datasets(problem, names=[fit])[fit]
    except SymcalError as exc:
        return [0.0] * len(p.inputs), f"zeros (the fitted dataset cannot be read: {exc})"
    if data.n == 0:
        return [0.0] * len(p.inputs), "zeros (the fitted dataset is empty)"
    row = data.matrix([c.name for c in p.inputs])[:, 0]
    values = [float(v) if math.isfinite(v) else 0.0 for v in row]
    missing = [c.name for c, v in zip(p.inputs, row, strict=True) if not math.isfinite(v)]
    note = f"the first row of dataset '{fit}' ({data.source})"
    if missing:
        note += f", with 0 for {', '.join(missing)} (not in it)"
    return values, note


def _command(problem: Problem, outdir: Path, result: object) -> str:
    from symcal.language.yamlio import display_path

    text = f"symcal codegen {display_path(Path(problem.path))}"
    if isinstance(result, (str, Path)):
        text += f" --result {result}"
    return text + f" -o {outdir}"


def _stack(p: Plan, code: CasadiCode) -> int:
    """Bytes of local arrays of the largest wrapper, plus CasADi's local scalars."""
    copies = 8 * (len(p.inputs) + (0 if p.baked else len(p.params)))
    return max(w.stack + copies for w in (code.residual, *code.outputs)) + 8 * code.scalars


def context(p: Plan, code: CasadiCode, sample: list[float], sample_note: str,
            command: str) -> dict[str, Any]:
    """What every template reads: the plan's fields, the calls of CasADi's functions,
    the example's sample reading and the command that regenerates the code.

    Parameters
    ----------
    p
        The plan.
    code
        CasADi's code for it.
    sample
        The example's input values, in the order of ``p.inputs``.
    sample_note
        Where they come from.
    command
        The command line that writes these files again.

    Returns
    -------
    dict
    """
    return {
        "problem": p.problem, "doc": p.doc, "prefix": p.prefix, "macro": p.macro,
        "files": [f.name for f in p.files], "hash": p.hash, "hash_chars": HASH_CHARS,
        "baked": p.baked, "source": p.source, "inputs": p.inputs, "params": p.params,
        "param_values": p.values if p.values is not None else p.initial,
        "residuals": p.residuals, "instances": p.instances, "residual": code.residual,
        "instance_calls": list(zip(p.instances, code.outputs, strict=True)),
        "stack": _stack(p, code), "sample": sample, "sample_note": sample_note,
        "command": command,
    }


def generate(problem: Problem, outdir: str | Path, result: ResultLike | None = None,
             force: bool = False, inputs: Iterable[str | Path] = (),
             target: Target | str = "c") -> list[Path]:
    """Write the C export of ``problem`` to ``outdir``.

    Parameters
    ----------
    problem
        The problem (``symcal.load_problem``).
    outdir
        The output directory; created if absent.  Files are written atomically.
    result
        A :class:`~symcal.calibrate.result.Result`, a result file written by ``symcal
        solve --out DIR`` (``DIR/result.json``), its dict (``Result.to_dict()``), or None:
        the parameters are then an argument of every function (``symcal_<P>_params``)
        instead of baked in.  Files and dicts are read by ``Result.load``.
    force
        Replace files in ``outdir`` that symcal did not write (a ``Makefile`` or
        ``main.c`` of your own); never an input file.
    inputs
        Further files the caller read, which must not be replaced either (the problem's
        own files, its data and the result file always count).
    target
        The template set that wraps CasADi's code (:data:`~symcal.export.render.TARGETS`,
        or a :class:`~symcal.export.render.Target`); ``"c"``, the C99 wrapper, example and
        Makefile, by default.

    Returns
    -------
    list of Path
        The files written: CasADi's source and header, then the target's files (for
        ``"c"``: the wrapper's header and source, the example ``main.c`` and the
        ``Makefile``).

    Raises
    ------
    SymcalError
        A result for another problem, from a failed solve, or computed from other files
        or data; names that collide in C; a part that cannot be written in C (the message
        names it and why); an output that is an input file, a file symcal did not write
        (unless ``force``), or a folder that cannot be written; an unknown target.
    """
    from symcal.base.files import OutputSet, check_outputs

    if isinstance(target, str) and target not in TARGETS:
        raise SymcalError(f"no code generation target '{target}'; symcal has "
                          f"{', '.join(TARGETS)} (or give a Target of your own templates)")
    chosen = TARGETS[target] if isinstance(target, str) else target
    p = plan(problem, result)
    outdir = Path(outdir)
    names = [f"{p.prefix}_casadi.c", f"{p.prefix}_casadi.h",
             *(name.format(prefix=p.prefix) for _, name in chosen.files)]
    reads = {Path(f).resolve() for f in (*p.files, *inputs)}
    reads |= {Path(d.path).resolve() for d in problem.datasets.values() if d.path is not None}
    if isinstance(result, (str, Path)):
        reads.add(Path(result).resolve())
    option, hint = f"-o {outdir}", " (or pass --force to replace it)"
    check_outputs([outdir / name for name in names], reads, option, force, hint)
    residual, outputs = casadi_functions(problem, p)
    code = casadi_code(p, residual, outputs)
    texts: Mapping[str, str] = {
        f"{p.prefix}_casadi.c": code.source,
        f"{p.prefix}_casadi.h": code.header,
        **render(chosen, context(p, code, *_sample(problem, p),
                                 _command(problem, outdir, result))),
    }
    with OutputSet(outdir, reads, option, force, hint) as stage:
        for name, text in texts.items():
            atomic_write_text(stage / name, text)
    return [outdir / name for name in texts]
