"""The frozen outcome of a calibration: estimate, identifiability, uncertainty, fit."""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from symcal.analysis.fit import SeriesStats
from symcal.analysis.identifiability import Identifiability, Uncertainty


@dataclass(frozen=True)
class ParameterResult:
    """One parameter after the solve."""

    name: str
    value: float
    initial: float
    unit: str
    fixed: bool
    se: float | None
    se_reason: str | None
    lower: float
    upper: float
    doc: str

    @property
    def at_bound(self) -> str | None:
        """``"lower"``/``"upper"`` when the value sits on (or beyond) a bound."""
        if self.value <= self.lower:
            return "lower"
        if self.value >= self.upper:
            return "upper"
        return None

    def to_dict(self) -> dict:
        """Plain-data form (infinite bounds as None)."""
        def bound(x: float) -> float | None:
            return None if math.isinf(x) else x

        return {"name": self.name, "value": self.value, "initial": self.initial,
                "unit": self.unit, "fixed": self.fixed, "se": self.se,
                "se_reason": self.se_reason, "lower": bound(self.lower),
                "upper": bound(self.upper), "at_bound": self.at_bound}


@dataclass(frozen=True)
class DatasetInfo:
    """Which data a result was computed on."""

    name: str
    source: str
    n: int
    dropped: int


@dataclass(frozen=True, eq=False)
class Result:
    """A calibration result.

    Use ``.params`` for the estimated values by name, ``.report()`` for the table a person
    reads and ``.to_dict()`` for the machine-readable document (``symcal solve --json``).
    """

    problem: str
    problem_path: str
    method: str
    success: bool
    status: str
    message: str
    iterations: int
    seconds: float
    parameters: tuple[ParameterResult, ...]
    identifiability: Identifiability
    uncertainty: Uncertainty
    statistics: tuple[SeriesStats, ...]
    datasets: tuple[DatasetInfo, ...]
    notes: tuple[str, ...]

    @property
    def params(self) -> MappingProxyType:
        """Estimated parameter values by name (read-only)."""
        return MappingProxyType({p.name: p.value for p in self.parameters})

    def stat(self, name: str, dataset: str = "calibration") -> SeriesStats:
        """The statistics of constraint or comparison ``name`` on ``dataset``."""
        for s in self.statistics:
            if s.name == name and s.dataset == dataset:
                return s
        raise KeyError(f"no statistics for '{name}' on dataset '{dataset}'")

    def to_dict(self) -> dict[str, Any]:
        """The whole result as plain data (JSON-ready)."""
        return {
            "symcal_result": 1,
            "problem": self.problem, "problem_path": self.problem_path,
            "solver": {"method": self.method, "success": self.success, "status": self.status,
                       "message": self.message, "iterations": self.iterations,
                       "seconds": self.seconds},
            "datasets": [d.__dict__ for d in self.datasets],
            "parameters": [p.to_dict() for p in self.parameters],
            "identifiability": self.identifiability.to_dict(),
            "uncertainty": self.uncertainty.to_dict(),
            "statistics": [s.to_dict() for s in self.statistics],
            "notes": list(self.notes),
        }

    def report(self) -> str:
        """The human-readable report (what ``symcal solve`` prints)."""
        from symcal.report import text_report

        return text_report(self)
