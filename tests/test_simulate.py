"""Tests of the simulator (symcal.simulation): the scenario language on a toy system, and
the courier written in it.

Every numerical check compares the simulator with an independent numpy computation of
the documented physics, written out here from the formulas (not imported).  The courier
scenarios reproduce the courier simulator they replaced bit for bit (hashes of its output
at commit 37e95dc in ``tests/data``).
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from symcal.base.errors import SpecError
from symcal.language.yamlio import display_path
from symcal.simulation import (
    input_noise,
    load_scenario,
    noise_streams,
    quiet,
    simulate,
    simulate_run,
    slipped_rows,
    truth,
)

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "problems" / "scenarios"
PLATEN = SCENARIOS / "courier_platen.yaml"
DUAL = SCENARIOS / "courier_dual.yaml"
RHO = 1.016
L_S = 9.7
L_O = 4.85
SEG = ("s1", "s2", "s3", "s4")
DEG = math.pi / 180.0
EFFECTS = ("harmonics", "angle", "lateral", "drift", "pitch_variation")

# The courier's segment errors (mm), as courier_platen.yaml declares them.
K = {
    "s1": [0.004, 0.017, -0.010, 0.0042, -0.0025, 0.0012, -0.0009, 0.0004, 0.0003],
    "s2": [-0.003, 0.0085, 0.0095, 0.003, 0.002, -0.001, 0.0007, 0.0003, -0.0002],
    "s3": [0.002, -0.0105, 0.014, -0.003, 0.0035, -0.0008, 0.0011, -0.0003, 0.0002],
    "s4": [0.001, -0.004, 0.012, 0.0015, -0.0025, 0.0006, 0.0008, -0.0002, 0.0003],
}
ZERO_K = {f"{s}.k{j}": 0.0 for s in SEG for j in range(9)}
RUNS = {"calibration": {"scatter": {"n": 400, "theta": [-1.5, 1.5]}},
        "flyby": {"line": {"n": 200, "theta": 0.3, "jitter": {"theta": 0.01}}}}


# --------------------------------------------------------------------------- helpers


def courier(errors: bool = False, effects: dict | None = None, model: bool = False,
            **constants: Any):
    """courier_platen.yaml without noise or quantization, every effect off except
    ``effects`` (name -> values, or None for the file's values), runs as in RUNS."""
    sc = load_scenario(SCENARIOS / "courier_platen_model.yaml" if model else PLATEN)
    changes: dict[str, Any] = {"constants": {"sigma_p": 0, "step_p": 0, **constants},
                               "runs": RUNS}
    if not errors:
        changes["truth"] = ZERO_K
    if not model:
        changes["effects"] = {name: {"on": name in (effects or {})} for name in EFFECTS}
        for name, values in (effects or {}).items():
            if values is not None:
                changes["effects"][name]["values"] = values
    return sc.overlay(changes)


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


# --------------------------------------------------------------------------- the courier


def _digest(values: np.ndarray) -> str:
    """sha256 of the values as little-endian doubles, -0.0 counted as 0.0."""
    return hashlib.sha256(np.ascontiguousarray(values + 0.0, dtype="<f8").tobytes()).hexdigest()


def test_courier_scenarios_reproduce_the_courier_simulator_bit_for_bit():
    """The courier, written in the scenario language, gives the data of the numpy
    simulator it replaced: every column bit for bit (a reading that rounds to zero may
    differ in the sign of that zero), except the coordination angles, where CasADi's atan
    and numpy's differ by one unit in the last place on a few samples (their mean and
    spread agree to 1e-14)."""
    old = json.loads((ROOT / "tests" / "data" / "courier_simulator_37e95dc.json").read_text())
    files = {"courier_platen": PLATEN, "courier_platen_clean": SCENARIOS /
             "courier_platen_clean.yaml", "courier_dual": DUAL, "courier_dual_clean":
             SCENARIOS / "courier_dual_clean.yaml",
             "hidden": ROOT / "examples" / "hidden_effect" / "scenario.yaml"}
    checked = 0
    scenarios = {name: load_scenario(path) for name, path in files.items()}
    runs: dict[tuple[str, str, str], dict[str, np.ndarray]] = {}
    for key, expected in old.items():
        name, run, seed, column = key.split("|")
        if (name, run, seed) not in runs:
            runs[name, run, seed] = simulate_run(scenarios[name], run, seed=int(seed))
        data = runs[name, run, seed]
        if isinstance(expected, str):
            assert _digest(data[column]) == expected, key
        else:
            assert np.mean(data[column]) == pytest.approx(expected["mean"], rel=1e-14)
            assert np.std(data[column]) == pytest.approx(expected["std"], rel=1e-14)
        checked += 1
    assert checked == 88


def test_geometry_matches_pinwheel_and_redundancy():
    sc = courier()
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
    assert np.max(np.abs(simulate_run(sc, "calibration")["theta_ref"])) > 0.02


def test_geometry_without_axial_offset_gives_sine():
    data = simulate_run(courier(l_o={"value": 0.0, "unit": "mm"}), "calibration", seed=1)
    p = readings(data)
    np.testing.assert_allclose((p[:, 0] - p[:, 2]) / L_S, np.sin(data["theta_ref"]),
                               rtol=0, atol=1e-12)


def test_small_angle_geometry_makes_eq4_exact():
    sc = courier().overlay({"expressions": {"st": "theta", "cm": 0}})
    data = simulate_run(sc, "calibration", seed=2)
    p = readings(data)
    x, y, th = true_pose(data)
    np.testing.assert_allclose(p, pinwheel(x, y, th, exact=False)[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose((p[:, 0] - p[:, 2]) / L_S, th, rtol=0, atol=1e-12)
    np.testing.assert_allclose((p[:, 1] - p[:, 3]) / L_S, th, rtol=0, atol=1e-12)


def test_distortion_at_true_position():
    data = simulate_run(courier(errors=True), "calibration", seed=4)
    p_true, _ = pinwheel(*true_pose(data))
    for i, s in enumerate(SEG):
        # the periodic error is evaluated in the segment's counter frame, p* - k0
        expected = p_true[:, i] - eq3(K[s], p_true[:, i] - K[s][0])
        np.testing.assert_allclose(data[f"p{i + 1}"], expected, rtol=0, atol=1e-13)
    assert np.max(np.abs(readings(data) - p_true)) > 0.02


def test_readings_solved_from_the_model_invert_it():
    data = simulate_run(courier(errors=True, model=True), "calibration", seed=5)
    p_true, _ = pinwheel(*true_pose(data), exact=False)
    p = readings(data)
    for i, s in enumerate(SEG):
        np.testing.assert_allclose(p[:, i] + eq3(K[s], p[:, i]), p_true[:, i], rtol=0,
                                   atol=1e-12)
    # and it is not the true-position form
    assert np.max(np.abs(p - (p_true - np.column_stack([eq3(K[s], p_true[:, i])
                                                          for i, s in enumerate(SEG)])))) > 1e-4


def test_solved_readings_make_the_eq9_model_exact():
    lateral = {"s1": (0.003, -0.0015), "s2": (-0.002, 0.0025), "s3": (0.001, 0.0),
               "s4": (0.0, 0.003)}
    full = yaml.safe_load(PLATEN.read_text())["effects"]["lateral"]
    full["values"] = {f"{s}.k{9 + j}": v[j] for s, v in lateral.items() for j in (0, 1)}
    sc = courier(errors=True, model=True).overlay({"effects": {"lateral": full}})
    data = simulate_run(sc, "calibration", seed=6)
    p = readings(data)
    f = 2 * np.pi / RHO
    theta_bar = ((p[:, 0] - p[:, 2]) + (p[:, 1] - p[:, 3])) / (2 * L_S)
    px, py = (p[:, 0] + p[:, 2]) / 2, (p[:, 1] + p[:, 3]) / 2
    args = [py - L_O * theta_bar, px + L_O * theta_bar, py + L_O * theta_bar, px - L_O * theta_bar]
    p_true, _ = pinwheel(*true_pose(data), exact=False)
    for i, s in enumerate(SEG):
        k9, k10 = lateral[s]
        p_hat = p[:, i] + eq3(K[s], p[:, i]) + k9 * np.sin(f * args[i]) + k10 * np.cos(f * args[i])
        np.testing.assert_allclose(p_hat, p_true[:, i], rtol=0, atol=1e-12)


def test_solved_readings_that_do_not_converge_are_refused():
    sc = courier(model=True).overlay({"truth": {"s1.k1": 0.5}})
    with pytest.raises(SpecError) as err:
        simulate_run(sc, "calibration")
    model = SCENARIOS / "courier_platen_model.yaml"
    assert str(err.value) == (
        f"{display_path(model)}:24: columns.p1.solve: the readings p1, p2, p3, p4 did not "
        "converge: their equations have no single root near the start on some samples (a "
        "reading must be a monotonic function of the state: the equations' derivative by "
        "the readings must not vanish)")


# --------------------------------------------------------------------------- effects


def effect_delta(effects: dict, run: str = "calibration") -> tuple:
    """Readings with and without ``effects`` (true-position physics, same seed)."""
    plain = simulate_run(courier(errors=True), run, seed=7)
    with_effect = simulate_run(courier(errors=True, effects=effects), run, seed=7)
    for key in ("t", "x_ref", "y_ref", "theta_ref"):
        np.testing.assert_array_equal(plain[key], with_effect[key])
    return readings(with_effect) - readings(plain), with_effect


def test_lateral_effect_formula():
    values = {"s1.k9": 0.003, "s1.k10": -0.0015, "s2.k9": 0.0, "s2.k10": 0.0,
              "s3.k9": -0.002, "s3.k10": 0.001, "s4.k9": 0.0, "s4.k10": 0.0025}
    delta, data = effect_delta({"lateral": values})
    _, q = pinwheel(*true_pose(data))
    f = 2 * np.pi / RHO
    for i, s in enumerate(SEG):
        k9, k10 = values[f"{s}.k9"], values[f"{s}.k10"]
        expected = -(k9 * np.sin(f * q[:, i]) + k10 * np.cos(f * q[:, i]))
        np.testing.assert_allclose(delta[:, i], expected, rtol=0, atol=1e-13)
    assert np.max(np.abs(delta[:, 0])) > 0.002 and np.all(delta[:, 1] == 0)


def test_lateral_coordinate_is_eq9_argument_to_second_order():
    data = simulate_run(courier(), "calibration", seed=8)
    x, y, th = true_pose(data)
    _, q = pinwheel(x, y, th)
    eq9 = np.column_stack([y - L_O * th, x + L_O * th, y + L_O * th, x - L_O * th])
    assert np.max(np.abs(q - eq9)) < (L_S / 2) * (1.5 * DEG) ** 2  # (l_s/2)(1 - cos t) bound


def test_angle_effect_formula():
    values = {"s1.a": 0.2, "s2.a": -0.1, "s3.a": 0.0, "s3.b": 0.1, "s4.a": 0.05}
    delta, data = effect_delta({"angle": values})
    p_true, _ = pinwheel(*true_pose(data))
    th = data["theta_ref"]
    f = 2 * np.pi / RHO
    for i, s in enumerate(SEG):
        a, b = values[f"{s}.a"], values.get(f"{s}.b", 0.0)
        u = p_true[:, i] - K[s][0]  # tooth phase in the segment's counter frame
        expected = -(a * th + b * th * np.sin(f * u))
        np.testing.assert_allclose(delta[:, i], expected, rtol=0, atol=1e-13)
    assert np.max(np.abs(delta[:, 0])) > 0.003


def test_harmonics_effect_formula():
    values = {"s1.h3_sin": 0.002, "s1.h3_cos": -0.001, "s2.h3_sin": 0.0, "s2.h3_cos": 0.0004,
              "s3.h3_sin": 0.001, "s3.h3_cos": 0.0, "s4.h3_sin": 0.0, "s4.h3_cos": 0.0}
    delta, data = effect_delta({"harmonics": values})
    p_true, _ = pinwheel(*true_pose(data))
    f = 2 * np.pi / RHO
    for i, s in enumerate(SEG):
        u = p_true[:, i] - K[s][0]  # tooth phase in the segment's counter frame
        expected = -(values[f"{s}.h3_sin"] * np.sin(3 * f * u)
                     + values[f"{s}.h3_cos"] * np.cos(3 * f * u))
        np.testing.assert_allclose(delta[:, i], expected, rtol=0, atol=1e-13)
    assert np.max(np.abs(delta[:, 0])) > 0.002


def test_drift_effect_formula():
    delta, data = effect_delta({"drift": {"s1.rate": 1e-5}})
    t = data["t"]
    np.testing.assert_allclose(t, 0.1 * np.arange(400), rtol=0, atol=1e-12)
    np.testing.assert_allclose(delta[:, 0], -1e-5 * t, rtol=0, atol=1e-13)
    assert np.all(delta[:, 1:] == 0) and abs(delta[-1, 0]) > 3e-4


def test_pitch_variation_formula():
    waves = {"x": [(0.002, 7.3, 0.4), (0.001, 23.0, 0.0)], "y": [(0.0015, 5.9, -1.0),
                                                                (0.0, 17.5, 0.0)]}
    values = {f"w{axis}_{key}{j + 1}": wave[k] for axis, ws in waves.items()
              for j, wave in enumerate(ws) for k, key in enumerate("alp")}
    _, data = effect_delta({"pitch_variation": values}, run="flyby")
    p_true, _ = pinwheel(*true_pose(data))

    def w(axis, p):
        return sum(a * np.sin(2 * np.pi * p / lam + ph) for a, lam, ph in waves[axis])

    for i, s in enumerate(SEG):
        u = p_true[:, i] + w("x" if i % 2 == 0 else "y", p_true[:, i])
        np.testing.assert_allclose(data[f"p{i + 1}"], u - eq3(K[s], u - K[s][0]), rtol=0,
                                   atol=1e-12)
    # it shows as a position error against the interferometer of about the wave size
    y_err = (data["p2"] + data["p4"]) / 2 - data["y_ref"]
    plain = simulate_run(courier(errors=True), "flyby", seed=7)
    y_err_plain = (plain["p2"] + plain["p4"]) / 2 - plain["y_ref"]
    assert 0.0005 < np.std(y_err - y_err_plain) < 0.0015


# --------------------------------------------------------------------------- noise


def test_platen_noise_std_matches_sigma():
    sigma = 0.001
    changes = {"runs": {"calibration": {"scatter": {"n": 20000}}}}
    noisy = readings(simulate_run(courier(errors=True, sigma_p=sigma).overlay(changes),
                                  "calibration", seed=9))
    calm = readings(simulate_run(courier(errors=True).overlay(changes), "calibration", seed=9))
    z = noisy - calm
    # 80000 draws: the standard error of the std is sigma / sqrt(2 N) = 0.25 %; allow 2 %.
    assert abs(np.std(z) / sigma - 1) < 0.02
    assert abs(np.mean(z)) < 5 * sigma / math.sqrt(z.size)
    corr = np.corrcoef(z.T)
    assert np.max(np.abs(corr - np.eye(4))) < 0.05


def test_quantization_gives_multiples_of_the_step():
    q = 0.0002
    data = simulate_run(courier(errors=True, sigma_p=0.0005, step_p=q), "calibration",
                        seed=10)
    steps = readings(data) / q
    assert np.max(np.abs(steps - np.round(steps))) < 1e-6
    raw = readings(simulate_run(courier(errors=True, sigma_p=0.0005), "calibration", seed=10))
    assert np.max(np.abs(readings(data) - raw)) <= q / 2 + 1e-12
    assert np.max(np.abs(readings(data) - raw)) > q / 4


def test_noise_floor_is_the_propagated_noise():
    from symcal.experiment.predict import noise_floors
    from symcal.problem.build import load_problem

    sc = courier(sigma_p=0.0005, step_p=0.0002).overlay(
        {"runs": {"calibration": {"scatter": {"n": 20000}}}})
    s = math.sqrt(0.0005**2 + 0.0002**2 / 12)
    assert input_noise(sc)["p1"] == pytest.approx(s, rel=1e-12)
    assert input_noise(sc)["t"] == 0.0
    problem = load_problem(ROOT / "problems" / "platen_self_calibration.yaml")
    floors = noise_floors(problem, sc)
    assert floors["g_p_std"] == pytest.approx(2 * s, rel=1e-12)   # g_p is linear in p
    p = readings(simulate_run(sc, "calibration", seed=11))
    g_p = (p[:, 0] - p[:, 2]) - (p[:, 1] - p[:, 3])
    assert np.std(g_p) == pytest.approx(floors["g_p_std"], rel=0.03)


def test_coordination_and_reference_noise():
    changes = {"constants": {"sigma_psi": 0.0}, "design": None,
               "runs": {"calibration": {"scatter": {"n": 20000}}}}
    calm = load_scenario(DUAL).overlay(changes)
    noisy = calm.overlay({"constants": {"sigma_psi": 2e-5},
                          "columns": {"x_ref": {"noise": 1e-4}, "y_ref": {"noise": "0.1 um"},
                                      "theta_ref": {"noise": 1e-6}}})
    a = simulate_run(noisy, "calibration", seed=12)
    b = simulate_run(calm, "calibration", seed=12)
    for key, sigma in (("psi_x", 2e-5), ("psi_y", 2e-5), ("x_ref", 1e-4), ("y_ref", 1e-4),
                       ("theta_ref", 1e-6)):
        assert np.std(a[key] - b[key]) == pytest.approx(sigma, rel=0.03), key
    np.testing.assert_array_equal(a["p1"], b["p1"])    # the platen's stream is its own


# --------------------------------------------------------------------------- coordination


def eq11(data: dict, theta: np.ndarray, h=50.0, l_x=90.0, l_y=5.0, o_x=1.016, o_y=1.016):
    p = readings(data)
    px, py = (p[:, 0] + p[:, 2]) / 2, (p[:, 1] + p[:, 3]) / 2
    cx, cy = h * np.tan(data["psi_x"]), h * np.tan(data["psi_y"])
    c, s = np.cos(theta), np.sin(theta)
    g_x = -px + c * cx - s * cy - l_y * s + l_x * c + o_x
    g_y = -py + s * cx + c * cy + l_y * c + l_x * s + o_y
    return g_x, g_y


def _dual_quiet(**changes: Any):
    return quiet(load_scenario(DUAL).overlay({"truth": ZERO_K, "effects": None, **changes}))


def test_coordination_satisfies_eq11():
    small = _dual_quiet(expressions={"st": "theta", "cm": 0})
    data = simulate_run(small, "calibration", seed=13)
    p = readings(data)
    theta_hat = ((p[:, 0] - p[:, 2]) + (p[:, 1] - p[:, 3])) / (2 * L_S)  # eq. (4), averaged
    for g in eq11(data, theta_hat):
        np.testing.assert_allclose(g, 0.0, rtol=0, atol=1e-10)
    # exact geometry: eq. (11) holds with the true angle
    exact = simulate_run(_dual_quiet(), "flyby", seed=1)
    for g in eq11(exact, exact["theta_ref"]):
        np.testing.assert_allclose(g, 0.0, rtol=0, atol=1e-10)
    assert np.max(np.abs(data["psi_x"])) > 1e-3


def test_the_courier_turns_about_the_coordination_sensor():
    data = simulate_run(_dual_quiet(), "calibration", seed=14)
    x, y, th = true_pose(data)
    sx = x - (np.cos(th) * 90.0 - np.sin(th) * 5.0)
    sy = y - (np.sin(th) * 90.0 + np.cos(th) * 5.0)
    for s in (sx, sy):
        assert s.min() >= -1e-12 and s.max() <= 2.032 + 1e-12 and np.ptp(s) > 1.9
    # the coordination sensor stays under the beacon: c = R^T (s - o)
    cx = np.cos(th) * (sx - 1.016) + np.sin(th) * (sy - 1.016)
    np.testing.assert_allclose(np.tan(data["psi_x"]) * 50.0, cx, rtol=0, atol=1e-10)
    assert np.max(np.abs(data["psi_x"])) < 0.03


def test_an_effect_on_an_expression_sees_its_base_value():
    """A PSD nonlinearity, c -> c + n2 c^2 + n3 c^3: inside the term, c is the value
    before it."""
    plain = simulate_run(_dual_quiet(), "flyby", seed=2)
    psd = {"values": {"n2": 0.01, "n3": -0.002, "m3": 0.004},
           "add": {"cx": "n2*cx**2 + n3*cx**3", "cy": "m3*cy**3"}}
    data = simulate_run(_dual_quiet(effects={"psd": psd}), "flyby", seed=2)
    for axis, (n2, n3) in (("x", (0.01, -0.002)), ("y", (0.0, 0.004))):
        c = 50.0 * np.tan(plain[f"psi_{axis}"])
        expected = np.arctan((c + n2 * c**2 + n3 * c**3) / 50.0)
        np.testing.assert_allclose(data[f"psi_{axis}"], expected, rtol=0, atol=1e-13)
    assert np.max(np.abs(data["psi_y"] - plain["psi_y"])) > 1e-5


# --------------------------------------------------------------------------- seeds, API


def test_seeds_are_reproducible_and_streams_independent():
    base = load_scenario(DUAL)
    sc = base.overlay({"runs": {"twin": copy.deepcopy(
        yaml.safe_load(DUAL.read_text())["runs"]["calibration"])}})
    a, b = simulate_run(sc, "calibration", seed=5), simulate_run(sc, "calibration", seed=5)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    other = simulate_run(sc, "calibration", seed=6)
    assert not np.array_equal(a["x_ref"], other["x_ref"])
    twin = simulate_run(sc, "twin", seed=5)  # same motion, different run: different draws
    assert not np.array_equal(a["x_ref"], twin["x_ref"])
    # states do not depend on the noise settings (independent streams)
    calm = simulate_run(quiet(sc), "calibration", seed=5)
    np.testing.assert_array_equal(a["x_ref"], calm["x_ref"])
    np.testing.assert_array_equal(a["theta_ref"], calm["theta_ref"])
    # a shorter scatter is a prefix of a longer one
    short = simulate_run(sc, "calibration", seed=5, n=50)
    np.testing.assert_array_equal(short["p3"], a["p3"][:50])
    np.testing.assert_array_equal(short["psi_y"], a["psi_y"][:50])
    assert [(k, s) for k, s, _ in noise_streams(sc)] == [
        (1, "platen"), (2, "coordination"), (3, "reference")]


def test_columns_and_simulate():
    plain = simulate(courier(), seed=1, n=7)
    assert list(plain) == ["calibration", "flyby"]
    assert list(plain["flyby"]) == ["t", "p1", "p2", "p3", "p4", "x_ref", "y_ref", "theta_ref"]
    dual = simulate(load_scenario(DUAL))
    assert list(dual["calibration"]) == [
        "t", "p1", "p2", "p3", "p4", "psi_x", "psi_y", "x_ref", "y_ref", "theta_ref"]
    for data in (plain["calibration"], dual["flyby"]):
        for column in data.values():
            assert column.dtype == np.float64 and column.ndim == 1
    assert len(dual["flyby"]["t"]) == 400 and len(plain["calibration"]["p1"]) == 7
    line = simulate(courier())["flyby"]
    assert line["y_ref"][0] == pytest.approx(-14.92) and line["y_ref"][-1] == pytest.approx(25.08)
    assert np.std(line["theta_ref"]) == pytest.approx(0.01 * DEG, rel=0.25)


def test_bad_arguments():
    sc = courier()
    with pytest.raises(ValueError, match="n must be a whole number of at least 1, found 0"):
        simulate_run(sc, "calibration", n=0)
    with pytest.raises(ValueError, match="seed must be"):
        simulate_run(sc, "calibration", seed=-1)


@pytest.mark.slow
def test_one_million_poses():
    sc = load_scenario(PLATEN)
    data = simulate_run(sc, "calibration", seed=0, n=10**6)
    assert all(column.shape == (10**6,) for column in data.values())
    assert np.all(np.isfinite(data["p4"]))


# --------------------------------------------------------------------------- truth


def test_truth_names_and_values():
    info = truth(load_scenario(DUAL))
    params = info["parameters"]
    assert info["scenario"] == "courier_dual"
    assert params["s3.k4"] == K["s3"][4] and params["s1.k0"] == K["s1"][0]
    assert params["s2.k9"] == -0.002 and params["s2.k10"] == 0.0025
    assert [params[k] for k in ("h", "l_x", "l_y", "o_x", "o_y")] == [50, 90, 5, 1.016, 1.016]
    assert info["units"]["h"] == "mm" and "s1.k0" not in info["units"]
    assert len(params) == 4 * 11 + 5
    assert info["effects"]["lateral"]["on"]
    assert info["effects"]["lateral"]["adds"]["e1"] == "s1.k9*sin(f*L1) + s1.k10*cos(f*L1)"
    assert info["noise"] == {"p1": 0.001, "p2": 0.001, "p3": 0.001, "p4": 0.001,
                             "psi_x": 2e-5, "psi_y": 2e-5}
    assert info["quantization"]["p3"] == 0.0002
    assert yaml.safe_load(yaml.safe_dump(info)) == info
    plain = truth(courier())
    assert set(plain["parameters"]) == set(ZERO_K)
    assert not plain["effects"]["lateral"]["on"]


def g_p_std(data: dict) -> float:
    p = readings(data)
    return float(np.std((p[:, 0] - p[:, 2]) - (p[:, 1] - p[:, 3])))


def test_default_platen_scenario_magnitudes():
    sc = load_scenario(PLATEN)
    data = simulate(sc, seed=0)
    assert 0.025 < g_p_std(data["calibration"]) < 0.035  # paper 29.3 um
    assert 0.008 < g_p_std(data["flyby"]) < 0.016  # paper 12.1 um
    cal = data["calibration"]
    assert cal["x_ref"].min() >= 0 and cal["x_ref"].max() <= 10 * RHO
    assert np.max(np.abs(cal["theta_ref"])) <= 0.5 * DEG
    fly = data["flyby"]
    assert np.ptp(fly["y_ref"]) == pytest.approx(40.0)
    assert all(truth(sc)["effects"][e]["on"] for e in EFFECTS)


def test_default_dual_scenario():
    sc = load_scenario(DUAL)
    data = simulate(sc, seed=0)
    cal, fly = data["calibration"], data["flyby"]
    assert len(cal["t"]) == 1000 and np.max(np.abs(cal["theta_ref"])) <= 1.5 * DEG
    assert np.max(np.abs(cal["psi_x"])) < 0.03 and np.max(np.abs(cal["psi_y"])) < 0.03
    assert np.ptp(fly["y_ref"]) == pytest.approx(8.0, abs=0.01)
    assert input_noise(sc)["psi_x"] == 2e-5
    assert truth(sc)["parameters"]["l_x"] == 90.0


# --------------------------------------------------------------------------- any system

TOY = """\
scenario: toy
doc: a pendulum-like toy, only to test the language
constants:
  L: {value: 250, unit: mm}
  T: {value: 4, unit: s}
truth:
  gain: {value: 1.5, doc: a gain}
  c3: 0.2
states:
  angle: {unit: deg}
  temp: {unit: K, value: 300}
expressions:
  tip: {expr: L*sin(angle), unit: mm}
columns:
  t: t
  x: {expr: tip, unit: m, noise: 0.5 mm, quantization: 0.0001, stream: xs}
  a_ref: {expr: angle, unit: deg}
  r: {solve: r + c3*r**3 - gain*tip/L, start: 0, doc: a reading that solves a cubic}
  k: {expr: temp, unit: K}
effects:
  bias:
    values: {b: {value: 2, unit: mm}}
    add: {tip: b}
runs:
  calibration:
    dt: 0.5
    scatter: {n: 2000, angle: [-30, 30], dwell: 0.25}
  line:
    t0: 10
    line: {n: 5, from: {angle: -10}, to: {angle: 10}, temp: 280}
  held:
    dwells: {count: 6, samples: 4, angle: [0, 90]}
  swing:
    dt: 0.25
    series: {n: 9, angle: 20*sin(2*pi*t/T)}
design:
  run: calibration
  limits: {angle: [-45, 45], dwell: [0, 1], n: [10, 5000]}
"""


@pytest.fixture()
def toy(tmp_path):
    path = tmp_path / "toy.yaml"
    path.write_text(TOY)
    return load_scenario(path)


def test_a_scatter_draws_within_ranges_in_the_states_unit(toy):
    data = simulate_run(toy, "calibration", seed=1)
    angle = data["a_ref"]                               # written in deg, as declared
    assert angle.min() >= -30 and angle.max() <= 30 and np.ptp(angle) > 55
    ends = np.isclose(np.abs(angle), 30.0, rtol=1e-14, atol=0)
    assert np.mean(ends) == pytest.approx(0.25, abs=0.03)          # dwell share
    np.testing.assert_array_equal(data["k"], 300.0)                # held at its value
    np.testing.assert_allclose(data["t"], 0.5 * np.arange(2000))
    calm = simulate_run(quiet(toy), "calibration", seed=1)
    tip = 0.25 * np.sin(np.radians(angle)) + 0.002                 # m: L sin + bias
    np.testing.assert_allclose(calm["x"], tip, rtol=0, atol=1e-15)
    assert np.std(data["x"] - calm["x"]) == pytest.approx(
        math.sqrt(0.0005**2 + 0.0001**2 / 12), rel=0.05)           # 0.5 mm in m
    assert np.max(np.abs(data["x"] / 1e-4 - np.round(data["x"] / 1e-4))) < 1e-6
    # a solved reading: r + c3 r^3 = gain tip / L
    r = calm["r"]
    np.testing.assert_allclose(r + 0.2 * r**3, 1.5 * (tip * 1000) / 250, rtol=0, atol=1e-13)


def test_a_solved_reading_in_a_large_internal_unit_converges(tmp_path):
    """A turbine's pulse rate solved from its flow in L/min (1.7e4 mm³/s internally): the
    equation's rounding is of the size of its terms, far above the absolute tolerance, and
    even the linear equation 'did not converge'.  Solved, it is the closed form."""
    (tmp_path / "flow.yaml").write_text("""\
scenario: flow
constants:
  K: {value: 52.3, unit: 1/L}
  b: {value: 0.4, unit: L/min}
states:
  Q: {unit: L/min}
columns:
  q_ref: {expr: Q, unit: L/min}
  f: {solve: f/K + b + q*f**2 - Q, start: 100, unit: Hz}
truth:
  q: {value: 1.0e-6, unit: L/min/Hz**2}
runs:
  calibration:
    scatter: {n: 500, Q: [30, 190]}
""")
    data = simulate_run(load_scenario(tmp_path / "flow.yaml"), "calibration", seed=1)
    f, flow = data["f"], data["q_ref"]
    # f/K + q f² = Q - b, K in 1/L and the flow per minute: f/(K·60) in L/min
    a, bq = 1e-6 * 1.0, 1.0 / (52.3 / 60.0)
    closed = (-bq + np.sqrt(bq**2 + 4 * a * (flow - 0.4))) / (2 * a)
    np.testing.assert_allclose(f, closed, rtol=1e-11)


def test_lines_dwells_and_series(toy):
    line = simulate_run(toy, "line")
    np.testing.assert_allclose(line["a_ref"], [-10, -5, 0, 5, 10], atol=1e-12)
    np.testing.assert_allclose(line["t"], 10 + 0.1 * np.arange(5))
    np.testing.assert_array_equal(line["k"], 280.0)
    held = simulate_run(toy, "held", seed=3)["a_ref"]
    assert held.shape == (24,)
    blocks = held.reshape(6, 4)
    assert np.all(blocks == blocks[:, :1]) and len(set(blocks[:, 0])) == 6
    assert held.min() >= 0 and held.max() <= 90
    assert simulate_run(toy, "held", seed=3, n=10)["a_ref"].tolist() == held[:10].tolist()
    swing = simulate_run(toy, "swing")
    t = 0.25 * np.arange(9)
    np.testing.assert_allclose(swing["a_ref"], 20 * np.sin(2 * np.pi * t / 4), atol=1e-12)


def test_effects_switch_off_and_the_truth_lists_them(toy):
    info = truth(toy)
    assert info["parameters"] == {"gain": 1.5, "c3": 0.2, "b": 2.0}
    assert info["units"] == {"b": "mm"}
    assert info["effects"]["bias"] == {"on": True, "doc": "", "values": {"b": 2.0},
                                       "adds": {"tip": "b"}}
    off = toy.overlay({"effects": {"bias": {"on": False}}})
    assert "b" not in truth(off)["parameters"] and not truth(off)["effects"]["bias"]["on"]
    a = simulate_run(quiet(toy), "line")["x"]
    b = simulate_run(quiet(off), "line")["x"]
    np.testing.assert_allclose(a - b, 0.002, rtol=1e-9)


def test_slips_are_glitches_of_a_share_of_the_rows(toy):
    sc = toy.overlay({"effects": {"glitch": {"slips": {"x": {"fraction": 0.1, "size": "1 mm"},
                                                       "a_ref": {"fraction": 0.0,
                                                                 "size": 1}}}}})
    rows = slipped_rows(sc, "calibration", seed=4)
    assert set(rows) == {"x", "a_ref"} and rows["a_ref"] == []
    assert 150 < len(rows["x"]) < 250
    jump = simulate_run(sc, "calibration", seed=4)["x"] - simulate_run(
        toy, "calibration", seed=4)["x"]
    np.testing.assert_allclose(np.abs(jump[rows["x"]]), 0.001, rtol=1e-9)
    assert np.count_nonzero(jump) == len(rows["x"])
    assert slipped_rows(sc, "calibration", 4, 300)["x"] == [r for r in rows["x"] if r < 300]
    assert truth(sc, seed=4)["effects"]["glitch"]["rows"]["calibration"]["x"] == rows["x"]


BAD = [
    ("tip: {expr: L*sin(angle), unit: mm}", "tip: {expr: L*sin(angel), unit: mm}",
     ":13: expressions.tip.expr: unknown symbol 'angel' (did you mean 'angle'?)"),
    ("tip: {expr: L*sin(angle), unit: mm}", "tip: {expr: L*sin(angle) + T, unit: mm}",
     ":13: expressions.tip.expr: cannot add 'L*sin(angle)' (mm, a length) and 'T' (s, a "
     "time)"),
    ("tip: {expr: L*sin(angle), unit: mm}", "tip: {expr: L*sin(angle), unit: s}",
     ":13: expressions.tip.expr: 'tip' is declared in s, a time but its expression is mm, "
     "a length"),
    ("tip: {expr: L*sin(angle), unit: mm}", "tip: {expr: L*sin(angle) + 0*tip2, unit: mm}\n"
     "  tip2: tip", ":14: expressions.tip2: 'tip' refers to itself: tip -> tip2 -> tip"),
    ("add: {tip: b}", "add: {tipp: b}",
     ":23: effects.bias.add.tipp: effect 'bias' adds to 'tipp', which is no expression or "
     "'expr' column (did you mean 'tip'?)"),
    ("start: 0,", "start: r,", ":18: columns.r.start: a start must not depend on the "
                               "readings being solved for"),
    ("{n: 2000, angle: [-30, 30], dwell: 0.25}", "{n: 2000, angel: [-30, 30]}",
     ":27: runs.calibration.scatter.angel: unknown key 'angel' (did you mean 'angle'?); a "
     "scatter takes n, dwell, dwell_at and the states (angle, temp)"),
    ("{n: 2000, angle: [-30, 30], dwell: 0.25}", "{n: 2000}",
     ":27: runs.calibration.scatter: state 'angle' is not given: give a range [lo, hi] or "
     "a value, or a 'value' in 'states'"),
    ("{n: 2000, angle: [-30, 30], dwell: 0.25}", "{n: 2000, angle: [30, -30]}",
     ":27: runs.calibration.scatter.angle: expected lo <= hi, found [30, -30]"),
    ("  temp: {unit: K, value: 300}", "  t: {unit: K, value: 300}",
     ":11: states.t: 't' cannot name a state: the time of each sample is the built-in "
     "state 't'"),
    ("noise: 0.5 mm", "noise: 0.5 s", ":16: columns.x.noise: noise: '0.5 s' is not in a unit "
                                      "of the column, which is in 'm'"),
    ("noise: 0.5 mm", "noise: sigma", ":16: columns.x.noise: noise: unknown symbol "),
    ("  r: {solve:", "  r: {expr: tip, solve:",
     ":18: columns.r: a column needs exactly one of 'expr' (its reading) or 'solve' (an "
     "equation its reading makes vanish); found 'expr' and 'solve'"),
    ("limits: {angle: [-45, 45]", "limits: {angle: [-20, 45]",
     ":38: design.limits.angle: run 'calibration' has angle [-30, 30], outside its limits "
     "[-20, 45]"),
    ("run: calibration\n  limits", "run: line\n  limits",
     ":37: design.run: run 'line' is a line; only a scatter or dwells run can be designed"),
    ("dwell: [0, 1]", "dwell: [0, 2]",
     ":38: design.limits.dwell: dwell is a share of the draws: its limits must lie within "
     "[0, 1], found [0, 2]"),
    ("n: [10, 5000]", "n: [10.5, 5000]", ":38: design.limits.n: n's limits must be whole "
                                         "numbers from 1 to"),
    ("limits: {angle: [-45, 45]", "limits: {speed: [1, 2]",
     ":38: design.limits.speed: unknown key 'speed'; allowed keys: angle, dwell, n"),
    ("series: {n: 9, angle: 20*sin(2*pi*t/T)}", "series: {n: 9, angle: 20*sin(2*pi*t/T) + L}",
     ":35: runs.swing.series.angle: cannot add '20.0*sin(2.0*pi*t/T)' (dimensionless) and "
     "'L' (mm, a length)"),
]


@pytest.mark.parametrize(("old", "new", "message"), BAD)
def test_bad_scenarios_are_refused_with_file_line_and_key(tmp_path, old, new, message):
    assert old in TOY
    path = tmp_path / "toy.yaml"
    path.write_text(TOY.replace(old, new, 1))
    with pytest.raises(SpecError) as err:
        load_scenario(path)
    assert str(err.value).startswith(f"{display_path(path)}{message}"), str(err.value)


def test_the_toy_is_valid_and_unknown_runs_are_named(toy):
    assert toy.run_names == ("calibration", "line", "held", "swing")
    with pytest.raises(SpecError, match=r"no run named 'calbration' \(did you mean "
                                        r"'calibration'\?\); runs: calibration, line"):
        simulate_run(toy, "calbration")


TURNTABLE = """scenario: turntable
constants:
  P1: {value: 40, unit: s}
  A: {value: 400, unit: deg}
states:
  theta: {unit: deg}
  omega: {unit: OMEGA}
columns:
  t: {expr: t, unit: s}
  theta_ref: {expr: theta, unit: deg}
  omega_ref: {expr: omega, unit: OMEGA}
runs:
  calibration:
    dt: 0.01
    series: {n: 3, theta: 400*sin(2*pi*t/P1), omega: RATE}
"""


def test_a_series_rate_without_its_angle_is_refused(tmp_path) -> None:
    """A new user's turntable: the angle written as a plain number (read in deg) and its
    rate with no angle in it (1/s, read as rad/s) made the rate 57 times too large,
    silently; it is refused, with the fix.  With the angle's unit, or in rad/s, it is
    read as written."""
    def scenario(omega: str, rate: str) -> Path:
        path = tmp_path / f"s{abs(hash((omega, rate)))}.yaml"
        path.write_text(TURNTABLE.replace("OMEGA", omega).replace("RATE", rate))
        return path

    with pytest.raises(SpecError) as err:
        simulate_run(load_scenario(scenario("deg/s", "400*(2*pi/P1)*cos(2*pi*t/P1)")),
                     "calibration", seed=0)
    assert str(err.value).split(": ", 1)[1] == (
        "runs.calibration.series.omega: state 'omega' is in deg/s but its expression is in "
        "1/s, which has no angle in it: it would be read as radians (57.3 deg/s per 1/s). "
        "Give the expression its angle (a constant with an angle unit, e.g. A: {value: "
        "400, unit: deg}), or write a plain number in deg/s")
    good = simulate_run(load_scenario(scenario("deg/s", "A*(2*pi/P1)*cos(2*pi*t/P1)")),
                        "calibration", seed=0)
    assert good["omega_ref"][0] == pytest.approx(400 * 2 * np.pi / 40)
    rad = simulate_run(load_scenario(scenario("rad/s", "(2*pi/P1)*cos(2*pi*t/P1)")),
                       "calibration", seed=0)
    assert rad["omega_ref"][0] == pytest.approx(2 * np.pi / 40)
