"""How a problem is solved: the solver options, apart from what is measured and on what data.

Plain values, read by the solvers; a problem file declares them under ``solver:``
(:mod:`symcal.language.solver` parses that section), and the Python API and the command
line override them field by field (:meth:`SolveOptions.over`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

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
