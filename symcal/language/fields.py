"""Strict validation of loaded YAML mappings: known keys, required keys, types."""

from __future__ import annotations

import math
import re
import unicodedata
from collections.abc import Iterable
from typing import Any

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import SpecError, Where, excerpt
from symcal.language.expr import RESERVED_NAMES
from symcal.language.yamlio import YList, YMap


def child_where(parent: Any, where: Where, key: str | int) -> Where:
    """Provenance of ``parent[key]``, using the key's own line and file when known.

    A key merged from a file that another one ``extends`` names that file and line, and
    the file that was loaded (``Where.via``).
    """
    line, file = None, None
    if isinstance(parent, YMap):
        line = parent.key_lines.get(key)
        file = parent.key_files.get(key)
    elif isinstance(parent, YList) and isinstance(key, int) and key < len(parent.item_lines):
        line = parent.item_lines[key]
        file = parent.item_files[key] if key < len(parent.item_files) else None
    return where.child(key, line, file)


def check_keys(
    mapping: Any, where: Where, required: Iterable[str] = (), optional: Iterable[str] = ()
) -> YMap:
    """Check that ``mapping`` is a mapping with exactly the allowed keys.

    Raises
    ------
    SpecError
        On a non-mapping, an unknown key (with a did-you-mean) or a missing required key.
    """
    mapping = expect_map(mapping, where)
    required = list(required)
    allowed = required + list(optional)
    for key in mapping:
        if key not in allowed:
            raise SpecError(
                child_where(mapping, where, key),
                f"unknown key '{excerpt(key)}'{did_you_mean(str(key), allowed)}"
                f"; allowed keys: {', '.join(allowed)}",
            )
    for key in required:
        if key not in mapping:
            raise SpecError(where, f"missing required key '{key}'")
    return mapping


def _type_name(value: Any) -> str:
    if value is None:
        return "nothing (null)"
    if isinstance(value, bool):
        return f"a boolean ({value})"
    if isinstance(value, int) and abs(value) > 10**15:
        return f"a number with {len(str(abs(value)))} digits"
    if isinstance(value, (int, float)):
        return f"a number ({value})"
    if isinstance(value, str):
        return f"text ('{excerpt(value)}')"
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, list):
        return "a list"
    return type(value).__name__


def expect_map(value: Any, where: Where) -> YMap:
    """Return ``value`` if it is a mapping (``None`` counts as empty), else raise."""
    if value is None:
        empty = YMap()
        empty.key_lines = {}
        empty.line = where.line
        return empty
    if not isinstance(value, YMap):
        raise SpecError(where, f"expected a mapping, found {_type_name(value)}")
    return value


def expect_list(value: Any, where: Where) -> YList:
    """Return ``value`` if it is a list, else raise."""
    if not isinstance(value, YList):
        raise SpecError(where, f"expected a list, found {_type_name(value)}")
    return value


def expect_str(value: Any, where: Where) -> str:
    """Return ``value`` if it is non-empty text, else raise."""
    if isinstance(value, str) and not value.strip():
        raise SpecError(where, "expected text, found an empty string" if not value
                        else "expected text, found only spaces")
    if not isinstance(value, str):
        raise SpecError(where, f"expected text, found {_type_name(value)}")
    return value


def expect_number(value: Any, where: Where) -> float:
    """Return ``value`` as a finite float if it is a number, else raise."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SpecError(where, f"expected a number, found {_type_name(value)}")
    try:
        number = float(value)
    except OverflowError:
        raise SpecError(where, f"expected a finite number, found {_type_name(value)}, beyond "
                               "the range of a double (about 1.8e308)") from None
    if not math.isfinite(number):
        raise SpecError(where, f"expected a finite number, found {value}")
    return number


#: Most observations a simulated run or dataset may have.
MAX_SAMPLES = 100_000_000


def expect_int(value: Any, where: Where, minimum: int | None = None,
               maximum: int | None = None) -> int:
    """Return ``value`` if it is an integer (within ``minimum``..``maximum``), else raise."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise SpecError(where, f"expected a whole number, found {_type_name(value)}")
    shown = value if abs(value) <= 10**15 else _type_name(value)
    if minimum is not None and value < minimum:
        raise SpecError(where, f"expected a whole number of at least {minimum}, found {shown}")
    if maximum is not None and value > maximum:
        raise SpecError(where, f"expected a whole number of at most {maximum}, found {shown}")
    return value


def expect_bool(value: Any, where: Where) -> bool:
    """Return ``value`` if it is a boolean, else raise."""
    if not isinstance(value, bool):
        raise SpecError(where, f"expected true or false, found {_type_name(value)}")
    return value


def is_name(text: str) -> bool:
    """Whether ``text`` is a plain identifier usable as a symbol name."""
    return text.isidentifier() and text.isascii()


def plain_name(text: str, prefix: str = "p") -> str:
    """``text`` (a file's stem, say) made a plain name: accents dropped, every run of
    other characters an underscore, and ``prefix_`` before one that would start with a
    digit or be empty (``prob-v2`` → ``prob_v2``, ``2nd try`` → ``p_2nd_try``)."""
    ascii_text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode()
    name = re.sub(r"[^A-Za-z0-9_]+", "_", ascii_text).strip("_")
    return name if name and not name[0].isdigit() else f"{prefix}_{name}".rstrip("_")


def expect_name(value: Any, where: Where, what: str = "name") -> str:
    """Return ``value`` if it is a plain identifier, else raise."""
    if not isinstance(value, str) or not is_name(value):
        raise SpecError(
            where, f"{what} must be a plain name (letters, digits, underscore), found "
                   f"{excerpt(repr(value))}"
        )
    return value


def expect_symbol(value: Any, where: Where, what: str = "name") -> str:
    """Return ``value`` if it can name a symbol: a plain name that the expression language
    does not reserve (``pi``, the function names), else raise."""
    name = expect_name(value, where, what)
    if name in RESERVED_NAMES:
        meaning = "the constant π" if name == "pi" else "a function"
        raise SpecError(where, f"'{name}' cannot be declared: expressions reserve it for "
                               f"{meaning}; choose another name")
    return name


def expect_choice(value: Any, where: Where, choices: tuple[str, ...], what: str) -> str:
    """Return ``value`` if it is one of ``choices``, else raise with a did-you-mean."""
    text = expect_str(value, where)
    if text not in choices:
        raise SpecError(where, f"unknown {what} '{excerpt(text)}'{did_you_mean(text, choices)}; "
                               f"choose from: {', '.join(choices)}")
    return text
