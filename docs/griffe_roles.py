"""A Griffe extension for the API reference (mkdocs.yml): symcal's docstrings write
cross-references as Sphinx roles (``:class:`~symcal.calibrate.result.Result```), which
Markdown would show as they are.  Each becomes inline code, linked to its entry in the
API reference when it names a public name of ``symcal`` (an unknown target would fail the
strict build)."""

from __future__ import annotations

import re
from typing import Any

import griffe

import symcal

ROLE = re.compile(r":(?:class|func|meth|attr|mod|data|exc|obj):`(~?)([\w.]+?)(\(\))?`")
PUBLIC = frozenset(symcal.__all__)


def markdown(match: re.Match[str]) -> str:
    """The Markdown of one role: ``~`` shows the last name only, as in Sphinx."""
    tilde, path, call = match.groups()
    name = path.rsplit(".", 1)[-1]
    text = f"`{(name if tilde else path)}{call or ''}`"
    if name in PUBLIC and (path == name or path.startswith("symcal.")):
        return f"[{text}][symcal.{name}]"
    return text


class SphinxRoles(griffe.Extension):
    """Rewrite the roles of every docstring as it is loaded."""

    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = ROLE.sub(markdown, obj.docstring.value)
