"""A candidate tested beyond its simpler terms sees the data: a simpler term that the
parameters absorb (a reference shunt's linear term in its own reading, its scale taken
by a Hall sensor's sensitivity) is left out of what it is tested beyond.  Evaluated at
the adjusted reading, what the parameters leave of that term is the reading's share of
the residual itself, and normalised it took the residual away: a new user's shunt
product with the temperature had the same F (7.96) on data with and without the Hall
sensor's temperature effect."""

from __future__ import annotations

import numpy as np
from test_reference_term import write_bench

import symcal
from symcal.data.dataset import make_dataset

LABEL = "sh.I += the product of v_sh and T"


def _product(tmp_path, effect: float):
    write_bench(tmp_path)
    rng = np.random.default_rng(5)
    n = 3000
    t = np.arange(n, dtype=float)
    current = 40 * np.sin(2 * np.pi * t / 300) + 9 * np.sin(2 * np.pi * t / 23)
    temp = 32.5 - 12.5 * np.cos(2 * np.pi * t / 2400)
    columns = {"t": t, "T": temp + rng.normal(0, 0.05, n),
               "v_sh": current * (1 + 5e-5 * (temp - 25)) + rng.normal(0, 0.01, n),
               "v_hall": 2.5 + 0.0398 * current * (1 + effect * (temp - 25))
               + rng.normal(0, 0.005, n)}
    data = {"calibration": make_dataset("calibration", "test", columns, [])}
    diag = symcal.diagnose(symcal.solve(tmp_path / "bench.yaml", data))
    return next(c for c in diag.candidates if c.label == LABEL)


def test_a_product_is_tested_beyond_what_its_simpler_terms_see(tmp_path) -> None:
    clean = _product(tmp_path, 0.0)
    warm = _product(tmp_path, -6e-4)          # the Hall sensitivity's tempco
    assert not clean.significant and clean.f_stat < 10
    assert warm.significant and warm.f_stat > 100 * clean.f_stat, (warm.f_stat,
                                                                   clean.f_stat)
