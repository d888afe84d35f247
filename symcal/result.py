"""The frozen outcome of a calibration: estimate, identifiability, uncertainty, fit."""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from symcal.analysis.fit import SeriesStats
from symcal.analysis.identifiability import Conditioning, Identifiability, Uncertainty
from symcal.analysis.implicit import ImplicitCheck


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


@dataclass(frozen=True)
class ConstraintCost:
    """One constraint's share of a stage's cost before and after the stage.

    ``cost_*`` is Σ (g/σ)²; ``rms_*`` is the RMS of g in the constraint's display unit.
    """

    name: str
    unit: str
    cost_before: float
    cost_after: float
    rms_before: float
    rms_after: float


@dataclass(frozen=True, eq=False)
class StageResult:
    """The outcome of one stage of a calibration."""

    name: str
    doc: str
    method: str
    success: bool
    status: str
    message: str
    iterations: int
    seconds: float
    free: tuple[str, ...]
    costs: tuple[ConstraintCost, ...]
    unmoved: tuple[str, ...]
    at_bound: tuple[str, ...]
    conditioning_before: Conditioning
    conditioning_after: Conditioning
    identifiability: Identifiability
    uncertainty: Uncertainty
    notes: tuple[str, ...] = ()

    @property
    def cost_before(self) -> float:
        """Total cost Σ (g/σ)² at the stage's start."""
        return sum(c.cost_before for c in self.costs)

    @property
    def cost_after(self) -> float:
        """Total cost Σ (g/σ)² at the stage's end."""
        return sum(c.cost_after for c in self.costs)

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form."""
        return {
            "name": self.name, "doc": self.doc, "method": self.method,
            "success": self.success, "status": self.status, "message": self.message,
            "iterations": self.iterations, "seconds": self.seconds, "free": list(self.free),
            "costs": [c.__dict__ for c in self.costs],
            "cost_before": self.cost_before, "cost_after": self.cost_after,
            "unmoved": list(self.unmoved), "at_bound": list(self.at_bound),
            "hessian_conditioning": {"before": self.conditioning_before.to_dict(),
                                     "after": self.conditioning_after.to_dict()},
            "identifiability": self.identifiability.to_dict(),
            "notes": list(self.notes),
        }


@dataclass(frozen=True, eq=False)
class Result:
    """A calibration result.

    Use ``.params`` for the estimated values by name, ``.report()`` for the table a person
    reads and ``.to_dict()`` for the machine-readable document (``symcal solve --json``).
    ``identifiability`` and ``uncertainty`` are those of the last stage; each stage's own
    are in ``stages``.  ``success`` is False when a stage failed (the estimate is then the
    failed stage's last iterate and later stages did not run) or when an implicit
    definition's fixed-point map does not contract on the data (``implicit``).
    """

    problem: str
    problem_path: str
    stages: tuple[StageResult, ...]
    parameters: tuple[ParameterResult, ...]
    identifiability: Identifiability
    uncertainty: Uncertainty
    statistics: tuple[SeriesStats, ...]
    datasets: tuple[DatasetInfo, ...]
    notes: tuple[str, ...]
    implicit: tuple[ImplicitCheck, ...] = ()

    @property
    def success(self) -> bool:
        """Whether every stage succeeded and every implicit definition converged."""
        return all(st.success for st in self.stages) and all(c.contracts for c in self.implicit)

    @property
    def method(self) -> str:
        """The methods of the stages, e.g. ``"linear"`` or ``"linear+linear+ipopt"``."""
        return "+".join(st.method for st in self.stages)

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
            "solver": {"method": self.method, "success": self.success,
                       "seconds": sum(st.seconds for st in self.stages)},
            "stages": [st.to_dict() for st in self.stages],
            "datasets": [d.__dict__ for d in self.datasets],
            "parameters": [p.to_dict() for p in self.parameters],
            "identifiability": self.identifiability.to_dict(),
            "uncertainty": self.uncertainty.to_dict(),
            "statistics": [s.to_dict() for s in self.statistics],
            "implicit": [c.to_dict() for c in self.implicit],
            "notes": list(self.notes),
        }

    def report(self) -> str:
        """The human-readable report (what ``symcal solve`` prints)."""
        from symcal.report import text_report

        return text_report(self)
