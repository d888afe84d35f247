"""Simulate the closed-chain self-calibration of a planar 3-link arm (numpy only).

The arm's base joint sits at the origin; links of lengths a1, a2, a3 carry the tool, which
is pinned to a fixed point (px, py) the arm does not know.  With three joints and two
constraints the pinned arm keeps one degree of freedom, its self-motion: joint 1 swings
back and forth and joints 2 and 3 follow (elbow-up).  Only the three joint encoders are
recorded.  Each encoder reads its joint's angle less an unknown offset:

    q_i = (phi_i - offset_i) / (1 + gain_i) + noise,

so that the model ``angle_i = q_i + offset_i`` holds exactly when every gain is zero.

Writes ``calibration.csv`` and ``validation.csv`` (columns ``t, q1, q2, q3``: seconds and
radians) and ``truth.json`` (the true parameters, and the values a calibration with
``a1`` known and ``e1.offset`` fixed at zero must find) into ``--out``.

Usage::

    python examples/planar_arm/simulate_arm.py --out build/planar_arm --seed 1
    python examples/planar_arm/simulate_arm.py --out build/arm_gain --gain e2=0.002
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

#: The true arm: link lengths (m), encoder offsets (rad), the pin (m).
TRUTH = {
    "a1": 0.4012, "a2": 0.2987, "a3": 0.2006,
    "e1.offset": 0.021, "e2.offset": -0.013, "e3.offset": 0.008,
    "px": 0.452, "py": 0.247,
}
NOISE = 2e-5    # encoder noise, rad (standard deviation)
SWING = 0.95    # amplitude of joint 1's swing about the pin's direction, rad
PERIOD = 10.0   # s, one back-and-forth of the self-motion
RUNS = {"calibration": (200, 20.0, 0.0), "validation": (100, 10.0, 0.3)}  # n, s, phase


def joint_angles(truth: dict[str, float], t: np.ndarray, phase: float) -> np.ndarray:
    """Absolute joint angles ``phi`` (N × 3, rad) of the pinned arm at times ``t``."""
    a1, a2, a3 = truth["a1"], truth["a2"], truth["a3"]
    pin = np.array([truth["px"], truth["py"]])
    phi1 = np.arctan2(pin[1], pin[0]) + SWING * np.sin(2 * np.pi * t / PERIOD + phase)
    wrist = a1 * np.column_stack([np.cos(phi1), np.sin(phi1)])
    reach = pin[None, :] - wrist
    d2 = np.sum(reach**2, axis=1)
    cos3 = (d2 - a2**2 - a3**2) / (2 * a2 * a3)
    if np.any(np.abs(cos3) > 1):
        raise ValueError("the pin is out of reach for part of the swing")
    phi3 = np.arccos(cos3)  # elbow-up branch
    phi2 = (np.arctan2(reach[:, 1], reach[:, 0]) - phi1
            - np.arctan2(a3 * np.sin(phi3), a2 + a3 * np.cos(phi3)))
    return np.column_stack([phi1, phi2, phi3])


def tool(truth: dict[str, float], phi: np.ndarray) -> np.ndarray:
    """Tool position (N × 2, m) from absolute joint angles: the forward kinematics."""
    c = np.cumsum(phi, axis=1)
    a = np.array([truth["a1"], truth["a2"], truth["a3"]])
    return np.column_stack([np.cos(c) @ a, np.sin(c) @ a])


def simulate(seed: int, gains: dict[str, float], noise: float = NOISE
             ) -> dict[str, np.ndarray]:
    """Every run as an ``N × 4`` table (t, q1, q2, q3)."""
    rng = np.random.default_rng(seed)
    offsets = np.array([TRUTH[f"e{i}.offset"] for i in (1, 2, 3)])
    gain = np.array([gains.get(f"e{i}", 0.0) for i in (1, 2, 3)])
    tables = {}
    for name, (n, duration, phase) in RUNS.items():
        t = np.linspace(0.0, duration, n)
        phi = joint_angles(TRUTH, t, phase)
        assert np.allclose(tool(TRUTH, phi), [TRUTH["px"], TRUTH["py"]], atol=1e-12)
        q = (phi - offsets[None, :]) / (1 + gain[None, :])
        q = q + noise * rng.standard_normal(q.shape)
        tables[name] = np.column_stack([t, q])
    return tables


def gauge_fixed(truth: dict[str, float]) -> dict[str, float]:
    """The parameters as a calibration with a1 known and e1.offset fixed at 0 finds them:
    the pin seen from encoder 1's zero (the base frame turned by e1.offset)."""
    c, s = np.cos(truth["e1.offset"]), np.sin(truth["e1.offset"])
    out = dict(truth)
    out["e1.offset"] = 0.0
    out["px"] = c * truth["px"] + s * truth["py"]
    out["py"] = -s * truth["px"] + c * truth["py"]
    return out


def main(argv: list[str] | None = None) -> int:
    """Command line: write the runs and the truth into ``--out``."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="folder to write the files into")
    parser.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    parser.add_argument("--gain", action="append", default=[], metavar="eI=G",
                        help="a gain error G of encoder I, e.g. e2=0.002 (0.2 %%)")
    parser.add_argument("--noise", type=float, default=NOISE, metavar="RAD",
                        help=f"encoder noise, standard deviation in rad (default {NOISE:g}; "
                             "0: noiseless, up to the 10 digits the files keep)")
    args = parser.parse_args(argv)
    if not args.noise >= 0:
        parser.error(f"--noise {args.noise}: give a standard deviation of at least 0")
    gains = {}
    for item in args.gain:
        name, _, value = item.partition("=")
        if name not in ("e1", "e2", "e3") or not value:
            parser.error(f"--gain {item!r}: expected e1=G, e2=G or e3=G")
        gains[name] = float(value)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name, table in simulate(args.seed, gains, args.noise).items():
        np.savetxt(out / f"{name}.csv", table, delimiter=",", header="t,q1,q2,q3",
                   comments="", fmt="%.10g")
    doc = {"seed": args.seed, "noise_rad": args.noise, "gains": gains, "parameters": TRUTH,
           "gauge_fixed": gauge_fixed(TRUTH)}
    (out / "truth.json").write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {', '.join(f'{n}.csv' for n in RUNS)} and truth.json to {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
