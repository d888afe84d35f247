"""The bundled courier scenarios with planted effects, for tests.

Each helper returns an effect in the scenario language (values and the terms it adds to
a segment's error ``e1..e4`` or to the coordination sensor's ``cx``, ``cy``), written out
here so that a test states the physics it plants.  In the courier files, ``v1..v4`` is
where a segment's tooth error is evaluated, ``ang`` the angle it sees and ``L1..L4`` the
lateral coordinates it sees: the true ones in ``courier_platen.yaml`` (physics), those of
the raw readings in ``courier_*_model.yaml`` (the models' own assumptions).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from symcal.simulation import Scenario, load_scenario

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "problems" / "scenarios"


def harmonic(segment: int, n: int, sin: float = 0.0, cos: float = 0.0) -> dict[str, Any]:
    """Harmonic ``n`` of segment ``segment``'s tooth phase: ``sin sin(n f v) + cos cos(n f v)``
    (mm)."""
    s = f"s{segment}"
    return {f"harmonic{n}_{s}": {
        "values": {f"{s}.h{n}_sin": sin, f"{s}.h{n}_cos": cos},
        "add": {f"e{segment}": f"{s}.h{n}_sin*sin({n}*f*v{segment}) + "
                               f"{s}.h{n}_cos*cos({n}*f*v{segment})"}}}


def drift(segment: int, rate: float) -> dict[str, Any]:
    """A drift of segment ``segment`` in time: ``rate t`` (mm/s)."""
    s = f"s{segment}"
    return {f"drift_{s}": {"values": {f"{s}.rate": rate}, "add": {f"e{segment}": f"{s}.rate*t"}}}


def angle(segment: int, a: float) -> dict[str, Any]:
    """An angle dependence of segment ``segment``: ``a ang`` (mm/rad)."""
    s = f"s{segment}"
    return {f"angle_{s}": {"values": {f"{s}.a": a}, "add": {f"e{segment}": f"ang*{s}.a"}}}


def lateral(segment: int, k9: float, k10: float) -> dict[str, Any]:
    """Eq. (9)'s lateral dependence of segment ``segment``: ``k9 sin(f L) + k10 cos(f L)``."""
    s = f"s{segment}"
    return {f"lateral_{s}": {"values": {f"{s}.k9": k9, f"{s}.k10": k10},
                             "add": {f"e{segment}": f"{s}.k9*sin(f*L{segment}) + "
                                                    f"{s}.k10*cos(f*L{segment})"}}}


def count_slips(fractions: dict[int, float]) -> dict[str, Any]:
    """Quadrature count slips: on a share of the rows segment ``i`` reads a quarter pitch
    off (either sign)."""
    return {"count_slips": {"slips": {f"p{i}": {"fraction": f, "size": "rho/4"}
                                      for i, f in fractions.items()}}}


def psd(x: dict[str, float] | None = None, y: dict[str, float] | None = None
        ) -> dict[str, Any]:
    """The coordination sensor's gain and nonlinearity per axis: ``c -> c + g c + n2 c^2
    + n3 c^3`` before ``psi = atan(c / h)`` (``g`` dimensionless, ``n2`` 1/mm, ``n3``
    1/mm^2)."""
    values, add = {}, {}
    for axis, terms in (("x", x or {}), ("y", y or {})):
        if not terms:
            continue
        parts = []
        for key, power in (("g", ""), ("n2", "**2"), ("n3", "**3")):
            values[f"psd_{key}{axis}"] = terms.get(key, 0.0)
            parts.append(f"psd_{key}{axis}*c{axis}{power}")
        add[f"c{axis}"] = " + ".join(parts)
    return {"psd": {"values": values, "add": add}}


def platen(*effects: dict[str, Any], model: bool = True, small_angle: bool = True,
           noise: float | None = None, quantization: float | None = None) -> Scenario:
    """The platen courier with only ``effects``: as the model assumes it (errors at the
    readings, small angles: ``courier_platen_model.yaml``) or, with ``model=False``, the
    physics of ``courier_platen_clean.yaml`` (errors at the true position; small angles
    unless ``small_angle=False``)."""
    name = "courier_platen_model.yaml" if model else "courier_platen_clean.yaml"
    sc = load_scenario(SCENARIOS / name)
    changes: dict[str, Any] = {}
    if not model and small_angle:
        changes["expressions"] = {"st": "theta", "cm": 0}
    if noise is not None or quantization is not None:
        changes["constants"] = {}
        if noise is not None:
            changes["constants"]["sigma_p"] = noise
        if quantization is not None:
            changes["constants"]["step_p"] = quantization
    if effects:
        changes["effects"] = {k: v for e in effects for k, v in e.items()}
    return sc.overlay(changes) if changes else sc


def dual(*effects: dict[str, Any], model: bool = False, **constants: float) -> Scenario:
    """The dual courier with extra ``effects``: ``courier_dual_clean.yaml`` (physics,
    small angles) or, with ``model=True``, ``courier_dual_model.yaml``; ``constants``
    override ``sigma_p``, ``step_p``, ``sigma_psi``."""
    name = "courier_dual_model.yaml" if model else "courier_dual_clean.yaml"
    sc = load_scenario(SCENARIOS / name)
    changes: dict[str, Any] = {}
    if constants:
        changes["constants"] = dict(constants)
    if effects:
        changes["effects"] = {k: v for e in effects for k, v in e.items()}
    return sc.overlay(changes) if changes else sc


def floors(problem: Any, scenario: Scenario) -> dict[str, float]:
    """The noise floor of each constraint (``NAME_std``, internal units), propagated from
    the scenario's declared noise at its truth."""
    from symcal.experiment.predict import noise_floors

    return noise_floors(symcal_problem(problem), scenario)


def symcal_problem(problem: Any) -> Any:
    """A problem object from a problem or its file."""
    from symcal.problem.build import load_problem

    return load_problem(problem) if isinstance(problem, (str, Path)) else problem
