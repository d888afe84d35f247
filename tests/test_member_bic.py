"""The members of a group that pay are ranked by BIC before their held-out spreads (a
new user's drone altimeter, a warm day: the barometer's reference temperature T0 is
10 K off).  By the held-out spreads alone the loop kept a quadratic in the GNSS height,
which scales its 0.5 m noise down in every residual: quiet, with laser.k 484 and hg 11
standard errors from the truth.  T0 (one parameter, its BIC lower by 6) is the effect.
A term linear in the GNSS height fits as well as T0 (BIC equal): GNSS is the problem's
reference (its one parameter fixed), and a calibrated sensor's term is kept before it."""

from __future__ import annotations

import re

import pytest

import symcal

FILES = {
    'baro.yaml': """\
model: baro
doc: >
  Barometric altimeter: altitude from static pressure by the standard-atmosphere
  formula h = T0/L * (1 - (p/p0)^n), p0 the reference (sea-level) pressure, which
  drifts with the weather and is calibrated.
constants:
  T0: {value: 288.15, unit: K, doc: reference temperature at sea level}
  L: {value: 0.0065, unit: K/m, doc: temperature lapse rate}
  n: {value: 0.190263, doc: exponent R*L/(g*M)}
inputs:
  p: {unit: hPa, doc: static pressure reading}
parameters:
  p0: {value: 1013.25, unit: hPa, scale: 1, doc: reference pressure (QNH)}
outputs:
  h: {expr: T0/L*(1 - (p/p0)**n), unit: m, doc: barometric altitude AMSL}
""",
    'gnss.yaml': """\
model: gnss
doc: GNSS receiver altitude with a constant datum offset d (h_read = h + d).
inputs:
  hr: {unit: m, doc: GNSS altitude reading}
parameters:
  d: {value: 0, unit: m, scale: 1, doc: datum offset}
outputs:
  h: {expr: hr - d, unit: m, doc: altitude AMSL}
""",
    'laser.yaml': """\
model: laser
doc: Downward laser rangefinder with a scale error k (height above ground = k * range).
inputs:
  r: {unit: m, doc: range reading}
parameters:
  k: {value: 1, scale: 1, doc: scale factor}
outputs:
  agl: {expr: k*r, unit: m, doc: height above ground}
""",
    'problem.yaml': """\
problem: altitude
doc: Drone altitude three ways; every parameter free, as a new user first writes it.
columns:
  t: {unit: s, role: time}
  p_baro: {unit: hPa, noise: 0.02 hPa, doc: barometer pressure}
  h_gnss: {unit: m, noise: 0.5 m, doc: GNSS altitude}
  r_laser: {unit: m, noise: 0.05 m, doc: laser range}
  pitch: {unit: deg, role: state, doc: drone pitch}
parameters:
  hg: {value: 100, unit: m, scale: 10, doc: ground height AMSL}
instances:
  baro: {model: baro.yaml, inputs: {p: p_baro}}
  gnss: {model: gnss.yaml, inputs: {hr: h_gnss}}
  laser: {model: laser.yaml, inputs: {r: r_laser}}
constraints:
  g_baro: {expr: baro.h - gnss.h, unit: m, doc: baro and GNSS agree}
  g_laser: {expr: hg + laser.agl - gnss.h, unit: m, doc: laser and GNSS agree}
datasets:
  calibration: {simulate: scenario.yaml, run: calibration, seed: 1}
  validation: {simulate: scenario.yaml, run: validation, seed: 1}
""",
    'problem_fixed.yaml': """\
problem: altitude_fixed
extends: problem.yaml
doc: GNSS datum offset known from the geoid model (2.5 m); p0, k and hg calibrated.
instances:
  gnss: {parameters: {d: {value: 2.5, fixed: true}}}
""",
    'scenario.yaml': """\
scenario: altitude
doc: a drone flying up and down over flat ground of height hg
constants:
  T0: {value: 288.15, unit: K}
  L: {value: 0.0065, unit: K/m}
  n: {value: 0.190263}
  Ac: {value: 70, unit: m}
  Av: {value: 40, unit: m}
  Pc: {value: 120, unit: s}
  Pv: {value: 50, unit: s}
  Pp: {value: 9, unit: s}
  Pq: {value: 6, unit: s}
truth:
  baro.p0: {value: 1008.0, unit: hPa}
  gnss.d: {value: 2.5, unit: m}
  laser.k: 1.01
  hg: {value: 120, unit: m}
states:
  agl: {unit: m}
  vz: {unit: m/s}
  pitch: {unit: deg}
expressions:
  h: {expr: hg + agl, unit: m}
  p0t: {expr: baro.p0, unit: hPa}
  T0t: {expr: T0, unit: K}
columns:
  t: {expr: t, unit: s}
  p_baro: {expr: p0t*(1 - L*h/T0t)**(1/n), unit: hPa, noise: 0.02 hPa}
  h_gnss: {expr: h + gnss.d, unit: m, noise: 0.5 m}
  r_laser: {expr: agl/laser.k, unit: m, noise: 0.05 m}
  pitch: {expr: pitch, unit: deg, noise: 0.1 deg}
  h_ref: {expr: h, unit: m}
effects:
  warm_day:
    on: true
    values: {dT0: {value: 10, unit: K}}
    add: {T0t: dT0}
runs:
  calibration:
    dt: 0.1
    series:
      n: 3000
      agl: 80 - 70*cos(2*pi*t/Pc)
      vz: Ac*2*pi/Pc*sin(2*pi*t/Pc)
      pitch: 8*sin(2*pi*t/Pp)
  validation:
    dt: 0.1
    series:
      n: 1500
      agl: 50 - 40*cos(2*pi*t/Pv)
      vz: Av*2*pi/Pv*sin(2*pi*t/Pv)
      pitch: 12*sin(2*pi*t/Pq)
""",
}
TRUTH = {"laser.k": 1.01, "baro.p0": 1008.0, "hg": 120.0}


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_the_effect_is_kept_not_a_stand_in_that_scales_a_noisy_reading(tmp_path,
                                                                       seed: int) -> None:
    for name, text in FILES.items():
        (tmp_path / name).write_text(text.replace("seed: 1", f"seed: {seed}"))
    result = symcal.improve(tmp_path / "problem_fixed.yaml", tmp_path / "out")
    assert result.quiet
    assert [r.added for r in result.rounds[1:]] in (
        ["baro's reference temperature at sea level T0 is off"],
        ["baro's temperature lapse rate L is off"])     # the same fit: T0/L is one scale
    params = result.rounds[-1].result.params
    for name, truth in TRUTH.items():
        assert abs(params[name].value - truth) < 4 * params[name].se, name
    # a stand-in in the reference's noisy reading paid too (a term linear or quadratic
    # in h_gnss, whichever of the group was tried), and is named as what the data alone
    # cannot rule out
    assert any(re.search(r"cannot tell .* from gnss\.h \+= a (term linear in|quadratic "
                         r"dependence on) h_gnss", note)
               for note in result.rounds[-1].notes())
