"""The courier's readings as a CasADi function of its pose, for designing motions.

:mod:`symcal.simulation.courier` simulates readings with numpy; an experiment design needs
their derivatives by the motion's parameters.  Here the same geometry is written once for
CasADi symbols (SX or MX): the pose of a run's motion (the platen centre, or the
coordination sensor's centre with ``rotate_about: coordination``) gives every column the
simulator writes, for an *ideal* courier: the segments read their true positions (eq. 3's
errors, the hidden effects and the pitch variation, all of a few µm, are left out), the
coordination sensor reads ``psi = atan(c / h)`` with its gain and nonlinearity, and the
reference reads the true pose.  The conventions are those of
:mod:`symcal.simulation.courier`.
"""

from __future__ import annotations

from typing import Any

import casadi as ca

from symcal.simulation.scenario import Scatter, Scenario

Symbolic = Any  # ca.SX or ca.MX (a scalar)


def platen_pose(scenario: Scenario, motion: Scatter, sx: Symbolic, sy: Symbolic,
                theta: Symbolic) -> tuple[Symbolic, Symbolic]:
    """The platen centre ``(x, y)`` of a pose ``(sx, sy, theta)`` of ``motion``."""
    if motion.rotate_about != "coordination" or scenario.coordination is None:
        return sx, sy
    coord = scenario.coordination
    cos_t, sin_t = ca.cos(theta), ca.sin(theta)
    return (sx + cos_t * coord.l_x - sin_t * coord.l_y,
            sy + sin_t * coord.l_x + cos_t * coord.l_y)


def ideal_columns(scenario: Scenario, motion: Scatter, sx: Symbolic, sy: Symbolic,
                  theta: Symbolic, t: Symbolic) -> dict[str, Symbolic]:
    """Every column of one observation of an ideal courier at one pose.

    Parameters
    ----------
    scenario
        The scenario (geometry of the platen sensor, coordination sensor and beacon).
    motion
        The scatter motion the pose belongs to (its ``rotate_about``).
    sx, sy, theta
        The pose as the motion states it (mm, mm, rad).
    t
        The observation's time (s).

    Returns
    -------
    dict of str to symbolic
        ``t, p1..p4, [psi_x, psi_y,] x_ref, y_ref, theta_ref``, as the simulator names them.
    """
    platen = scenario.platen
    x, y = platen_pose(scenario, motion, sx, sy, theta)
    half = platen.l_s / 2.0
    offsets = ((-platen.l_o, -half), (half, -platen.l_o), (platen.l_o, half),
               (-half, platen.l_o))
    if platen.geometry == "exact":
        sin_t, cos_m1 = ca.sin(theta), ca.cos(theta) - 1.0
    else:
        sin_t, cos_m1 = theta, 0.0
    out: dict[str, Symbolic] = {"t": t}
    for i, (a, b) in enumerate(offsets):
        world_x = x + a * cos_m1 - b * sin_t
        world_y = y + a * sin_t + b * cos_m1
        out[f"p{i + 1}"] = world_x if i % 2 == 0 else world_y
    coord = scenario.coordination
    if coord is not None:
        dx, dy = x - coord.o_x, y - coord.o_y
        cos_t = ca.cos(theta)
        sin_r = ca.sin(theta)
        cx = cos_t * dx + sin_r * dy - coord.l_x
        cy = -sin_r * dx + cos_t * dy - coord.l_y
        if coord.nonlinearity is not None:
            nx, ny = coord.nonlinearity
            cx = cx + nx.g * cx + nx.n2 * cx**2 + nx.n3 * cx**3
            cy = cy + ny.g * cy + ny.n2 * cy**2 + ny.n3 * cy**3
        out["psi_x"] = ca.atan(cx / coord.h)
        out["psi_y"] = ca.atan(cy / coord.h)
    out.update(x_ref=x, y_ref=y, theta_ref=theta)
    return out
