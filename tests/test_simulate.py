"""Tests of the courier simulator (symcal.simulation).

Every numerical check compares the simulator with an independent numpy computation of
the documented physics, written out here from the formulas (not imported).
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from symcal.base.errors import SpecError
from symcal.language.yamlio import display_path
from symcal.simulation import (
    load_scenario,
    noise_floor,
    simulate,
    simulate_run,
    truth,
)

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "problems" / "scenarios"
RHO = 1.016
L_S = 9.7
L_O = 4.85
SEG = ("s1", "s2", "s3", "s4")
DEG = math.pi / 180.0

# Segment errors (mm) used by the tests: large enough to matter, monotonic readings.
K = {
    "s1": [0.004, 0.017, -0.010, 0.0042, -0.0025, 0.0012, -0.0009, 0.0004, 0.0003],
    "s2": [-0.003, 0.0085, 0.0095, 0.003, 0.002, -0.001, 0.0007, 0.0003, -0.0002],
    "s3": [0.002, -0.0105, 0.014, -0.003, 0.0035, -0.0008, 0.0011, -0.0003, 0.0002],
    "s4": [0.001, -0.004, 0.012, 0.0015, -0.0025, 0.0006, 0.0008, -0.0002, 0.0003],
}
COORD = {"h": 50.0, "l_x": 90.0, "l_y": 5.0, "o_x": 1.016, "o_y": 1.016}


# --------------------------------------------------------------------------- helpers


def base_doc(errors: bool = False, **platen: Any) -> dict:
    """A scenario document with everything off (no errors, noise or quantization)."""
    segments = {s: ({f"k{j}": v for j, v in enumerate(K[s])} if errors else {}) for s in SEG}
    return {
        "scenario": "test",
        "platen": {"noise": 0.0, "quantization": 0.0, "segments": segments, **platen},
        "runs": {
            "calibration": {
                "scatter": {"n": 400, "x": [0.0, 10.16], "y": [0.0, 10.16],
                            "theta_deg": [-1.5, 1.5]},
            },
            "flyby": {
                "line": {"n": 200, "from": [5.08, -14.92], "to": [5.08, 25.08],
                         "theta_deg": 0.3, "theta_jitter_deg": 0.01},
            },
        },
    }


def with_coordination(doc: dict, **coord: Any) -> dict:
    doc = copy.deepcopy(doc)
    doc["coordination"] = {**COORD, **coord}
    return doc


def write(tmp_path: Path, doc: dict | str, name: str = "scenario.yaml") -> Path:
    path = tmp_path / name
    text = doc if isinstance(doc, str) else yaml.safe_dump(doc, sort_keys=False)
    path.write_text(text, encoding="utf-8")
    return path


def load(tmp_path: Path, doc: dict, name: str = "scenario.yaml"):
    return load_scenario(write(tmp_path, doc, name))


def readings(data: dict) -> np.ndarray:
    return np.column_stack([data[f"p{i}"] for i in range(1, 5)])


def pinwheel(x, y, theta, l_s=L_S, l_o=L_O, exact=True):
    """Independent p* and q (n, 4): world coordinate of each segment minus its body offset."""
    offsets = [(-l_o, -l_s / 2), (l_s / 2, -l_o), (l_o, l_s / 2), (-l_s / 2, l_o)]
    cos_t, sin_t = (np.cos(theta), np.sin(theta)) if exact else (1.0, theta)
    p, q = [], []
    for i, (a, b) in enumerate(offsets):
        world_x = x + a * cos_t - b * sin_t
        world_y = y + a * sin_t + b * cos_t
        if i % 2 == 0:
            p.append(world_x - a)
            q.append(world_y - b)
        else:
            p.append(world_y - b)
            q.append(world_x - a)
    return np.column_stack(p), np.column_stack(q)


def eq3(k, u, rho=RHO):
    """Eq. (3) written out term by term."""
    f = 2 * np.pi / rho
    return (k[0] + k[1] * np.sin(f * u) + k[2] * np.cos(f * u)
            + k[3] * np.sin(2 * f * u) + k[4] * np.cos(2 * f * u)
            + k[5] * np.sin(4 * f * u) + k[6] * np.cos(4 * f * u)
            + k[7] * np.sin(6 * f * u) + k[8] * np.cos(6 * f * u))


def true_pose(data: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return data["x_ref"], data["y_ref"], data["theta_ref"]


# --------------------------------------------------------------------------- geometry


def test_geometry_matches_pinwheel_and_redundancy(tmp_path):
    sc = load(tmp_path, base_doc())
    for run in ("calibration", "flyby"):
        data = simulate_run(sc, run, seed=3)
        p = readings(data)
        x, y, th = true_pose(data)
        expected, _ = pinwheel(x, y, th)
        np.testing.assert_allclose(p, expected, rtol=0, atol=1e-12)
        np.testing.assert_allclose((p[:, 0] + p[:, 2]) / 2, x, rtol=0, atol=1e-12)
        np.testing.assert_allclose((p[:, 1] + p[:, 3]) / 2, y, rtol=0, atol=1e-12)
        g_p = (p[:, 0] - p[:, 2]) - (p[:, 1] - p[:, 3])
        np.testing.assert_allclose(g_p, 0.0, rtol=0, atol=1e-12)
        # The pinwheel's offset l_o along the measuring axis adds 2 l_o (1 - cos t).
        second_order = 2 * L_O / L_S * (1 - np.cos(th))
        np.testing.assert_allclose((p[:, 0] - p[:, 2]) / L_S, np.sin(th) + second_order,
                                   rtol=0, atol=1e-12)
        np.testing.assert_allclose((p[:, 1] - p[:, 3]) / L_S, np.sin(th) + second_order,
                                   rtol=0, atol=1e-12)
    assert np.max(np.abs(simulate_run(sc, "calibration")["theta_ref"])) > 0.02


def test_geometry_without_axial_offset_gives_sine(tmp_path):
    sc = load(tmp_path, base_doc(l_o=0.0))
    data = simulate_run(sc, "calibration", seed=1)
    p = readings(data)
    np.testing.assert_allclose((p[:, 0] - p[:, 2]) / L_S, np.sin(data["theta_ref"]),
                               rtol=0, atol=1e-12)


def test_small_angle_geometry_makes_eq4_exact(tmp_path):
    sc = load(tmp_path, base_doc(geometry="small_angle"))
    data = simulate_run(sc, "calibration", seed=2)
    p = readings(data)
    x, y, th = true_pose(data)
    np.testing.assert_allclose(p, pinwheel(x, y, th, exact=False)[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose((p[:, 0] - p[:, 2]) / L_S, th, rtol=0, atol=1e-12)
    np.testing.assert_allclose((p[:, 1] - p[:, 3]) / L_S, th, rtol=0, atol=1e-12)


# --------------------------------------------------------------------------- distortion


def test_distortion_at_true_position(tmp_path):
    sc = load(tmp_path, base_doc(errors=True))
    data = simulate_run(sc, "calibration", seed=4)
    p_true, _ = pinwheel(*true_pose(data))
    for i, s in enumerate(SEG):
        # the periodic error is evaluated in the segment's counter frame, p* - k0
        expected = p_true[:, i] - eq3(K[s], p_true[:, i] - K[s][0])
        np.testing.assert_allclose(data[f"p{i + 1}"], expected, rtol=0, atol=1e-13)
    assert np.max(np.abs(readings(data) - p_true)) > 0.02


def test_distortion_at_reading_inverts_the_model(tmp_path):
    sc = load(tmp_path, base_doc(errors=True, distortion_at="reading"))
    data = simulate_run(sc, "calibration", seed=5)
    p_true, _ = pinwheel(*true_pose(data))
    p = readings(data)
    for i, s in enumerate(SEG):
        np.testing.assert_allclose(p[:, i] + eq3(K[s], p[:, i]), p_true[:, i], rtol=0, atol=1e-12)
    # and it is not the true-position form
    assert np.max(np.abs(p - (p_true - np.column_stack([eq3(K[s], p_true[:, i])
                                                          for i, s in enumerate(SEG)])))) > 1e-4


def test_reading_mode_makes_the_eq9_model_exact(tmp_path):
    lateral = {"s1": {"k9": 0.003, "k10": -0.0015}, "s2": {"k9": -0.002, "k10": 0.0025},
               "s3": {"k9": 0.001}, "s4": {"k10": 0.003}}
    doc = base_doc(errors=True, distortion_at="reading", geometry="small_angle",
                   effects={"lateral": lateral})
    data = simulate_run(load(tmp_path, doc), "calibration", seed=6)
    p = readings(data)
    f = 2 * np.pi / RHO
    theta_bar = ((p[:, 0] - p[:, 2]) + (p[:, 1] - p[:, 3])) / (2 * L_S)
    px, py = (p[:, 0] + p[:, 2]) / 2, (p[:, 1] + p[:, 3]) / 2
    args = [py - L_O * theta_bar, px + L_O * theta_bar, py + L_O * theta_bar, px - L_O * theta_bar]
    p_true, _ = pinwheel(*true_pose(data), exact=False)
    for i, s in enumerate(SEG):
        k9, k10 = lateral[s].get("k9", 0.0), lateral[s].get("k10", 0.0)
        p_hat = p[:, i] + eq3(K[s], p[:, i]) + k9 * np.sin(f * args[i]) + k10 * np.cos(f * args[i])
        np.testing.assert_allclose(p_hat, p_true[:, i], rtol=0, atol=1e-12)


def test_reading_mode_rejects_non_monotonic_errors(tmp_path):
    doc = base_doc(distortion_at="reading")
    doc["platen"]["segments"]["s1"] = {"k1": 0.5}
    path = write(tmp_path, doc)
    sc = load_scenario(path)
    with pytest.raises(SpecError) as err:
        simulate_run(sc, "calibration")
    assert str(err.value) == (
        f"{display_path(path)}:2: platen.distortion_at: distortion_at: reading did not "
        "converge: the segment errors are too steep for the reading to be a monotonic "
        "function of the position (need |de/dp| < 1)"
    )


# --------------------------------------------------------------------------- effects


def effect_delta(tmp_path: Path, effects: dict, run: str = "calibration") -> tuple:
    """Readings with and without ``effects`` (true-position physics, same seed)."""
    plain = simulate_run(load(tmp_path, base_doc(errors=True), "plain.yaml"), run, seed=7)
    doc = base_doc(errors=True, effects=effects)
    with_effect = simulate_run(load(tmp_path, doc, "effect.yaml"), run, seed=7)
    for key in ("t", "x_ref", "y_ref", "theta_ref"):
        np.testing.assert_array_equal(plain[key], with_effect[key])
    return readings(with_effect) - readings(plain), with_effect


def test_lateral_effect_formula(tmp_path):
    lateral = {"s1": {"k9": 0.003, "k10": -0.0015}, "s3": {"k9": -0.002, "k10": 0.001},
               "s4": {"k10": 0.0025}}
    delta, data = effect_delta(tmp_path, {"lateral": lateral})
    _, q = pinwheel(*true_pose(data))
    f = 2 * np.pi / RHO
    for i, s in enumerate(SEG):
        k9, k10 = lateral.get(s, {}).get("k9", 0.0), lateral.get(s, {}).get("k10", 0.0)
        expected = -(k9 * np.sin(f * q[:, i]) + k10 * np.cos(f * q[:, i]))
        np.testing.assert_allclose(delta[:, i], expected, rtol=0, atol=1e-13)
    assert np.max(np.abs(delta[:, 0])) > 0.002 and np.all(delta[:, 1] == 0)


def test_lateral_coordinate_is_eq9_argument_to_second_order(tmp_path):
    data = simulate_run(load(tmp_path, base_doc()), "calibration", seed=8)
    x, y, th = true_pose(data)
    _, q = pinwheel(x, y, th)
    eq9 = np.column_stack([y - L_O * th, x + L_O * th, y + L_O * th, x - L_O * th])
    assert np.max(np.abs(q - eq9)) < (L_S / 2) * (1.5 * DEG) ** 2  # (l_s/2)(1 - cos t) bound


def test_angle_effect_formula(tmp_path):
    angle = {"s1": {"a": 0.2, "b": 0.1, "c": -0.05}, "s2": {"a": -0.1}, "s4": {"c": 0.3}}
    delta, data = effect_delta(tmp_path, {"angle": angle})
    p_true, _ = pinwheel(*true_pose(data))
    th = data["theta_ref"]
    f = 2 * np.pi / RHO
    for i, s in enumerate(SEG):
        a, b, c = (angle.get(s, {}).get(key, 0.0) for key in ("a", "b", "c"))
        u = p_true[:, i] - K[s][0]  # tooth phase in the segment's counter frame
        expected = -(a * th + b * th * np.sin(f * u) + c * th * np.cos(f * u))
        np.testing.assert_allclose(delta[:, i], expected, rtol=0, atol=1e-13)
    assert np.max(np.abs(delta[:, 0])) > 0.003


def test_harmonics_effect_formula(tmp_path):
    harmonics = {"s1": [{"n": 3, "sin": 0.002, "cos": -0.001}, {"n": 5, "sin": 0.0007}],
                 "s2": [{"n": 12, "cos": 0.0004}], "s3": [{"n": 1, "sin": 0.001}]}
    delta, data = effect_delta(tmp_path, {"harmonics": harmonics})
    p_true, _ = pinwheel(*true_pose(data))
    f = 2 * np.pi / RHO
    for i, s in enumerate(SEG):
        expected = np.zeros(len(p_true))
        for h in harmonics.get(s, []):
            u = p_true[:, i] - K[s][0]  # tooth phase in the segment's counter frame
            expected -= h.get("sin", 0.0) * np.sin(h["n"] * f * u)
            expected -= h.get("cos", 0.0) * np.cos(h["n"] * f * u)
        np.testing.assert_allclose(delta[:, i], expected, rtol=0, atol=1e-13)
    assert np.max(np.abs(delta[:, 0])) > 0.002


def test_drift_effect_formula(tmp_path):
    drift = {"s2": {"rate": 1e-5, "quadratic": 2e-8}, "s4": {"rate": -3e-5}}
    delta, data = effect_delta(tmp_path, {"drift": drift})
    t = data["t"]
    np.testing.assert_allclose(t, 0.1 * np.arange(400), rtol=0, atol=1e-12)
    for i, s in enumerate(SEG):
        rate, quad = drift.get(s, {}).get("rate", 0.0), drift.get(s, {}).get("quadratic", 0.0)
        np.testing.assert_allclose(delta[:, i], -(rate * t + quad * t**2), rtol=0, atol=1e-13)
    assert abs(delta[-1, 3]) > 1e-3


def test_pitch_variation_formula(tmp_path):
    waves = {"x": [{"amplitude": 0.002, "wavelength": 7.3, "phase": 0.4},
                   {"amplitude": 0.001, "wavelength": 23.0}],
             "y": [{"amplitude": 0.0015, "wavelength": 5.9, "phase": -1.0}]}
    _, data = effect_delta(tmp_path, {"pitch_variation": waves}, run="flyby")
    p_true, _ = pinwheel(*true_pose(data))

    def w(axis, p):
        return sum(wv["amplitude"] * np.sin(2 * np.pi * p / wv["wavelength"] + wv.get("phase", 0.0))
                   for wv in waves[axis])

    for i, s in enumerate(SEG):
        u = p_true[:, i] + w("x" if i % 2 == 0 else "y", p_true[:, i])
        np.testing.assert_allclose(data[f"p{i + 1}"], u - eq3(K[s], u - K[s][0]), rtol=0,
                                   atol=1e-12)
    # it shows as a position error against the interferometer of about the wave size
    y_err = (data["p2"] + data["p4"]) / 2 - data["y_ref"]
    plain = simulate_run(load(tmp_path, base_doc(errors=True), "plain.yaml"), "flyby", seed=7)
    y_err_plain = (plain["p2"] + plain["p4"]) / 2 - plain["y_ref"]
    assert 0.0005 < np.std(y_err - y_err_plain) < 0.0015


# --------------------------------------------------------------------------- noise


def test_platen_noise_std_matches_sigma(tmp_path):
    sigma = 0.001
    doc = base_doc(errors=True, noise=sigma)
    doc["runs"]["calibration"]["scatter"]["n"] = 20000
    noisy = readings(simulate_run(load(tmp_path, doc, "noisy.yaml"), "calibration", seed=9))
    doc["platen"]["noise"] = 0.0
    quiet = readings(simulate_run(load(tmp_path, doc, "quiet.yaml"), "calibration", seed=9))
    z = noisy - quiet
    # 80000 draws: the standard error of the std is sigma / sqrt(2 N) = 0.25 %; allow 2 %.
    assert abs(np.std(z) / sigma - 1) < 0.02
    assert abs(np.mean(z)) < 5 * sigma / math.sqrt(z.size)
    corr = np.corrcoef(z.T)
    assert np.max(np.abs(corr - np.eye(4))) < 0.05


def test_quantization_gives_multiples_of_the_step(tmp_path):
    q = 0.0002
    doc = base_doc(errors=True, noise=0.0005, quantization=q)
    data = simulate_run(load(tmp_path, doc), "calibration", seed=10)
    steps = readings(data) / q
    assert np.max(np.abs(steps - np.round(steps))) < 1e-6
    doc["platen"]["quantization"] = 0.0
    raw = readings(simulate_run(load(tmp_path, doc, "raw.yaml"), "calibration", seed=10))
    assert np.max(np.abs(readings(data) - raw)) <= q / 2 + 1e-12
    assert np.max(np.abs(readings(data) - raw)) > q / 4


def test_noise_floor_matches_a_pure_noise_simulation(tmp_path):
    doc = base_doc(noise=0.0005, quantization=0.0002)
    doc["runs"]["calibration"]["scatter"]["n"] = 20000
    sc = load(tmp_path, doc)
    floor = noise_floor(sc)
    s = math.sqrt(0.0005**2 + 0.0002**2 / 12)
    assert floor["platen_reading_std"] == pytest.approx(s, rel=1e-12)
    assert floor["g_p_std"] == pytest.approx(2 * s, rel=1e-12)
    p = readings(simulate_run(sc, "calibration", seed=11))
    g_p = (p[:, 0] - p[:, 2]) - (p[:, 1] - p[:, 3])
    assert np.std(g_p) == pytest.approx(floor["g_p_std"], rel=0.03)


def test_coordination_and_reference_noise(tmp_path):
    doc = with_coordination(base_doc(), noise=2e-5)
    doc["reference"] = {"position_noise": 1e-4, "angle_noise": 1e-6}
    doc["runs"]["calibration"]["scatter"]["n"] = 20000
    noisy = simulate_run(load(tmp_path, doc, "noisy.yaml"), "calibration", seed=12)
    doc["coordination"]["noise"] = 0.0
    doc["reference"] = {}
    quiet = simulate_run(load(tmp_path, doc, "quiet.yaml"), "calibration", seed=12)
    for key, sigma in (("psi_x", 2e-5), ("psi_y", 2e-5), ("x_ref", 1e-4), ("y_ref", 1e-4),
                       ("theta_ref", 1e-6)):
        assert np.std(noisy[key] - quiet[key]) == pytest.approx(sigma, rel=0.03), key


# --------------------------------------------------------------------------- coordination


def eq11(data: dict, theta: np.ndarray, h=50.0, l_x=90.0, l_y=5.0, o_x=1.016, o_y=1.016):
    p = readings(data)
    px, py = (p[:, 0] + p[:, 2]) / 2, (p[:, 1] + p[:, 3]) / 2
    cx, cy = h * np.tan(data["psi_x"]), h * np.tan(data["psi_y"])
    c, s = np.cos(theta), np.sin(theta)
    g_x = -px + c * cx - s * cy - l_y * s + l_x * c + o_x
    g_y = -py + s * cx + c * cy + l_y * c + l_x * s + o_y
    return g_x, g_y


@pytest.mark.parametrize("rotate_about", ["platen", "coordination"])
def test_coordination_satisfies_eq11(tmp_path, rotate_about):
    doc = with_coordination(base_doc(geometry="small_angle"))
    doc["runs"]["calibration"]["scatter"]["rotate_about"] = rotate_about
    data = simulate_run(load(tmp_path, doc), "calibration", seed=13)
    p = readings(data)
    theta_hat = ((p[:, 0] - p[:, 2]) + (p[:, 1] - p[:, 3])) / (2 * L_S)  # eq. (4), averaged
    for g in eq11(data, theta_hat):
        np.testing.assert_allclose(g, 0.0, rtol=0, atol=1e-10)
    # exact geometry: eq. (11) holds with the true angle
    exact = simulate_run(load(tmp_path, with_coordination(base_doc()), "x.yaml"), "flyby", seed=1)
    for g in eq11(exact, exact["theta_ref"]):
        np.testing.assert_allclose(g, 0.0, rtol=0, atol=1e-10)
    assert np.max(np.abs(data["psi_x"])) > 1e-3


def test_rotate_about_coordination_samples_the_sensor_position(tmp_path):
    doc = with_coordination(base_doc())
    doc["runs"]["calibration"]["scatter"].update(
        {"x": [0.0, 2.032], "y": [0.0, 2.032], "rotate_about": "coordination"})
    data = simulate_run(load(tmp_path, doc), "calibration", seed=14)
    x, y, th = true_pose(data)
    sx = x - (np.cos(th) * 90.0 - np.sin(th) * 5.0)
    sy = y - (np.sin(th) * 90.0 + np.cos(th) * 5.0)
    for s in (sx, sy):
        assert s.min() >= -1e-12 and s.max() <= 2.032 + 1e-12 and np.ptp(s) > 1.9
    # the coordination sensor stays under the beacon: c = R^T (s - o)
    cx = np.cos(th) * (sx - 1.016) + np.sin(th) * (sy - 1.016)
    np.testing.assert_allclose(np.tan(data["psi_x"]) * 50.0, cx, rtol=0, atol=1e-10)
    assert np.max(np.abs(data["psi_x"])) < 0.03


def test_psd_nonlinearity_formula(tmp_path):
    nl = {"x": {"n2": 0.01, "n3": -0.002}, "y": {"n3": 0.004}}
    plain = simulate_run(load(tmp_path, with_coordination(base_doc()), "a.yaml"), "flyby", seed=2)
    doc = with_coordination(base_doc(), nonlinearity=nl)
    data = simulate_run(load(tmp_path, doc, "b.yaml"), "flyby", seed=2)
    for axis in ("x", "y"):
        c = 50.0 * np.tan(plain[f"psi_{axis}"])
        n2, n3 = nl[axis].get("n2", 0.0), nl[axis].get("n3", 0.0)
        expected = np.arctan((c + n2 * c**2 + n3 * c**3) / 50.0)
        np.testing.assert_allclose(data[f"psi_{axis}"], expected, rtol=0, atol=1e-13)
    assert np.max(np.abs(data["psi_y"] - plain["psi_y"])) > 1e-5


# --------------------------------------------------------------------------- seeds, API


def test_seeds_are_reproducible_and_streams_independent(tmp_path):
    doc = with_coordination(base_doc(errors=True, noise=0.0005, quantization=0.0002),
                            noise=2e-5)
    doc["runs"]["twin"] = copy.deepcopy(doc["runs"]["calibration"])
    sc = load(tmp_path, doc)
    a, b = simulate_run(sc, "calibration", seed=5), simulate_run(sc, "calibration", seed=5)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    other = simulate_run(sc, "calibration", seed=6)
    assert not np.array_equal(a["x_ref"], other["x_ref"])
    twin = simulate_run(sc, "twin", seed=5)  # same motion, different run: different draws
    assert not np.array_equal(a["x_ref"], twin["x_ref"])
    # poses do not depend on the noise settings (independent streams)
    doc["platen"]["noise"] = 0.0
    doc["coordination"]["noise"] = 0.0
    quiet = simulate_run(load(tmp_path, doc, "quiet.yaml"), "calibration", seed=5)
    np.testing.assert_array_equal(a["x_ref"], quiet["x_ref"])
    np.testing.assert_array_equal(a["theta_ref"], quiet["theta_ref"])
    # a shorter scatter is a prefix of a longer one
    short = simulate_run(sc, "calibration", seed=5, n=50)
    np.testing.assert_array_equal(short["p3"], a["p3"][:50])
    np.testing.assert_array_equal(short["psi_y"], a["psi_y"][:50])


def test_columns_and_simulate(tmp_path):
    plain = simulate(load(tmp_path, base_doc()), seed=1, n=7)
    assert list(plain) == ["calibration", "flyby"]
    assert list(plain["flyby"]) == ["t", "p1", "p2", "p3", "p4", "x_ref", "y_ref", "theta_ref"]
    dual = simulate(load(tmp_path, with_coordination(base_doc()), "dual.yaml"))
    assert list(dual["calibration"]) == [
        "t", "p1", "p2", "p3", "p4", "psi_x", "psi_y", "x_ref", "y_ref", "theta_ref"]
    for data in (plain["calibration"], dual["flyby"]):
        for column in data.values():
            assert column.dtype == np.float64 and column.ndim == 1
    assert len(dual["flyby"]["t"]) == 200 and len(plain["calibration"]["p1"]) == 7
    line = dual["flyby"]
    assert line["y_ref"][0] == pytest.approx(-14.92) and line["y_ref"][-1] == pytest.approx(25.08)
    assert np.std(line["theta_ref"]) == pytest.approx(0.01 * DEG, rel=0.25)


def test_bad_arguments(tmp_path):
    sc = load(tmp_path, base_doc())
    with pytest.raises(ValueError, match="n must be a whole number of at least 1, found 0"):
        simulate_run(sc, "calibration", n=0)
    with pytest.raises(ValueError, match="seed must be"):
        simulate_run(sc, "calibration", seed=-1)


@pytest.mark.slow
def test_one_million_poses(tmp_path):
    sc = load_scenario(SCENARIOS / "courier_platen.yaml")
    data = simulate_run(sc, "calibration", seed=0, n=10**6)
    assert all(column.shape == (10**6,) for column in data.values())
    assert np.all(np.isfinite(data["p4"]))


# --------------------------------------------------------------------------- truth


def test_truth_names_and_values(tmp_path):
    lateral = {"s2": {"k9": 0.002, "k10": -0.001}}
    doc = with_coordination(base_doc(errors=True, noise=0.0005, effects={"lateral": lateral}),
                            noise=2e-5)
    info = truth(load(tmp_path, doc))
    params = info["parameters"]
    assert info["scenario"] == "test"
    assert params["s3.k4"] == K["s3"][4] and params["s1.k0"] == K["s1"][0]
    assert params["s2.k9"] == 0.002 and params["s2.k10"] == -0.001 and params["s1.k9"] == 0.0
    assert {params[k] for k in ("h", "l_x", "l_y", "o_x", "o_y")} == set(COORD.values())
    assert len(params) == 4 * 11 + 5
    assert info["effects"]["lateral"]["on"] and not info["effects"]["angle"]["on"]
    assert info["effects"]["distortion_at"]["value"] == "true_position"
    assert info["noise"]["platen_sigma"] == 0.0005 and info["noise"]["psi_sigma"] == 2e-5
    assert yaml.safe_load(yaml.safe_dump(info)) == info
    plain = truth(load(tmp_path, base_doc(), "plain.yaml"))["parameters"]
    assert sorted(plain) == sorted(f"{s}.k{j}" for s in SEG for j in range(9))


# --------------------------------------------------------------------------- defaults


def g_p_std(data: dict) -> float:
    p = readings(data)
    return float(np.std((p[:, 0] - p[:, 2]) - (p[:, 1] - p[:, 3])))


def test_default_platen_scenario_magnitudes():
    sc = load_scenario(SCENARIOS / "courier_platen.yaml")
    data = simulate(sc, seed=0)
    assert 0.025 < g_p_std(data["calibration"]) < 0.035  # paper 29.3 um
    assert 0.008 < g_p_std(data["flyby"]) < 0.016  # paper 12.1 um
    cal = data["calibration"]
    assert cal["x_ref"].min() >= 0 and cal["x_ref"].max() <= 10 * RHO
    assert np.max(np.abs(cal["theta_ref"])) <= 0.5 * DEG
    fly = data["flyby"]
    assert np.ptp(fly["y_ref"]) == pytest.approx(40.0)
    assert set(truth(sc)["effects"]) >= {"lateral", "angle", "harmonics", "drift",
                                         "pitch_variation"}
    assert all(truth(sc)["effects"][e]["on"] for e in ("lateral", "pitch_variation"))


def test_default_dual_scenario():
    sc = load_scenario(SCENARIOS / "courier_dual.yaml")
    data = simulate(sc, seed=0)
    cal, fly = data["calibration"], data["flyby"]
    assert len(cal["t"]) == 1000 and np.max(np.abs(cal["theta_ref"])) <= 1.5 * DEG
    assert np.max(np.abs(cal["psi_x"])) < 0.03 and np.max(np.abs(cal["psi_y"])) < 0.03
    assert np.ptp(fly["y_ref"]) == pytest.approx(8.0, abs=0.01)
    floor = noise_floor(sc)
    assert floor["c_std"] == pytest.approx(0.001) and floor["g_p_std"] > 0.002
    assert truth(sc)["parameters"]["l_x"] == 90.0


# --------------------------------------------------------------------------- bad input

BAD = """\
scenario: bad
platen:
  noise: 0.0
  segments: {s1: {}, s2: {}, s3: {}, s4: {}}
runs:
  calibration:
    scatter: {n: 10, x: [0, 1], y: [0, 1], theta_deg: [-1, 1]}
"""


def bad(tmp_path: Path, old: str, new: str) -> tuple[str, str]:
    assert old in BAD
    path = write(tmp_path, BAD.replace(old, new))
    with pytest.raises(SpecError) as err:
        load_scenario(path)
    return str(err.value), display_path(path)


def test_bad_base_is_valid(tmp_path):
    assert load_scenario(write(tmp_path, BAD)).run_names == ("calibration",)


def test_unknown_key_with_did_you_mean(tmp_path):
    message, shown = bad(tmp_path, "  noise: 0.0", "  nosie: 0.0")
    assert message == (
        f"{shown}:3: platen.nosie: unknown key 'nosie' (did you mean 'noise'?); allowed keys: "
        "segments, pitch, l_s, l_o, distortion_at, geometry, noise, quantization, effects"
    )


def test_unknown_segment_in_effect(tmp_path):
    message, shown = bad(tmp_path, "  noise: 0.0\n", "  noise: 0.0\n  effects:\n"
                         "    lateral:\n      s5: {k9: 0.001}\n")
    assert message == (
        f"{shown}:6: platen.effects.lateral.s5: unknown key 's5' (did you mean 's1'?); "
        "allowed keys: s1, s2, s3, s4"
    )


def test_missing_key(tmp_path):
    message, shown = bad(tmp_path, ", theta_deg: [-1, 1]}", "}")
    assert message == f"{shown}:7: runs.calibration.scatter: missing required key 'theta_deg'"


def test_missing_segment(tmp_path):
    message, shown = bad(tmp_path, ", s4: {}}", "}")
    assert message == f"{shown}:4: platen.segments: missing required key 's4'"


def test_wrong_type(tmp_path):
    message, shown = bad(tmp_path, "{n: 10,", "{n: many,")
    assert message == (
        f"{shown}:7: runs.calibration.scatter.n: expected a whole number, found text ('many')"
    )


def test_wrong_number_type(tmp_path):
    message, shown = bad(tmp_path, "  noise: 0.0", "  noise: [1]")
    assert message == f"{shown}:3: platen.noise: expected a number, found a list"


def test_negative_noise(tmp_path):
    message, shown = bad(tmp_path, "  noise: 0.0", "  noise: -0.001")
    assert message == f"{shown}:3: platen.noise: expected a number of at least 0, found -0.001"


def test_bad_choice(tmp_path):
    message, shown = bad(tmp_path, "  noise: 0.0", "  distortion_at: readings")
    assert message == (
        f"{shown}:3: platen.distortion_at: expected one of true_position, reading, "
        "found 'readings' (did you mean 'reading'?)"
    )


def test_bad_range(tmp_path):
    message, shown = bad(tmp_path, "x: [0, 1]", "x: [1, 0]")
    assert message == (
        f"{shown}:7: runs.calibration.scatter.x: range [lo, hi] must have lo <= hi, found [1, 0]"
    )
    message, shown = bad(tmp_path, "y: [0, 1]", "y: [0, 1, 2]")
    assert message == (
        f"{shown}:7: runs.calibration.scatter.y: expected a range [lo, hi] of two numbers, "
        "found a list of 3"
    )


def test_rotate_about_needs_coordination(tmp_path):
    message, shown = bad(tmp_path, "theta_deg: [-1, 1]}", "theta_deg: [-1, 1],\n"
                         "              rotate_about: coordination}")
    assert message == (
        f"{shown}:8: runs.calibration.scatter.rotate_about: rotate_about: coordination needs "
        "a 'coordination' section in the scenario"
    )


def test_run_needs_exactly_one_motion(tmp_path):
    message, shown = bad(tmp_path, "    scatter:", "    line: {n: 3, from: [0, 0], to: [1, 1]}\n"
                         "    scatter:")
    assert message == (
        f"{shown}:6: runs.calibration: a run needs exactly one motion, 'scatter' or 'line'; "
        "found 'scatter' and 'line'"
    )


def test_missing_top_level_key_and_empty_effect(tmp_path):
    message, shown = bad(tmp_path, "scenario: bad\n", "")
    assert message == f"{shown}:1: missing required key 'scenario'"
    message, shown = bad(tmp_path, "  noise: 0.0\n", "  noise: 0.0\n  effects: {drift: {}}\n")
    assert message == (
        f"{shown}:4: platen.effects.drift: lists no segment (s1..s4); remove the effect to "
        "switch it off"
    )


def test_unknown_run(tmp_path):
    path = write(tmp_path, BAD)
    sc = load_scenario(path)
    with pytest.raises(SpecError) as err:
        simulate_run(sc, "calibratoin")
    assert str(err.value) == (
        f"{display_path(path)}:5: runs: no run named 'calibratoin' "
        "(did you mean 'calibration'?); runs: calibration"
    )
