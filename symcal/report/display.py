"""How a :class:`~symcal.calibrate.result.Result` and a
:class:`~symcal.revise.diagnose.Diagnosis` display in IPython and Jupyter: their text
report, as the command line prints it.

The presenter layer registers the display (:func:`register`, called by the package
``symcal`` when its public API is first used), so that results and diagnoses import no
presenter: they are plain frozen data.
"""

from __future__ import annotations

import html
from collections.abc import Callable
from typing import Any

_REGISTERED: list[bool] = []


def _pre(text: str) -> str:
    return f"<pre style=\"font-size: 90%\">{html.escape(text)}</pre>"


def _methods(render: Callable[[Any], str]) -> dict[str, Callable[..., Any]]:
    """``_repr_html_`` (Jupyter) and ``_repr_pretty_`` (the IPython terminal) of ``render``."""
    def repr_html(self: Any) -> str:
        return _pre(render(self))

    def repr_pretty(self: Any, printer: Any, cycle: bool) -> None:
        printer.text(f"<{type(self).__name__}>" if cycle else render(self))

    return {"_repr_html_": repr_html, "_repr_pretty_": repr_pretty}


def register() -> None:
    """Give :class:`Result` and :class:`Diagnosis` their notebook display (once each).

    A :class:`Diagnosis` is registered once its module is imported (by whatever made
    one): registering it does not import the diagnosis, which imports SciPy's statistics
    (seconds at a first solve that never diagnoses)."""
    import sys

    if len(_REGISTERED) == 2:
        return
    from symcal.report.text import diagnosis_report, text_report

    if not _REGISTERED:
        from symcal.calibrate.result import Result

        for name, method in _methods(text_report).items():
            setattr(Result, name, method)
        _REGISTERED.append(True)
    module = sys.modules.get("symcal.revise.diagnose")
    if module is not None:
        for name, method in _methods(diagnosis_report).items():
            setattr(module.Diagnosis, name, method)
        _REGISTERED.append(True)
