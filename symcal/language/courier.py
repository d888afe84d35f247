"""The courier's data contract, as a column preset a problem can name (``columns: courier``).

Nothing of the courier is a default: a problem for another system declares its own
``columns:`` and inherits none of these.
"""

from __future__ import annotations

#: The courier's columns (the data contract of the README): name → (unit, role, doc,
#: noise).  Role ``time`` marks the time of an observation (a drift is a term linear in
#: it); ``axis`` marks the raw position readings along which residuals are plotted;
#: ``reference`` the interferometer's readings, which are never an effect.  The
#: noise of the time and of the interferometer is declared here (a clock is exact; a
#: laser interferometer resolves about 10 nm and 0.1 µrad, negligible beside the
#: sensors'); the platen and coordination readings' noise is their models' (their inputs'
#: ``noise``), overridden per instance or in a problem's ``noise:`` section.
COURIER_COLUMNS: dict[str, tuple[str, str, str, str | None]] = {
    "t": ("s", "time", "time of the observation", "0 s"),
    "p1": ("mm", "axis", "raw reading of platen segment 1 (x)", None),
    "p2": ("mm", "axis", "raw reading of platen segment 2 (y)", None),
    "p3": ("mm", "axis", "raw reading of platen segment 3 (x)", None),
    "p4": ("mm", "axis", "raw reading of platen segment 4 (y)", None),
    "psi_x": ("rad", "", "coordination sensor angle to the beacon, x", None),
    "psi_y": ("rad", "", "coordination sensor angle to the beacon, y", None),
    "x_ref": ("mm", "reference", "interferometer x (ground truth)", "0.01 um"),
    "y_ref": ("mm", "reference", "interferometer y (ground truth)", "0.01 um"),
    "theta_ref": ("rad", "reference", "interferometer angle (ground truth)", "0.1 urad"),
}

#: Column presets by the name a problem gives under ``columns:``.
PRESETS: dict[str, dict[str, tuple[str, str, str, str | None]]] = {"courier": COURIER_COLUMNS}
