"""Templates into text: the Jinja2 environment, its filters and the template sets.

A *target* is a set of Jinja2 templates under ``symcal/export/templates/<name>/`` (shipped
as package data) and the files they become; every template of a set reads the same plain
data (the plan of :mod:`symcal.export.plan` and the calls of
:mod:`symcal.export.casadi_code`), so another target is a new template set, not new code.

Text from the YAML files reaches the generated code only through the filters: ``comment``
and ``wrap`` (inside a C comment: one line, no comment delimiter, no trigraph),
``c_string`` (a C string literal), ``make_comment`` (a Makefile comment); numbers through
``c_number`` (a literal that reads back exactly).  Templates are rendered strictly: an
undefined name is an error, not an empty string.
"""

from __future__ import annotations

import functools
import textwrap
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import jinja2

__all__ = ["TARGETS", "Target", "c_number", "c_string", "comment", "make_comment", "render",
           "wrap"]


@dataclass(frozen=True)
class Target:
    """A template set: where its templates are and the files it writes.

    Attributes
    ----------
    name
        Its name; the folder of its templates under ``symcal/export/templates/``.
    files
        ``(template, file name)`` pairs in the order they are written; ``{prefix}`` in a
        file name is the export's C prefix.
    folder
        A folder of your own templates instead of symcal's (None: symcal's).
    """

    name: str
    files: tuple[tuple[str, str], ...]
    folder: Path | None = None


#: The template sets symcal ships, by name.
TARGETS: Mapping[str, Target] = {
    "c": Target("c", (("wrapper.h.j2", "{prefix}.h"), ("wrapper.c.j2", "{prefix}.c"),
                      ("main.c.j2", "main.c"), ("Makefile.j2", "Makefile"))),
}


def comment(text: object) -> str:
    """Text safe inside a C comment: one line, no comment delimiter, no trigraph."""
    line = " ".join(str(text).split())
    return line.replace("*/", "* /").replace("/*", "/ *").replace("??", "? ?")


def wrap(text: object, first: str = " * ", rest: str | None = None, width: int = 92) -> str:
    """A C comment paragraph: :func:`comment` text wrapped to ``width``, each line
    starting with ``first`` (the first) or ``rest`` (the others; default ``first``)."""
    lines = textwrap.wrap(comment(text), width, initial_indent=first,
                          subsequent_indent=first if rest is None else rest,
                          break_on_hyphens=False)
    return "\n".join(lines or [first.rstrip()])


def c_string(text: object) -> str:
    """A C string literal (ASCII; other bytes as octal escapes)."""
    out = []
    for byte in str(text).encode("utf-8"):
        ch = chr(byte)
        if ch in '"\\?':
            out.append("\\" + ch)
        elif 32 <= byte < 127:
            out.append(ch)
        else:
            out.append(f"\\{byte:03o}")
    return '"' + "".join(out) + '"'


def c_number(value: float) -> str:
    """A C double literal that reads back exactly (``repr`` of the float, with a point)."""
    text = repr(float(value))
    return text if any(c in text for c in ".en") else text + ".0"


def make_comment(text: object) -> str:
    """Text safe in a Makefile comment: one line, not ending in a backslash (which would
    continue the comment onto the next line)."""
    return " ".join(str(text).split()).rstrip("\\")


def names(items: Iterable[Any]) -> str:
    """The YAML names of exported scalars, comma separated (for a comment: filter it)."""
    return ", ".join(str(c.name) for c in items)


def _packaged(target: str, template: str) -> str:
    """A template of symcal's from the package data (any installation: folder, wheel,
    zip)."""
    path = resources.files("symcal.export").joinpath("templates", target, template)
    return path.read_text(encoding="utf-8")


@functools.cache
def environment(target: Target) -> jinja2.Environment:
    """The Jinja2 environment of a template set (symcal's templates are read once per
    process; a folder of your own is read again when a template changes)."""
    loader: jinja2.BaseLoader = (
        jinja2.FunctionLoader(functools.partial(_packaged, target.name))
        if target.folder is None else jinja2.FileSystemLoader(target.folder))
    env = jinja2.Environment(
        loader=loader, undefined=jinja2.StrictUndefined, autoescape=False, trim_blocks=True,
        lstrip_blocks=True, keep_trailing_newline=True)
    env.filters.update(comment=comment, wrap=wrap, c_string=c_string, c_number=c_number,
                       make_comment=make_comment, names=names)
    return env


def render(target: Target, context: Mapping[str, Any]) -> dict[str, str]:
    """Every file of ``target``, rendered from ``context``.

    Parameters
    ----------
    target
        The template set.
    context
        The names the templates read; ``prefix`` names the files.

    Returns
    -------
    dict
        File name to text, in the order of ``target.files``.
    """
    env = environment(target)
    return {name.format(prefix=context["prefix"]): env.get_template(template).render(context)
            for template, name in target.files}
