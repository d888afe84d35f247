"""The ``candidates:`` sections: the search space of candidate effects a model, an
instance or a problem declares (issue 23), parsed and checked against the names in its
scope.

On a model (``candidates:`` at the top of a model file) or an instance (``candidates:``
in a problem's instance entry, which replaces its model's)::

    candidates:
      variables: [p, t]            # names in that scope (a model: its inputs, outputs,
                                   # expressions; an instance also problem columns,
                                   # expressions and other instances' signals: s3.p)
      kinds: [harmonic, linear]    # a subset of KINDS
      harmonics: [1, 2, 3]         # orders, or a maximum: 3
      none: true                   # never add a term to this sensor (or kinds: [])

A key not written keeps the default of the search for it.  On a problem
(``candidates:`` at the top level)::

    candidates:
      constants: false             # or a list of constant keys or patterns: [s?.rho, l_s]
      fixed: [imu.gain]            # which fixed parameters may be tested (default: all)

Names are resolved to the problem's names by the compiler
(:mod:`symcal.problem.space`).
"""

from __future__ import annotations

import fnmatch
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import SpecError, Where, excerpt
from symcal.language.fields import (
    check_keys,
    child_where,
    expect_bool,
    expect_int,
    expect_list,
    expect_str,
)

#: The kinds of candidate effect a space may name.
KINDS = ("linear", "quadratic", "cubic", "harmonic", "drift", "product", "power", "gain",
         "coupling", "angle_harmonic", "latency", "constant", "zero")
#: The highest harmonic order a space may name.
MAX_HARMONIC = 64


@dataclass(frozen=True)
class CandidatesSpec:
    """A model's or instance's ``candidates:`` as written (names in its own scope).

    ``variables``, ``kinds`` and ``harmonics`` are None where the key is not written (the
    search's default applies); ``kinds`` is ``()`` for ``none: true`` or ``kinds: []``.
    """

    variables: tuple[tuple[str, Where], ...] | None
    kinds: tuple[str, ...] | None
    harmonics: tuple[int, ...] | None
    where: Where

    @property
    def none(self) -> bool:
        """Whether no term may be added to this sensor."""
        return self.kinds == ()


@dataclass(frozen=True)
class ProblemCandidatesSpec:
    """A problem's ``candidates:``: which constants and fixed parameters the search may
    test, as patterns (None: every one; ``()``: none)."""

    constants: tuple[tuple[str, Where], ...] | None
    fixed: tuple[tuple[str, Where], ...] | None
    where: Where


def parse_candidates(value: Any, where: Where) -> CandidatesSpec:
    """Parse a model's or instance's ``candidates:`` (see the module doc).

    Raises
    ------
    SpecError
        For an unknown key or kind (with a did-you-mean), a harmonic order that is not a
        positive integer, ``none: true`` beside kinds, or a name written twice.
    """
    entry = check_keys(value, where, optional=["variables", "kinds", "harmonics", "none",
                                               "doc"])
    variables = None
    if "variables" in entry:
        at = child_where(entry, where, "variables")
        items = expect_list(entry["variables"], at)
        variables = tuple((expect_str(v, child_where(items, at, i)).strip(),
                           child_where(items, at, i)) for i, v in enumerate(items))
        _unique([n for n, _ in variables], [w for _, w in variables], "variable")
    kinds = None
    if "kinds" in entry:
        at = child_where(entry, where, "kinds")
        items = expect_list(entry["kinds"], at)
        found = []
        for i, v in enumerate(items):
            item_at = child_where(items, at, i)
            text = expect_str(v, item_at)
            if text not in KINDS:
                raise SpecError(item_at, f"unknown kind of candidate '{excerpt(text)}'"
                                         f"{did_you_mean(text, KINDS)}; kinds: "
                                         f"{', '.join(KINDS)}")
            found.append(text)
        _unique(found, [child_where(items, at, i) for i in range(len(found))], "kind")
        kinds = tuple(found)
    if "none" in entry:
        at = child_where(entry, where, "none")
        if expect_bool(entry["none"], at):
            if kinds:
                raise SpecError(at, "'none: true' says no term is ever added to this sensor, "
                                    "but 'kinds' names some: keep one of them")
            kinds = ()
    harmonics = None
    if "harmonics" in entry:
        harmonics = _harmonics(entry["harmonics"], child_where(entry, where, "harmonics"))
    return CandidatesSpec(variables, kinds, harmonics, where)


def _harmonics(value: Any, where: Where) -> tuple[int, ...]:
    """``[1, 2, 3]`` or a maximum ``3`` (orders 1 to 3)."""
    if not isinstance(value, list):
        return tuple(range(1, expect_int(value, where, 1, MAX_HARMONIC) + 1))
    items = expect_list(value, where)
    ats = [child_where(items, where, i) for i in range(len(items))]
    orders = [expect_int(v, at, 1, MAX_HARMONIC) for v, at in zip(items, ats, strict=True)]
    _unique([str(o) for o in orders], ats, "harmonic order")
    return tuple(sorted(orders))


def _unique(names: list[str], wheres: list[Where], what: str) -> None:
    seen: set[str] = set()
    for name, at in zip(names, wheres, strict=True):
        if name in seen:
            raise SpecError(at, f"{what} '{excerpt(name)}' is written twice")
        seen.add(name)


def parse_problem_candidates(value: Any, where: Where) -> ProblemCandidatesSpec:
    """Parse a problem's top-level ``candidates:`` (``constants``, ``fixed``: ``true``,
    ``false`` or a list of names or patterns)."""
    entry = check_keys(value, where, optional=["constants", "fixed", "doc"])

    def names(key: str) -> tuple[tuple[str, Where], ...] | None:
        if key not in entry:
            return None
        at = child_where(entry, where, key)
        if isinstance(entry[key], bool):
            return None if entry[key] else ()
        items = expect_list(entry[key], at)
        return tuple((expect_str(v, child_where(items, at, i)).strip(),
                      child_where(items, at, i)) for i, v in enumerate(items))

    return ProblemCandidatesSpec(names("constants"), names("fixed"), where)


def model_candidate_names(inputs: Iterable[str], outputs: Iterable[str],
                          expressions: Iterable[str]) -> list[str]:
    """The names a model's ``candidates: variables`` may use (``base.`` names excluded)."""
    return [n for n in (*inputs, *outputs, *expressions) if not n.startswith("base.")]


def check_model_variables(spec: CandidatesSpec, known: list[str], model: str) -> None:
    """Refuse a variable that is not an input, output or expression of the model."""
    for name, at in spec.variables or ():
        if name not in known:
            raise SpecError(at, f"'{excerpt(name)}' is not an input, output or expression of "
                                f"model '{model}'{did_you_mean(name, known)}; a model's "
                                f"candidates use its own names: {', '.join(known) or 'none'}")


def select(patterns: tuple[tuple[str, Where], ...] | None, names: list[str],
           what: str) -> tuple[str, ...]:
    """The names ``patterns`` select (every name for None); a pattern that matches none is
    refused with a did-you-mean."""
    if patterns is None:
        return tuple(names)
    chosen: list[str] = []
    for pattern, at in patterns:
        matched = [n for n in names if fnmatch.fnmatchcase(n, pattern)]
        if not matched:
            raise SpecError(at, f"'{excerpt(pattern)}' matches no {what}"
                                f"{did_you_mean(pattern, names)}; {what}s: "
                                f"{', '.join(names) or 'none'}")
        chosen += [n for n in matched if n not in chosen]
    return tuple(n for n in names if n in chosen)
