"""The parameter values an export bakes in, from a calibration result.

A result is read only through :meth:`symcal.calibrate.result.Result.load` (which refuses
a missing, foreign, stale or incomplete ``result.json``); this module adds what an export
needs besides: a successful solve, finite values, data files unchanged since the solve.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from symcal.base.errors import SymcalError
from symcal.calibrate.result import Result
from symcal.problem.symbolic import Problem

#: A calibration result: the object, its ``result.json`` file, or that file's document.
ResultLike = Result | str | Path | Mapping[str, Any]

__all__ = ["ResultLike", "baked_values"]


def _label(result: ResultLike) -> str:
    """How messages name a result."""
    if isinstance(result, Result):
        return f"the result of '{result.name}'"
    if isinstance(result, Mapping):
        return "the result"
    return f"result file {result}"


def baked_values(result: ResultLike, problem: Problem) -> tuple[tuple[float, ...], str]:
    """The parameter values of ``result``, in ``problem.theta`` order, and its label.

    Parameters
    ----------
    result
        A :class:`~symcal.calibrate.result.Result`, a result file (``symcal solve --out
        DIR`` writes ``DIR/result.json``) or its document (``Result.to_dict()``).
    problem
        The problem exported.

    Returns
    -------
    values, label
        The values, and how messages and the generated code name the result.

    Raises
    ------
    SymcalError
        What :meth:`Result.load` refuses (a missing, unreadable or foreign file, another
        problem, changed problem or model files, an incomplete document); a result for a
        problem with other parameters; a failed solve; a value that is not finite; a data
        file that changed or vanished since the solve.
    """
    label = _label(result)
    if isinstance(result, Result):
        if result.problem.parameter_names != problem.parameter_names:
            raise SymcalError(f"the result is for problem '{result.name}', whose parameters "
                              f"are not those of '{problem.name}'")
        loaded = result
    else:
        loaded = Result.load(result, problem)
    if not loaded.success:
        raise SymcalError(f"{label} is from a failed solve; symcal exports only a "
                          "successful calibration (or none: omit --result to pass the "
                          "parameters at run time)")
    for name, value in zip(problem.parameter_names, loaded.theta, strict=True):
        if not math.isfinite(value):
            raise SymcalError(f"{label}: parameter '{name}' has the value {value}, not a "
                              "finite number")
    try:
        loaded.check_data()
    except SymcalError as exc:
        raise SymcalError(f"{label} was computed on other data: {exc.message}") from None
    return tuple(float(v) for v in loaded.theta), label
