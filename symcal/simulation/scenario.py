"""Scenario files of the courier simulator: YAML -> validated, frozen dataclasses.

A scenario states the *true* sensors of a simulated courier (Quaid & Rizzi, §2-3.2) and
the motions ("runs") to record.  Units are mm, rad and s throughout; angles of motions
are written in degrees (keys ending in ``_deg``) and stored in radians.

Schema (``*`` marks a required key; every other key has the default shown)::

    scenario*: NAME                   # plain name
    doc: TEXT
    platen*:
      pitch: 1.016                    # tooth pitch rho (mm); f = 2 pi / rho
      l_s: 9.7                        # distance between the segments of a pair (mm)
      l_o: 4.85                       # offset of each segment along its own axis (mm)
      distortion_at: true_position    # or: reading   (where eq. 3 is evaluated)
      geometry: exact                 # or: small_angle (sin t -> t, cos t -> 1)
      noise: 0.0001                   # Gaussian sigma of each reading (mm)
      quantization: 0.0002            # reading step (mm); 0 disables
      segments*:                      # eq. (3) coefficients (mm); missing k's are 0
        s1*: {k0: 0, k1: 0, ..., k8: 0}
        s2*: {...}
        s3*: {...}
        s4*: {...}
      effects:                        # each one off unless present; listed segments only
        lateral:         {s1: {k9: 0, k10: 0}, ...}               # mm, eq. (9) phase
        angle:           {s1: {a: 0, b: 0, c: 0}, ...}             # mm/rad
        harmonics:       {s1: [{n*: 3, sin: 0, cos: 0}, ...], ...}  # mm
        drift:           {s1: {rate: 0, quadratic: 0}, ...}         # mm/s, mm/s^2
        pitch_variation: {x: [{amplitude*: .., wavelength*: .., phase: 0}, ...], y: [...]}
        count_slips:     {s1: {fraction*: 0.01}, ...}  # readings off by +-pitch/4 (glitches)
    coordination:                     # optional: the coordination sensor (eq. 10-11)
      h*: ..                          # height of the beacon above the PSD (mm)
      l_x*: ..                        # body offset coordination sensor -> platen sensor (mm)
      l_y*: ..
      o_x*: ..                        # beacon position in platen coordinates (mm)
      o_y*: ..
      noise: 0                        # Gaussian sigma of psi_x and psi_y (rad)
      nonlinearity:                   # PSD gain and nonlinearity: c + g c + n2 c^2 + n3 c^3
        x: {g: 0, n2: 0, n3: 0}       # 1, 1/mm, 1/mm^2 (per axis)
        y: {g: 0, n2: 0, n3: 0}
    reference:                        # interferometer ground truth
      position_noise: 0               # sigma of x_ref, y_ref (mm)
      angle_noise: 0                  # sigma of theta_ref (rad)
    runs*:                            # one or more, in order (the order seeds the streams)
      NAME:
        dt: 0.1                       # time step between samples (s)
        t0: 0                         # time of the first sample (s)
        doc: TEXT
        scatter:                      # exactly one of scatter / line
          n*: 1000
          x*: [lo, hi]                # mm
          y*: [lo, hi]                # mm
          theta_deg*: [lo, hi]        # degrees
          rotate_about: platen        # or: coordination
          dwell: 0                    # share of poses at the ends of the theta range
        line:
          n*: 400
          from*: [x, y]               # mm
          to*: [x, y]                 # mm
          theta_deg: 0                # constant angle (degrees)
          theta_jitter_deg: 0         # sigma of Gaussian jitter on theta (degrees)
          rotate_about: platen        # or: coordination

    design:                           # optional: what ``symcal design`` may change
      run*: NAME                      # a scatter run
      doc: TEXT
      limits*:                        # each listed motion parameter may change within
        x: [lo, hi]                   #   its limits (mm); unlisted ones stay as written
        y: [lo, hi]                   # mm
        theta_deg: [lo, hi]           # degrees
        dwell: [lo, hi]               # within [0, 1]
        n: [lo, hi]                   # whole numbers of observations

``dwell: w`` makes a share ``w`` of a scatter's poses dwell at the two ends of its
``theta_deg`` range (half at each; drawn from a stream of their own, so the positions stay
those of the same scatter without dwell); the rest turn uniformly over the range.  A
``design`` section declares the courier's limits: the motion the run describes must lie
within them.

``rotate_about: coordination`` (needs a ``coordination`` section) means that the sampled
or interpolated ``(x, y)`` are the world position ``s`` of the coordination sensor's
centre, about which the courier turns; the platen-sensor pose that every column refers to
is then ``(x, y) = s + R(theta) (l_x, l_y)``.  The coordination sensor sits under the
beacon (``c = 0``) when ``s = (o_x, o_y)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import SpecError, Where
from symcal.language.fields import (
    MAX_SAMPLES,
    check_keys,
    child_where,
    expect_int,
    expect_list,
    expect_map,
    expect_name,
    expect_number,
    expect_str,
)
from symcal.language.overlay import load_with_extends, merge_scenario
from symcal.language.yamlio import YMap

SEGMENT_NAMES: tuple[str, ...] = ("s1", "s2", "s3", "s4")
FOURIER_KEYS: tuple[str, ...] = tuple(f"k{j}" for j in range(9))
DISTORTION_MODES: tuple[str, ...] = ("true_position", "reading")
GEOMETRIES: tuple[str, ...] = ("exact", "small_angle")
PIVOTS: tuple[str, ...] = ("platen", "coordination")
EFFECT_NAMES: tuple[str, ...] = ("lateral", "angle", "harmonics", "drift", "pitch_variation",
                                 "count_slips")
#: The motion parameters of a scatter run that a ``design`` section may let change.
DESIGN_KEYS: tuple[str, ...] = ("x", "y", "theta_deg", "dwell", "n")

DEFAULT_PITCH = 1.016
DEFAULT_L_S = 9.7
DEFAULT_L_O = 4.85
DEFAULT_NOISE = 1e-4
DEFAULT_QUANTIZATION = 2e-4
DEFAULT_DT = 0.1


# --------------------------------------------------------------------------- dataclasses


@dataclass(frozen=True)
class Lateral:
    """Lateral dependence of one segment: ``k9 sin(f q) + k10 cos(f q)`` (mm)."""

    k9: float = 0.0
    k10: float = 0.0


@dataclass(frozen=True)
class AngleTerm:
    """Angle dependence of one segment: ``a t + b t sin(f u) + c t cos(f u)`` (mm/rad)."""

    a: float = 0.0
    b: float = 0.0
    c: float = 0.0


@dataclass(frozen=True)
class Harmonic:
    """One extra harmonic of the tooth error: ``sin sin(n f u) + cos cos(n f u)`` (mm)."""

    n: int
    sin: float = 0.0
    cos: float = 0.0


@dataclass(frozen=True)
class Drift:
    """Slow drift of one segment in time: ``rate t + quadratic t^2`` (mm/s, mm/s^2)."""

    rate: float = 0.0
    quadratic: float = 0.0


@dataclass(frozen=True)
class Wave:
    """One sinusoid of the tooth-pitch variation: ``amplitude sin(2 pi p / wavelength + phase)``."""

    amplitude: float
    wavelength: float
    phase: float = 0.0


@dataclass(frozen=True)
class PitchVariation:
    """Tooth-pitch variation along the platen, per axis: ``w(p) = sum of waves``."""

    x: tuple[Wave, ...] = ()
    y: tuple[Wave, ...] = ()


@dataclass(frozen=True)
class CountSlip:
    """Quadrature count slips of one segment: on a share ``fraction`` of the observations,
    drawn at random, its reading is off by a quarter pitch (either sign), a glitch of
    that one observation."""

    fraction: float = 0.0


@dataclass(frozen=True)
class Effects:
    """The switchable effects; ``None`` means off, otherwise one entry per segment s1..s4."""

    lateral: tuple[Lateral, ...] | None = None
    angle: tuple[AngleTerm, ...] | None = None
    harmonics: tuple[tuple[Harmonic, ...], ...] | None = None
    drift: tuple[Drift, ...] | None = None
    pitch_variation: PitchVariation | None = None
    count_slips: tuple[CountSlip, ...] | None = None

    def active(self) -> tuple[str, ...]:
        """Names of the effects that are switched on."""
        return tuple(name for name in EFFECT_NAMES if getattr(self, name) is not None)


@dataclass(frozen=True)
class Platen:
    """The true platen sensor: geometry, eq. (3) coefficients, effects and noise."""

    segments: tuple[tuple[float, ...], ...]
    pitch: float = DEFAULT_PITCH
    l_s: float = DEFAULT_L_S
    l_o: float = DEFAULT_L_O
    distortion_at: str = "true_position"
    geometry: str = "exact"
    noise: float = DEFAULT_NOISE
    quantization: float = DEFAULT_QUANTIZATION
    effects: Effects = field(default_factory=Effects)
    where: Where = field(default=Where("<scenario>"), compare=False)


@dataclass(frozen=True)
class AxisNonlinearity:
    """PSD gain error and nonlinearity of one axis: ``c -> c + g c + n2 c^2 + n3 c^3``
    (``g`` dimensionless, ``n2`` 1/mm, ``n3`` 1/mm^2)."""

    n2: float = 0.0
    n3: float = 0.0
    g: float = 0.0


@dataclass(frozen=True)
class Coordination:
    """The true coordination sensor and beacon (eq. 10-11)."""

    h: float
    l_x: float
    l_y: float
    o_x: float
    o_y: float
    noise: float = 0.0
    nonlinearity: tuple[AxisNonlinearity, AxisNonlinearity] | None = None


@dataclass(frozen=True)
class Reference:
    """The interferometer ground truth: Gaussian noise on position (mm) and angle (rad)."""

    position_noise: float = 0.0
    angle_noise: float = 0.0


@dataclass(frozen=True)
class Scatter:
    """``n`` poses drawn uniformly over ``x`` x ``y`` x ``theta`` (mm, mm, rad); a share
    ``dwell`` of them at the two ends of the ``theta`` range instead."""

    n: int
    x: tuple[float, float]
    y: tuple[float, float]
    theta: tuple[float, float]
    rotate_about: str = "platen"
    dwell: float = 0.0


@dataclass(frozen=True)
class Line:
    """``n`` poses evenly spaced from ``start`` to ``end`` at angle ``theta`` (rad)."""

    n: int
    start: tuple[float, float]
    end: tuple[float, float]
    theta: float = 0.0
    theta_jitter: float = 0.0
    rotate_about: str = "platen"


@dataclass(frozen=True)
class Run:
    """One named motion and its clock."""

    name: str
    motion: Scatter | Line
    dt: float = DEFAULT_DT
    t0: float = 0.0
    doc: str = ""


@dataclass(frozen=True)
class DesignSpace:
    """What ``symcal design`` may change: the motion parameters of one scatter run and
    their limits (``x``, ``y`` in mm, ``theta_deg`` in degrees, ``dwell``, ``n``)."""

    run: str
    limits: tuple[tuple[str, tuple[float, float]], ...]
    doc: str = ""
    where: Where = field(default=Where("<scenario>"), compare=False)

    @property
    def bounds(self) -> dict[str, tuple[float, float]]:
        """The limits by motion parameter (``DESIGN_KEYS`` order)."""
        return dict(self.limits)

    def limit_where(self, key: str) -> Where:
        """Provenance of the limit of ``key``."""
        return self.where.child("limits").child(key)


@dataclass(frozen=True)
class Scenario:
    """A validated courier scenario (see the module docstring for the YAML schema)."""

    name: str
    platen: Platen
    runs: tuple[Run, ...]
    coordination: Coordination | None = None
    reference: Reference = field(default_factory=Reference)
    doc: str = ""
    source: str = "<scenario>"
    runs_where: Where = field(default=Where("<scenario>"), compare=False)
    design: DesignSpace | None = None

    @property
    def run_names(self) -> tuple[str, ...]:
        """Names of the runs, in file order."""
        return tuple(run.name for run in self.runs)

    def run_index(self, name: str) -> int:
        """Position of run ``name`` (it seeds the run's random streams).

        Raises
        ------
        SpecError
            If the scenario has no such run (with a did-you-mean).
        """
        for index, run in enumerate(self.runs):
            if run.name == name:
                return index
        raise SpecError(
            self.runs_where,
            f"no run named '{name}'{did_you_mean(str(name), self.run_names)}"
            f"; runs: {', '.join(self.run_names)}",
        )


# --------------------------------------------------------------------------- field helpers


def _number(
    mapping: YMap,
    where: Where,
    key: str,
    default: float | None = None,
    *,
    positive: bool = False,
    nonnegative: bool = False,
) -> float:
    """A number at ``mapping[key]`` (``default`` when absent), optionally sign-checked."""
    if key not in mapping:
        if default is None:
            raise SpecError(where, f"missing required key '{key}'")
        return default
    kw = child_where(mapping, where, key)
    value = expect_number(mapping[key], kw)
    if positive and value <= 0:
        raise SpecError(kw, f"expected a positive number, found {value:g}")
    if nonnegative and value < 0:
        raise SpecError(kw, f"expected a number of at least 0, found {value:g}")
    return value


def _choice(mapping: YMap, where: Where, key: str, choices: tuple[str, ...], default: str) -> str:
    """One of ``choices`` at ``mapping[key]`` (``default`` when absent)."""
    if key not in mapping:
        return default
    kw = child_where(mapping, where, key)
    value = mapping[key]
    if not isinstance(value, str) or value not in choices:
        raise SpecError(
            kw,
            f"expected one of {', '.join(choices)}, found {value!r}"
            f"{did_you_mean(str(value), choices)}",
        )
    return value


def _numbers(value: Any, where: Where, count: int, what: str) -> tuple[float, ...]:
    """A list of exactly ``count`` numbers."""
    items = expect_list(value, where)
    if len(items) != count:
        raise SpecError(where, f"expected {what}, found a list of {len(items)}")
    return tuple(expect_number(item, child_where(items, where, i)) for i, item in enumerate(items))


def _range(mapping: YMap, where: Where, key: str, scale: float = 1.0) -> tuple[float, float]:
    """A ``[lo, hi]`` range with ``lo <= hi``, multiplied by ``scale``."""
    kw = child_where(mapping, where, key)
    lo, hi = _numbers(mapping[key], kw, 2, "a range [lo, hi] of two numbers")
    if lo > hi:
        raise SpecError(kw, f"range [lo, hi] must have lo <= hi, found [{lo:g}, {hi:g}]")
    return lo * scale, hi * scale


def _point(mapping: YMap, where: Where, key: str) -> tuple[float, float]:
    """An ``[x, y]`` point."""
    kw = child_where(mapping, where, key)
    x, y = _numbers(mapping[key], kw, 2, "a point [x, y] of two numbers")
    return x, y


# --------------------------------------------------------------------------- platen


def _segments(value: Any, where: Where) -> tuple[tuple[float, ...], ...]:
    mapping = check_keys(value, where, required=SEGMENT_NAMES)
    out = []
    for name in SEGMENT_NAMES:
        sw = child_where(mapping, where, name)
        seg = check_keys(mapping[name], sw, optional=FOURIER_KEYS)
        out.append(tuple(_number(seg, sw, key, 0.0) for key in FOURIER_KEYS))
    return tuple(out)


def _per_segment(value: Any, where: Where, parse: Any) -> tuple[Any, ...]:
    """An effect given for some of s1..s4; unlisted segments get ``parse(None, ...)``."""
    mapping = check_keys(value, where, optional=SEGMENT_NAMES)
    if not mapping:
        raise SpecError(
            where, "lists no segment (s1..s4); remove the effect to switch it off"
        )
    return tuple(
        parse(mapping.get(name), child_where(mapping, where, name)) for name in SEGMENT_NAMES
    )


def _lateral(value: Any, where: Where) -> Lateral:
    mapping = check_keys(value, where, optional=("k9", "k10"))
    return Lateral(_number(mapping, where, "k9", 0.0), _number(mapping, where, "k10", 0.0))


def _angle(value: Any, where: Where) -> AngleTerm:
    mapping = check_keys(value, where, optional=("a", "b", "c"))
    return AngleTerm(*(_number(mapping, where, key, 0.0) for key in ("a", "b", "c")))


def _drift(value: Any, where: Where) -> Drift:
    mapping = check_keys(value, where, optional=("rate", "quadratic"))
    return Drift(_number(mapping, where, "rate", 0.0), _number(mapping, where, "quadratic", 0.0))


def _harmonic(value: Any, where: Where) -> Harmonic:
    mapping = check_keys(value, where, required=("n",), optional=("sin", "cos"))
    n = expect_int(mapping["n"], child_where(mapping, where, "n"), minimum=1)
    return Harmonic(n, _number(mapping, where, "sin", 0.0), _number(mapping, where, "cos", 0.0))


def _harmonics(value: Any, where: Where) -> tuple[Harmonic, ...]:
    if value is None:
        return ()
    items = expect_list(value, where)
    return tuple(_harmonic(item, child_where(items, where, i)) for i, item in enumerate(items))


def _wave(value: Any, where: Where) -> Wave:
    mapping = check_keys(value, where, required=("amplitude", "wavelength"), optional=("phase",))
    return Wave(
        _number(mapping, where, "amplitude"),
        _number(mapping, where, "wavelength", positive=True),
        _number(mapping, where, "phase", 0.0),
    )


def _waves(mapping: YMap, where: Where, key: str) -> tuple[Wave, ...]:
    if key not in mapping:
        return ()
    kw = child_where(mapping, where, key)
    items = expect_list(mapping[key], kw)
    return tuple(_wave(item, child_where(items, kw, i)) for i, item in enumerate(items))


def _pitch_variation(value: Any, where: Where) -> PitchVariation:
    mapping = check_keys(value, where, optional=("x", "y"))
    out = PitchVariation(_waves(mapping, where, "x"), _waves(mapping, where, "y"))
    if not out.x and not out.y:
        raise SpecError(where, "lists no wave for x or y; remove the effect to switch it off")
    return out


def _count_slip(value: Any, where: Where) -> CountSlip:
    if value is None:
        return CountSlip()
    mapping = check_keys(value, where, required=("fraction",))
    fraction = _number(mapping, where, "fraction", nonnegative=True)
    if fraction > 1.0:
        raise SpecError(child_where(mapping, where, "fraction"),
                        f"fraction is a share of the observations: expected a number from 0 "
                        f"to 1, found {fraction:g}")
    return CountSlip(fraction)


def _effects(value: Any, where: Where) -> Effects:
    mapping = check_keys(value, where, optional=EFFECT_NAMES)
    parsers = {
        "lateral": lambda v, w: _per_segment(v, w, _lateral),
        "angle": lambda v, w: _per_segment(v, w, _angle),
        "harmonics": lambda v, w: _per_segment(v, w, _harmonics),
        "drift": lambda v, w: _per_segment(v, w, _drift),
        "pitch_variation": _pitch_variation,
        "count_slips": lambda v, w: _per_segment(v, w, _count_slip),
    }
    found: dict[str, Any] = {
        name: parsers[name](mapping[name], child_where(mapping, where, name))
        for name in EFFECT_NAMES
        if name in mapping
    }
    return Effects(**found)


def _platen(value: Any, where: Where) -> Platen:
    optional = ("pitch", "l_s", "l_o", "distortion_at", "geometry", "noise", "quantization",
                "effects")
    mapping = check_keys(value, where, required=("segments",), optional=optional)
    return Platen(
        segments=_segments(mapping["segments"], child_where(mapping, where, "segments")),
        pitch=_number(mapping, where, "pitch", DEFAULT_PITCH, positive=True),
        l_s=_number(mapping, where, "l_s", DEFAULT_L_S, positive=True),
        l_o=_number(mapping, where, "l_o", DEFAULT_L_O),
        distortion_at=_choice(mapping, where, "distortion_at", DISTORTION_MODES, "true_position"),
        geometry=_choice(mapping, where, "geometry", GEOMETRIES, "exact"),
        noise=_number(mapping, where, "noise", DEFAULT_NOISE, nonnegative=True),
        quantization=_number(mapping, where, "quantization", DEFAULT_QUANTIZATION,
                             nonnegative=True),
        effects=_effects(mapping.get("effects"), child_where(mapping, where, "effects")),
        where=where,
    )


# --------------------------------------------------------------------------- coordination


def _axis_nonlinearity(value: Any, where: Where) -> AxisNonlinearity:
    mapping = check_keys(value, where, optional=("g", "n2", "n3"))
    return AxisNonlinearity(_number(mapping, where, "n2", 0.0), _number(mapping, where, "n3", 0.0),
                            _number(mapping, where, "g", 0.0))


def _coordination(value: Any, where: Where) -> Coordination:
    required = ("h", "l_x", "l_y", "o_x", "o_y")
    mapping = check_keys(value, where, required=required, optional=("noise", "nonlinearity"))
    nonlinearity = None
    if "nonlinearity" in mapping:
        nw = child_where(mapping, where, "nonlinearity")
        nl = check_keys(mapping["nonlinearity"], nw, optional=("x", "y"))
        nonlinearity = (
            _axis_nonlinearity(nl.get("x"), child_where(nl, nw, "x")),
            _axis_nonlinearity(nl.get("y"), child_where(nl, nw, "y")),
        )
    return Coordination(
        h=_number(mapping, where, "h", positive=True),
        l_x=_number(mapping, where, "l_x"),
        l_y=_number(mapping, where, "l_y"),
        o_x=_number(mapping, where, "o_x"),
        o_y=_number(mapping, where, "o_y"),
        noise=_number(mapping, where, "noise", 0.0, nonnegative=True),
        nonlinearity=nonlinearity,
    )


def _reference(value: Any, where: Where) -> Reference:
    mapping = check_keys(value, where, optional=("position_noise", "angle_noise"))
    return Reference(
        position_noise=_number(mapping, where, "position_noise", 0.0, nonnegative=True),
        angle_noise=_number(mapping, where, "angle_noise", 0.0, nonnegative=True),
    )


# --------------------------------------------------------------------------- runs


def _pivot(mapping: YMap, where: Where, has_coordination: bool) -> str:
    pivot = _choice(mapping, where, "rotate_about", PIVOTS, "platen")
    if pivot == "coordination" and not has_coordination:
        raise SpecError(
            child_where(mapping, where, "rotate_about"),
            "rotate_about: coordination needs a 'coordination' section in the scenario",
        )
    return pivot


def _scatter(value: Any, where: Where, has_coordination: bool) -> Scatter:
    mapping = check_keys(value, where, required=("n", "x", "y", "theta_deg"),
                         optional=("rotate_about", "dwell"))
    dwell = _number(mapping, where, "dwell", 0.0, nonnegative=True)
    if dwell > 1.0:
        raise SpecError(child_where(mapping, where, "dwell"),
                        f"dwell is a share of the poses: expected a number from 0 to 1, "
                        f"found {dwell:g}")
    return Scatter(
        n=expect_int(mapping["n"], child_where(mapping, where, "n"), minimum=1,
                     maximum=MAX_SAMPLES),
        x=_range(mapping, where, "x"),
        y=_range(mapping, where, "y"),
        theta=_range(mapping, where, "theta_deg", math.pi / 180.0),
        rotate_about=_pivot(mapping, where, has_coordination),
        dwell=dwell,
    )


def _line(value: Any, where: Where, has_coordination: bool) -> Line:
    mapping = check_keys(value, where, required=("n", "from", "to"),
                         optional=("theta_deg", "theta_jitter_deg", "rotate_about"))
    deg = math.pi / 180.0
    return Line(
        n=expect_int(mapping["n"], child_where(mapping, where, "n"), minimum=1,
                     maximum=MAX_SAMPLES),
        start=_point(mapping, where, "from"),
        end=_point(mapping, where, "to"),
        theta=_number(mapping, where, "theta_deg", 0.0) * deg,
        theta_jitter=_number(mapping, where, "theta_jitter_deg", 0.0, nonnegative=True) * deg,
        rotate_about=_pivot(mapping, where, has_coordination),
    )


def _run(name: str, value: Any, where: Where, has_coordination: bool) -> Run:
    mapping = check_keys(value, where, optional=("scatter", "line", "dt", "t0", "doc"))
    motions = [key for key in ("scatter", "line") if key in mapping]
    if len(motions) != 1:
        found = " and ".join(f"'{m}'" for m in motions) or "neither"
        raise SpecError(
            where, f"a run needs exactly one motion, 'scatter' or 'line'; found {found}"
        )
    kind = motions[0]
    mw = child_where(mapping, where, kind)
    motion = (_scatter if kind == "scatter" else _line)(mapping[kind], mw, has_coordination)
    doc = mapping.get("doc")
    return Run(
        name=name,
        motion=motion,
        dt=_number(mapping, where, "dt", DEFAULT_DT, positive=True),
        t0=_number(mapping, where, "t0", 0.0),
        doc="" if doc is None else expect_str(doc, child_where(mapping, where, "doc")),
    )


def _runs(value: Any, where: Where, has_coordination: bool) -> tuple[Run, ...]:
    mapping = expect_map(value, where)
    if not mapping:
        raise SpecError(where, "a scenario needs at least one run")
    out = []
    for key, run in mapping.items():
        rw = child_where(mapping, where, key)
        name = expect_name(key, rw, "a run name")
        out.append(_run(name, run, rw, has_coordination))
    return tuple(out)


# --------------------------------------------------------------------------- design


def _limit(mapping: YMap, where: Where, key: str) -> tuple[float, float]:
    lo, hi = _range(mapping, where, key)
    kw = child_where(mapping, where, key)
    if key == "dwell" and not 0.0 <= lo <= hi <= 1.0:
        raise SpecError(kw, f"dwell is a share of the poses: its limits must lie within "
                            f"[0, 1], found [{lo:g}, {hi:g}]")
    if key == "n":
        if lo != int(lo) or hi != int(hi) or lo < 1 or hi > MAX_SAMPLES:
            raise SpecError(kw, f"n's limits must be whole numbers from 1 to {MAX_SAMPLES}, "
                                f"found [{lo:g}, {hi:g}]")
    return lo, hi


def _motion_values(motion: Scatter) -> dict[str, tuple[float, float]]:
    """The scatter's motion parameters in the units of a design's limits."""
    deg = 180.0 / math.pi
    return {"x": motion.x, "y": motion.y,
            "theta_deg": (motion.theta[0] * deg, motion.theta[1] * deg),
            "dwell": (motion.dwell, motion.dwell), "n": (float(motion.n), float(motion.n))}


def _design(value: Any, where: Where, runs: tuple[Run, ...]) -> DesignSpace:
    mapping = check_keys(value, where, required=("run", "limits"), optional=("doc",))
    rw = child_where(mapping, where, "run")
    name = expect_name(mapping["run"], rw, "a run name")
    names = tuple(run.name for run in runs)
    if name not in names:
        raise SpecError(rw, f"no run named '{name}'{did_you_mean(name, names)}; runs: "
                            f"{', '.join(names)}")
    motion = runs[names.index(name)].motion
    if not isinstance(motion, Scatter):
        raise SpecError(rw, f"run '{name}' is a line; only a scatter run can be designed")
    lw = child_where(mapping, where, "limits")
    limits_map = check_keys(mapping["limits"], lw, optional=DESIGN_KEYS)
    if not limits_map:
        raise SpecError(lw, f"lists no motion parameter that may change; list some of "
                            f"{', '.join(DESIGN_KEYS)}")
    limits = tuple((key, _limit(limits_map, lw, key)) for key in DESIGN_KEYS
                   if key in limits_map)
    current = _motion_values(motion)
    for key, (lo, hi) in limits:
        a, b = current[key]
        if a < lo - 1e-12 * max(1.0, abs(lo)) or b > hi + 1e-12 * max(1.0, abs(hi)):
            shown = f"{a:g}" if a == b else f"[{a:g}, {b:g}]"
            raise SpecError(child_where(limits_map, lw, key),
                            f"run '{name}' has {key} {shown}, outside its limits "
                            f"[{lo:g}, {hi:g}]")
    doc = mapping.get("doc")
    return DesignSpace(name, limits,
                       "" if doc is None else expect_str(doc, child_where(mapping, where,
                                                                          "doc")).strip(),
                       where)


# --------------------------------------------------------------------------- entry points


def parse_scenario(doc: YMap, where: Where) -> Scenario:
    """Validate a loaded scenario document.

    Parameters
    ----------
    doc
        The top-level mapping, as returned by :func:`symcal.language.yamlio.load_yaml`.
    where
        Its provenance.

    Returns
    -------
    Scenario
        The frozen scenario.

    Raises
    ------
    SpecError
        On any unknown or missing key, wrong type or invalid value, naming file:line
        and key path.
    """
    check_keys(doc, where, required=("scenario", "platen", "runs"),
               optional=("doc", "extends", "coordination", "reference", "design"))
    name = expect_name(doc["scenario"], child_where(doc, where, "scenario"), "a scenario name")
    coordination = None
    if "coordination" in doc:
        coordination = _coordination(doc["coordination"], child_where(doc, where, "coordination"))
    runs_where = child_where(doc, where, "runs")
    text = doc.get("doc")
    runs = _runs(doc["runs"], runs_where, coordination is not None)
    design = None
    if doc.get("design") is not None:
        design = _design(doc["design"], child_where(doc, where, "design"), runs)
    return Scenario(
        name=name,
        platen=_platen(doc["platen"], child_where(doc, where, "platen")),
        runs=runs,
        coordination=coordination,
        reference=_reference(doc.get("reference"), child_where(doc, where, "reference")),
        doc="" if text is None else expect_str(text, child_where(doc, where, "doc")).strip(),
        source=where.file,
        runs_where=runs_where,
        design=design,
    )


def load_scenario(path: str | Path) -> Scenario:
    """Load and validate a scenario YAML file.

    Parameters
    ----------
    path
        The scenario file (schema in this module's docstring).

    Returns
    -------
    Scenario
        A frozen dataclass tree; change it with :func:`dataclasses.replace`.

    Raises
    ------
    SpecError
        If the file is missing, is not valid YAML, or does not follow the schema; the
        message names ``file:line``, the key path and, for unknown keys, the nearest
        valid key.
    """
    doc, where = load_with_extends(path, "scenario", merge_scenario)
    return parse_scenario(doc, where)
