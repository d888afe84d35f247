"""How a problem is solved: the solver options, apart from what is measured and on what data.

A problem file may declare them under ``solver:``; the Python API and the command line
override them field by field (:meth:`SolveOptions.over`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

from symcal.base.errors import SpecError, Where
from symcal.language.fields import (
    check_keys,
    child_where,
    expect_choice,
    expect_int,
    expect_map,
    expect_number,
)

METHODS = ("auto", "linear", "ipopt", "lm")
#: The largest iteration limit accepted (IPOPT stores it in a C int).
MAX_ITER_LIMIT = 1_000_000


@dataclass(frozen=True)
class SolveOptions:
    """Solver options of a calibration.

    Attributes
    ----------
    method
        ``"auto"`` (closed form when the stage is linear, else ``"lm"``), ``"linear"``,
        ``"ipopt"`` or ``"lm"`` (symcal's trust-region Levenberg-Marquardt) for every
        stage; None keeps each stage's own ``method``.
    max_iter
        Iteration limit of each IPOPT or LM stage (every run of a stage counts against it).
    tol
        IPOPT's optimality tolerance.
    ipopt
        Further IPOPT options by name (numbers or text), passed as given.
    """

    method: str | None = None
    max_iter: int = 200
    tol: float = 1e-8
    ipopt: Mapping[str, float | int | str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "ipopt", MappingProxyType(dict(self.ipopt)))

    def over(self, **changes: Any) -> SolveOptions:
        """These options with the fields given (not None) replaced."""
        return replace(self, **{k: v for k, v in changes.items() if v is not None})


def parse_solver(value: Any, where: Where) -> SolveOptions:
    """Parse a problem's ``solver: {method, max_iter, tol, ipopt}`` section."""
    entry = check_keys(value, where, optional=["method", "max_iter", "tol", "ipopt"])
    options = SolveOptions()
    if "method" in entry:
        options = replace(options, method=expect_choice(
            entry["method"], child_where(entry, where, "method"), METHODS, "method"))
    if "max_iter" in entry:
        at = child_where(entry, where, "max_iter")
        limit = expect_int(entry["max_iter"], at, 1)
        if limit > MAX_ITER_LIMIT:
            raise SpecError(at, f"at most {MAX_ITER_LIMIT} iterations, found {limit}")
        options = replace(options, max_iter=limit)
    if "tol" in entry:
        at = child_where(entry, where, "tol")
        tol = expect_number(entry["tol"], at)
        if tol <= 0:
            raise SpecError(at, f"tol must be positive, found {entry['tol']}")
        options = replace(options, tol=tol)
    if "ipopt" in entry:
        at = child_where(entry, where, "ipopt")
        extra: dict[str, float | int | str] = {}
        for key, val in expect_map(entry["ipopt"], at).items():
            key_at = child_where(entry["ipopt"], at, key)
            if isinstance(val, bool) or not isinstance(val, (int, float, str)):
                raise SpecError(key_at, f"an IPOPT option must be a number or text, found "
                                        f"{val!r}")
            extra[str(key)] = val
        options = replace(options, ipopt=extra)
    return options
