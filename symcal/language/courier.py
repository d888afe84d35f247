"""The courier's data contract, as a column preset a problem can name (``columns: courier``).

Nothing of the courier is a default: a problem for another system declares its own
``columns:`` and inherits none of these.
"""

from __future__ import annotations

#: The courier's columns (the data contract of the README): name → (unit, role, doc).  Role
#: ``time`` marks the time of an observation (a drift is a term linear in it); ``axis``
#: marks the raw position readings along which residuals are plotted.
COURIER_COLUMNS: dict[str, tuple[str, str, str]] = {
    "t": ("s", "time", "time of the observation"),
    "p1": ("mm", "axis", "raw reading of platen segment 1 (x)"),
    "p2": ("mm", "axis", "raw reading of platen segment 2 (y)"),
    "p3": ("mm", "axis", "raw reading of platen segment 3 (x)"),
    "p4": ("mm", "axis", "raw reading of platen segment 4 (y)"),
    "psi_x": ("rad", "", "coordination sensor angle to the beacon, x"),
    "psi_y": ("rad", "", "coordination sensor angle to the beacon, y"),
    "x_ref": ("mm", "", "interferometer x (ground truth)"),
    "y_ref": ("mm", "", "interferometer y (ground truth)"),
    "theta_ref": ("rad", "", "interferometer angle (ground truth)"),
}

#: Column presets by the name a problem gives under ``columns:``.
PRESETS: dict[str, dict[str, tuple[str, str, str]]] = {"courier": COURIER_COLUMNS}
