"""Checks of implicit definitions (fixed-point steps x = F(x)) on the data.

The steps converge where the map contracts, |∂F/∂x| < 1; after the last step the
remaining error is at most |last change| · L/(1 − L), L the largest |∂F/∂x|.  Where
L ≥ 1 the unrolled steps do not converge and the model's outputs are not to be trusted.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from symcal.base.numeric import mapped
from symcal.data.dataset import Dataset
from symcal.problem.symbolic import Problem


@dataclass(frozen=True)
class ImplicitCheck:
    """How well one implicit definition converged on one dataset."""

    name: str
    dataset: str
    steps: int
    contraction: float
    last_step: float

    @property
    def contracts(self) -> bool:
        """Whether the fixed-point map contracts on every observation."""
        return self.contraction < 1.0

    @property
    def remaining(self) -> float:
        """Bound on the distance of the last iterate from the fixed point."""
        if not self.contracts:
            return float("inf")
        return self.last_step * self.contraction / (1.0 - self.contraction)

    def to_dict(self) -> dict:
        """Plain-data form."""
        return {"name": self.name, "dataset": self.dataset, "steps": self.steps,
                "max_derivative": self.contraction, "max_last_step": self.last_step,
                "remaining_error_bound": None if not self.contracts else self.remaining,
                "contracts": self.contracts}

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> ImplicitCheck:
        """Inverse of :meth:`to_dict`."""
        contraction = doc["max_derivative"]
        return cls(doc["name"], doc["dataset"], doc["steps"],
                   float("inf") if contraction is None else contraction, doc["max_last_step"])


def implicit_checks(
    problem: Problem, datasets: dict[str, Dataset], theta: np.ndarray
) -> tuple[ImplicitCheck, ...]:
    """Evaluate every implicit definition's contraction and last step on every dataset."""
    if not problem.implicit:
        return ()
    outputs = [ca.vertcat(*(ca.fabs(i.derivative) for i in problem.implicit)),
               ca.vertcat(*(ca.fabs(i.last_step) for i in problem.implicit))]
    fn = mapped(problem.theta, problem.u, outputs, "implicit_checks")
    checks = []
    for ds in datasets.values():
        derivative, last = fn(theta, ds.matrix(problem.columns))
        for k, item in enumerate(problem.implicit):
            d = derivative[:, k]
            worst = float(np.max(d)) if np.all(np.isfinite(d)) else float("inf")
            checks.append(ImplicitCheck(item.name, ds.name, item.steps, worst,
                                        float(np.nanmax(last[:, k]))))
    return tuple(checks)
