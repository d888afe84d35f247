"""A delay read through the rate of a noisy column is not attenuated (errors in
variables): a new user's drone, its GNSS height (0.5 m noise at 10 Hz) 0.3 s late; the
central differences' rate was mostly noise and the delay fitted 0.10 s."""

from __future__ import annotations

import numpy as np
import pytest
from test_member_bic import FILES

import symcal
from symcal.data.derived import ATTENUATION, rate, rate_and_noise


def _climb(n: int = 3000, dt: float = 0.1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.arange(n) * dt
    return t, 80 - 70 * np.cos(2 * np.pi * t / 120), 70 * 2 * np.pi / 120 * np.sin(
        2 * np.pi * t / 120)


@pytest.mark.parametrize("sigma", [0.05, 0.5, 2.0])
def test_the_rate_of_a_noisy_column_is_not_attenuated(sigma: float) -> None:
    t, h, vz = _climb()
    rng = np.random.default_rng(3)
    noisy = h + rng.normal(0, sigma, len(t))
    smooth = rate(noisy, t, sigma)
    central = np.gradient(noisy, t)
    # the slope of the truth on the rate: what a fitted delay is multiplied by
    att = float(np.cov(vz, smooth)[0, 1] / np.var(smooth))
    assert 1 - 3 * ATTENUATION < att < 1 + 3 * ATTENUATION
    if sigma >= 0.5:
        assert float(np.cov(vz, central)[0, 1] / np.var(central)) < 0.5


def test_without_declared_noise_the_rate_is_central_differences() -> None:
    t, h, _ = _climb(200)
    t = t + np.random.default_rng(4).uniform(0, 0.05, len(t))     # uneven steps
    np.testing.assert_array_equal(rate(h, t), np.gradient(h, t, edge_order=1))
    np.testing.assert_array_equal(rate(h, t, 0.0), np.gradient(h, t, edge_order=1))
    # a small declared noise leaves a smooth column's central differences
    np.testing.assert_array_equal(rate(h, t, 1e-6), np.gradient(h, t, edge_order=1))


@pytest.mark.parametrize("sigma", [0.0005, 0.05, 0.5])
def test_the_noise_a_rate_carries_is_what_its_noise_leaves(sigma: float) -> None:
    """The stated root mean square of a rate's noise is the spread of the difference of
    two draws' rates over √2, on 20 pairs (central differences: sigma/(√2 dt) exactly;
    smoothed where the noise would dominate: less)."""
    t, h, _ = _climb()
    rng = np.random.default_rng(5)
    diffs, stated = [], set()
    for _ in range(20):
        one, s1 = rate_and_noise(h + rng.normal(0, sigma, len(t)), t, sigma)
        two, s2 = rate_and_noise(h + rng.normal(0, sigma, len(t)), t, sigma)
        diffs.append(one - two)
        stated |= {s1, s2}
    assert len(stated) == 1          # the same window on every draw
    spread = float(np.sqrt(np.mean(np.square(diffs)) / 2))
    assert spread == pytest.approx(stated.pop(), rel=0.05)
    if sigma == 0.0005:              # central differences
        assert spread == pytest.approx(sigma / (np.sqrt(2) * 0.1), rel=0.05)
    assert rate_and_noise(h, t)[1] == 0.0


LATE = FILES["scenario.yaml"].replace("""  warm_day:
    on: true
    values: {dT0: {value: 10, unit: K}}
    add: {T0t: dT0}
""", """  gnss_latency:
    on: true
    values: {gnss.tau: {value: 0.3, unit: s}}
    add: {h_gnss: -gnss.tau*vz}
""")


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 3])
def test_a_late_gnss_is_found_with_its_whole_delay(tmp_path, seed: int) -> None:
    assert LATE != FILES["scenario.yaml"]
    for name, text in {**FILES, "scenario.yaml": LATE}.items():
        (tmp_path / name).write_text(text.replace("seed: 1", f"seed: {seed}"))
    result = symcal.improve(tmp_path / "problem_fixed.yaml", tmp_path / "out")
    assert result.quiet
    assert [r.added for r in result.rounds[1:]] == [
        "gnss's readings (h_gnss) lag by a constant delay"]
    tau = result.rounds[-1].result.params["tau_gnss"]
    assert abs(tau.value - 0.3) < 4 * tau.se and tau.se < 0.01
    rate_column = (tmp_path / "out" / "problem_fixed_round1.yaml").read_text()
    assert "h_gnss_rate: {rate_of: h_gnss" in rate_column
    # its noise declared as what the GNSS's 0.5 m leaves in the smoothed rate (neglected,
    # a gyro's 4 ms delay ended 4 % above its floor: the rate of its 0.05 deg/s noise at
    # 100 Hz carries 3.5 deg/s², 14 mdeg/s times the delay)
    assert "its noise is what h_gnss's declared noise leaves in a rate" in rate_column
    declared = symcal.load_problem(tmp_path / "out" / "problem_fixed_round1.yaml")
    noise = declared.column_specs["h_gnss_rate"].noise
    assert noise is not None and noise.unit == "m/s"      # smoothed: below central diffs
    assert 0 < noise.value < 0.5 / (np.sqrt(2) * 0.1)


@pytest.mark.slow
def test_design_predicts_a_problem_with_a_rate_column(tmp_path) -> None:
    """`symcal design` computes the columns a problem derives (``rate_of``) on the run it
    simulates, as a solve does (it refused: "missing column 'h_gnss_rate'"), and predicts
    the delay's standard error the solve states (within 20 %)."""
    from symcal.experiment.predict import predict
    from symcal.simulation import load_scenario

    for name, text in {**FILES, "scenario.yaml": LATE}.items():
        (tmp_path / name).write_text(text)
    result = symcal.improve(tmp_path / "problem_fixed.yaml", tmp_path / "out")
    revised = symcal.load_problem(tmp_path / "out" / "problem_fixed_round1.yaml")
    predicted = predict(revised, load_scenario(tmp_path / "scenario.yaml"), "calibration")
    stated = result.rounds[-1].result.params["tau_gnss"].se
    assert predicted.se["tau_gnss"] == pytest.approx(stated, rel=0.2)
