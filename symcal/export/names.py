"""C names of an export: identifiers from YAML names, the prefix of a problem, collisions.

Every YAML name becomes a C identifier by :func:`c_identifier`; a scope of names (a
struct's fields) is a :class:`Namespace`, which refuses two YAML names that become the
same identifier, naming both.
"""

from __future__ import annotations

import re
from collections.abc import Mapping

from symcal.base.errors import SymcalError

__all__ = ["RESERVED", "Namespace", "c_identifier", "c_prefix"]

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


def c_identifier(name: str) -> str:
    """A C identifier for a YAML name: ``[A-Za-z0-9_]``, no leading digit, no keyword.

    Other characters (the ``.`` of ``s1.k3``) become ``_``; a leading digit gets a
    leading ``_``; a C keyword or standard macro name gets a trailing ``_``.

    Parameters
    ----------
    name
        The name as written in the YAML files.

    Returns
    -------
    str
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

    Parameters
    ----------
    problem
        The problem's name.

    Returns
    -------
    str
    """
    core = re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9_]", "_", problem)).strip("_")
    return f"symcal_{core}" if core else "symcal_problem"


class Namespace:
    """C names of one scope (a struct's fields, or a set of identifiers): no two alike.

    Parameters
    ----------
    reserved
        C names already taken, and what took them (for the message).
    """

    def __init__(self, reserved: Mapping[str, str] | None = None) -> None:
        self.owner: dict[str, str] = dict(reserved or {})

    def claim(self, name: str) -> str:
        """The C identifier of YAML name ``name``, taken in this scope.

        Raises
        ------
        SymcalError
            When another name of the scope already became that identifier.
        """
        c = c_identifier(name)
        if c in self.owner:
            raise SymcalError(f"cannot export: {self.owner[c]} and '{name}' both become the "
                              f"C name '{c}'")
        self.owner[c] = f"'{name}'"
        return c
