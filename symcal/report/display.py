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
    """Give :class:`Result` and :class:`Diagnosis` their notebook display (once)."""
    if _REGISTERED:
        return
    from symcal.calibrate.result import Result
    from symcal.report.text import diagnosis_report, text_report
    from symcal.revise.diagnose import Diagnosis

    for cls, render in ((Result, text_report), (Diagnosis, diagnosis_report)):
        for name, method in _methods(render).items():
            setattr(cls, name, method)
    _REGISTERED.append(True)
