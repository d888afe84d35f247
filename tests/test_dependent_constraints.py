"""A constraint that is a combination of the others makes every row's propagated
covariance singular.  The note blamed readings "declared exact there" (a new user's oven:
thermocouple minus RTD, RTD minus pyrometer, and thermocouple minus pyrometer, none of
them exact)."""

from __future__ import annotations

import numpy as np

import symcal
from symcal.data.dataset import make_dataset

PROBLEM = """problem: three
columns:
  a: {unit: K, noise: 0.1 K}
  b: {unit: K, noise: 0.1 K}
  c: {unit: K, noise: 0.1 K}
parameters:
  p1: {value: 0, unit: K}
  p2: {value: 0, unit: K}
constraints:
  g1: {expr: a - b - p1, unit: K}
  g2: {expr: b - c - p2, unit: K}
  g3: {expr: a - c - p1 - p2, unit: K}
datasets:
  calibration: {path: cal.csv, role: fit}
"""


def test_a_dependent_constraint_is_named_as_a_cause_of_singular_weights(tmp_path) -> None:
    path = tmp_path / "three.yaml"
    path.write_text(PROBLEM)
    rng = np.random.default_rng(3)
    t = np.linspace(280, 360, 300)
    cols = {"a": t + 0.5 + rng.normal(size=t.size) * 0.1,
            "b": t + rng.normal(size=t.size) * 0.1,
            "c": t - 0.2 + rng.normal(size=t.size) * 0.1}
    result = symcal.solve(path, {"calibration": make_dataset("calibration", "sim", cols,
                                                              list(cols))})
    note = next(n for n in result.stages[-1].notes if "is singular on" in n)
    assert note == ("weighting: the propagated covariance of the constraints is singular "
                    "on 300 of 300 observations (the readings they use are declared exact "
                    "there, or one constraint is a combination of the others, as g3 = g1 + "
                    "g2: leave it out); kept equal weights")
    assert abs(result.params["p1"].value - 0.5) < 4 * result.params["p1"].se
