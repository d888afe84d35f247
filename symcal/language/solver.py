"""A problem's ``solver:`` section into :class:`~symcal.base.options.SolveOptions`."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from symcal.base.errors import SpecError, Where
from symcal.base.options import MAX_ITER_LIMIT, METHODS, SolveOptions
from symcal.language.fields import (
    check_keys,
    child_where,
    expect_choice,
    expect_int,
    expect_map,
    expect_number,
)


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
