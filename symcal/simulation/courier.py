"""The courier simulator: poses, platen and coordination sensors, hidden effects, truth.

Conventions (Quaid & Rizzi §2-3.2; units mm, rad, s; ``f = 2 pi / pitch``)
--------------------------------------------------------------------------
*Pose.*  ``(x, y, theta)`` is the platen-sensor centre in the world (platen) frame.

*Platen sensor.*  Four segments in a pinwheel at body positions ``(a_i, b_i)``::

    s1 (-l_o, -l_s/2) measures x     s2 (+l_s/2, -l_o) measures y
    s3 (+l_o, +l_s/2) measures x     s4 (-l_s/2, +l_o) measures y

A body point ``(a, b)`` is at world ``(x + a cos t - b sin t, y + a sin t + b cos t)``.
Each segment's counter is zeroed so that it reads the centre coordinate at ``theta = 0``:
the true position ``p*_i`` of an x-segment is the world x of its location minus ``a_i``
(of a y-segment, world y minus ``b_i``); its lateral coordinate ``q_i`` is the other world
coordinate minus the other body offset.  Hence, exactly,
``(p*1 + p*3)/2 = x``, ``(p*2 + p*4)/2 = y``, ``g_p = (p*1 - p*3) - (p*2 - p*4) = 0`` and
``p*1 - p*3 = l_s sin t + 2 l_o (1 - cos t)``; to second order ``q_1 = y - l_o t``,
``q_2 = x + l_o t``, ``q_3 = y + l_o t``, ``q_4 = x - l_o t``, eq. (9)'s arguments.
With ``geometry: small_angle`` the pose enters linearised (``sin t -> t``,
``cos t -> 1``): ``p*1 = x + (l_s/2) t`` and ``q_1 = y - l_o t`` exactly, so eq. (4)
returns ``theta`` exactly.

*Segment error* (eq. 3) at tooth coordinate ``v``:
``e(v) = k0 + k1 sin(f v) + k2 cos(f v) + k3 sin(2fv) + ... + k8 cos(6fv)``, and the
switchable extras, each off unless the scenario lists it:

- lateral: ``k9 sin(f q) + k10 cos(f q)``
- angle: ``a t + b t sin(f v) + c t cos(f v)``
- harmonics: ``sum_n s_n sin(n f v) + c_n cos(n f v)``
- drift: ``rate t_s + quadratic t_s^2`` (``t_s`` the time column)
- pitch variation: the tooth coordinate is ``u = p* + w(p*)`` with
  ``w(p) = sum A sin(2 pi p / wavelength + phase)``, ``w_x`` for s1, s3 and ``w_y`` for
  s2, s4 (without it ``u = p*``); the reading counts teeth.
- count slips: on a share ``fraction`` of the observations (each drawn independently,
  per segment, from a stream of its own) the segment's reading is off by ``+-pitch/4``, a
  quadrature count lost or gained on that observation only (a glitch); the slipped rows
  are in :func:`slipped_rows` and in :func:`truth` given a seed.

Readings.  ``distortion_at: true_position`` (physics, default):
``p_bar = u - E(u - k0, q, theta, t)`` with ``E`` = eq. (3) + extras: the tooth error is
periodic in the segment's own counter frame, whose zero is offset by ``k0``, and is
evaluated at the true position in that frame.  (The models' Fourier coefficients use the
same frame, so they equal the scenario's; see models/platen_segment_implicit.yaml.)
``distortion_at: reading`` (the calibration model's assumption ``p_hat = p_bar + e(p_bar)``):
``p_bar`` solves ``p_bar + E(p_bar, q_bar, theta_bar, t) = u`` to 1e-13 mm, where the
extras see what a model sees: ``theta_bar = ((p1-p3) + (p2-p4)) / (2 l_s)``, the eq. (9)
arguments ``q_bar_1 = p_y - l_o theta_bar`` etc. from the raw readings.  Then Gaussian
noise (``platen.noise``) and rounding to ``platen.quantization``.

*Coordination sensor* (eq. 10-11).  ``c = R(t)^T ((x, y) - (o_x, o_y)) - (l_x, l_y)``,
optionally ``c -> c + g c + n2 c^2 + n3 c^3`` per axis (PSD gain and nonlinearity), then
``psi = atan(c / h)`` plus Gaussian noise.  Hence eq. (11) holds exactly for the true
pose: ``(x, y) = (o_x, o_y) + R(t) (c + l)``.

*Random streams.*  ``default_rng(SeedSequence(seed, spawn_key=(run_index, stream)))`` with
independent streams for poses, platen noise, coordination noise and reference noise; all
draws are row-wise, so a run with a smaller ``n`` is a prefix of one with a larger ``n``
(scatter runs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from symcal.base.errors import SpecError
from symcal.simulation.scenario import (
    FOURIER_KEYS,
    SEGMENT_NAMES,
    Coordination,
    Line,
    Platen,
    Run,
    Scenario,
    Wave,
)

SEGMENTS: tuple[str, ...] = SEGMENT_NAMES
FOURIER_HARMONICS: tuple[int, ...] = (1, 2, 4, 6)
PLATEN_COLUMNS: tuple[str, ...] = ("t", "p1", "p2", "p3", "p4")
COORDINATION_COLUMNS: tuple[str, ...] = ("psi_x", "psi_y")
REFERENCE_COLUMNS: tuple[str, ...] = ("x_ref", "y_ref", "theta_ref")
STREAMS: dict[str, int] = {"pose": 0, "platen": 1, "coordination": 2, "reference": 3,
                           "dwell": 4, "slips": 5}

_X_SEGMENT = np.array([True, False, True, False])
_READING_TOLERANCE = 1e-13
_MAX_ITERATIONS = 60


@dataclass(frozen=True)
class Poses:
    """Sampled true poses of one run: time (s), platen-centre x, y (mm) and theta (rad)."""

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    theta: np.ndarray


# --------------------------------------------------------------------------- geometry


def columns(scenario: Scenario) -> tuple[str, ...]:
    """The column names a run of ``scenario`` produces, in order."""
    coord = COORDINATION_COLUMNS if scenario.coordination is not None else ()
    return PLATEN_COLUMNS + coord + REFERENCE_COLUMNS


def body_offsets(l_s: float, l_o: float) -> np.ndarray:
    """Body positions ``(a_i, b_i)`` of segments s1..s4 (shape ``(4, 2)``, mm)."""
    h = l_s / 2.0
    return np.array([[-l_o, -h], [h, -l_o], [l_o, h], [-h, l_o]])


def segment_coordinates(
    platen: Platen, x: np.ndarray, y: np.ndarray, theta: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """True positions ``p*`` and lateral coordinates ``q`` of the four segments.

    Parameters
    ----------
    platen
        The platen sensor (its ``l_s``, ``l_o`` and ``geometry`` are used).
    x, y, theta
        Platen-centre poses, shape ``(n,)``.

    Returns
    -------
    (p_true, q)
        Arrays of shape ``(n, 4)`` (columns s1..s4), in mm.
    """
    offsets = body_offsets(platen.l_s, platen.l_o)
    a, b = offsets[:, 0], offsets[:, 1]
    th = theta[:, None]
    if platen.geometry == "exact":
        sin_t, cos_m1 = np.sin(th), np.cos(th) - 1.0
    else:
        sin_t, cos_m1 = th, np.zeros_like(th)
    world_x = x[:, None] + a * cos_m1 - b * sin_t
    world_y = y[:, None] + a * sin_t + b * cos_m1
    return np.where(_X_SEGMENT, world_x, world_y), np.where(_X_SEGMENT, world_y, world_x)


def pitch_warp(waves: tuple[Wave, ...], p: np.ndarray) -> np.ndarray:
    """Tooth-pitch variation ``w(p) = sum A sin(2 pi p / wavelength + phase)`` (mm)."""
    w = np.zeros_like(p)
    for wave in waves:
        w += wave.amplitude * np.sin(2.0 * math.pi / wave.wavelength * p + wave.phase)
    return w


def tooth_coordinates(platen: Platen, p_true: np.ndarray) -> np.ndarray:
    """Tooth coordinates ``u = p* + w(p*)`` of the four segments (``u = p*`` if off)."""
    variation = platen.effects.pitch_variation
    if variation is None:
        return p_true
    u = p_true.copy()
    for i in range(4):
        waves = variation.x if _X_SEGMENT[i] else variation.y
        u[:, i] += pitch_warp(waves, p_true[:, i])
    return u


# --------------------------------------------------------------------------- errors


def fourier_error(k: tuple[float, ...], v: np.ndarray, pitch: float) -> np.ndarray:
    """Eq. (3): ``k0 + k1 sin(f v) + k2 cos(f v) + ... + k8 cos(6 f v)`` (mm).

    Parameters
    ----------
    k
        The nine coefficients ``k0..k8`` (mm).
    v
        Tooth coordinates (mm).
    pitch
        Tooth pitch ``rho`` (mm); ``f = 2 pi / rho``.
    """
    return _fourier(k, v, pitch)[0]


class _Phases:
    """``sin(n w v)`` and ``cos(n w v)`` for integer ``n``, from one sine and cosine.

    Harmonics 2, 3, 4, 6, ... follow from double- and triple-angle identities (exact up to
    rounding, ~1e-16 relative); other ``n`` are evaluated directly.
    """

    def __init__(self, v: np.ndarray, w: float) -> None:
        self.v, self.w = v, w
        self._cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        if n not in self._cache:
            self._cache[n] = self._compute(n)
        return self._cache[n]

    def _compute(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        if n == 1:
            arg = self.w * self.v
            return np.sin(arg), np.cos(arg)
        if n % 2 == 0:
            s, c = self(n // 2)
            return 2.0 * s * c, 1.0 - 2.0 * s * s
        if n == 3:
            s, c = self(1)
            return s * (3.0 - 4.0 * s * s), c * (4.0 * c * c - 3.0)
        arg = (n * self.w) * self.v
        return np.sin(arg), np.cos(arg)


def _fourier(
    k: tuple[float, ...], v: np.ndarray, pitch: float, phases: _Phases | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (3) and its derivative with respect to ``v``."""
    f = 2.0 * math.pi / pitch
    phases = _Phases(v, f) if phases is None else phases
    value = np.full_like(v, k[0], dtype=float)
    slope = np.zeros_like(value)
    for j, n in enumerate(FOURIER_HARMONICS):
        _add_harmonic(value, slope, phases, n, f, k[1 + 2 * j], k[2 + 2 * j])
    return value, slope


def _add_harmonic(
    value: np.ndarray, slope: np.ndarray, phases: _Phases, n: int, f: float, ks: float, kc: float
) -> None:
    """Add ``ks sin(n f v) + kc cos(n f v)`` and its ``v``-derivative in place."""
    if ks == 0.0 and kc == 0.0:
        return
    s, c = phases(n)
    value += ks * s + kc * c
    slope += (n * f) * (ks * c - kc * s)


def segment_error(
    platen: Platen, i: int, v: np.ndarray, q: np.ndarray, theta: np.ndarray, t: np.ndarray
) -> np.ndarray:
    """Total error ``E`` of segment ``i`` (0..3): eq. (3) plus the switched-on extras.

    Parameters
    ----------
    platen
        The platen sensor.
    i
        Segment index (0 for s1, ..., 3 for s4).
    v, q, theta, t
        Tooth coordinate, lateral coordinate (mm), angle (rad) and time (s), shape ``(n,)``.

    Returns
    -------
    numpy.ndarray
        ``E`` in mm.
    """
    return _segment_terms(platen, i, v, q, theta, t)[0]


def _segment_terms(
    platen: Platen, i: int, v: np.ndarray, q: np.ndarray, theta: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``E`` of segment ``i`` and its partial derivatives by ``v``, ``theta`` and ``q``."""
    f = 2.0 * math.pi / platen.pitch
    phases = _Phases(v, f)
    value, d_v = _fourier(platen.segments[i], v, platen.pitch, phases)
    d_theta = np.zeros_like(value)
    d_q = np.zeros_like(value)
    effects = platen.effects
    if effects.harmonics is not None:
        for h in effects.harmonics[i]:
            _add_harmonic(value, d_v, phases, h.n, f, h.sin, h.cos)
    if effects.angle is not None:
        term = effects.angle[i]
        s, c = phases(1)
        d_theta += term.a + term.b * s + term.c * c
        value += theta * d_theta
        d_v += theta * f * (term.b * c - term.c * s)
    if effects.lateral is not None:
        lat = effects.lateral[i]
        s, c = np.sin(f * q), np.cos(f * q)
        value += lat.k9 * s + lat.k10 * c
        d_q += f * (lat.k9 * c - lat.k10 * s)
    if effects.drift is not None:
        drift = effects.drift[i]
        value += drift.rate * t + drift.quadratic * t * t
    return value, d_v, d_theta, d_q


def raw_view(platen: Platen, p_bar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What a calibration model sees in raw readings: eq. (9) arguments and eq. (4) angle.

    Returns
    -------
    (q_bar, theta_bar)
        ``q_bar`` of shape ``(n, 4)``: ``p_y - l_o t, p_x + l_o t, p_y + l_o t, p_x - l_o t``
        and ``theta_bar = ((p1 - p3) + (p2 - p4)) / (2 l_s)``, shape ``(n,)``.
    """
    p1, p2, p3, p4 = p_bar.T
    theta = ((p1 - p3) + (p2 - p4)) / (2.0 * platen.l_s)
    px, py = (p1 + p3) / 2.0, (p2 + p4) / 2.0
    lo = platen.l_o * theta
    return np.column_stack([py - lo, px + lo, py + lo, px - lo]), theta


# --------------------------------------------------------------------------- readings


def noiseless_readings(platen: Platen, poses: Poses) -> np.ndarray:
    """Raw platen readings ``p_bar`` before noise and quantization, shape ``(n, 4)``."""
    p_true, q = segment_coordinates(platen, poses.x, poses.y, poses.theta)
    u = tooth_coordinates(platen, p_true)
    if platen.distortion_at == "reading":
        return _solve_readings(platen, u, poses.t)
    p_bar = np.empty_like(u)
    for i in range(4):
        # the tooth error is periodic in the segment's own (counter) frame, whose zero is
        # offset by k0: evaluate it at the true position in that frame, u - k0
        v = u[:, i] - platen.segments[i][0]
        p_bar[:, i] = u[:, i] - segment_error(platen, i, v, q[:, i], poses.theta, poses.t)
    return p_bar


def _solve_readings(platen: Platen, u: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Solve ``p_bar + E(p_bar, q_bar, theta_bar, t) = u`` by Newton steps.

    Rows (observations) are independent 4x4 systems; each row is dropped once its four
    residuals are below the tolerance.
    """
    scale = float(np.max(np.abs(u), initial=0.0))
    tolerance = _READING_TOLERANCE + 8.0 * float(np.finfo(float).eps) * scale
    p_bar = u.copy()
    rows = np.arange(len(u))
    for _ in range(_MAX_ITERATIONS):
        current = p_bar[rows]
        residual, jacobian = _reading_residual(platen, current, u[rows], t[rows])
        worst = np.max(np.abs(residual), axis=1, initial=0.0)
        if not np.all(np.isfinite(worst)):
            break
        open_rows = worst > tolerance
        if not np.any(open_rows):
            return p_bar
        rows = rows[open_rows]
        step = np.linalg.solve(jacobian[open_rows], residual[open_rows][..., None])[..., 0]
        p_bar[rows] = current[open_rows] - step
    raise SpecError(
        platen.where.child("distortion_at"),
        "distortion_at: reading did not converge: the segment errors are too steep for the "
        "reading to be a monotonic function of the position (need |de/dp| < 1)",
    )


def _raw_view_derivatives(platen: Platen) -> tuple[np.ndarray, np.ndarray]:
    """Constant derivatives of :func:`raw_view`: ``d theta_bar / d p`` (4,), ``d q_bar / d p``."""
    d_theta = np.array([1.0, 1.0, -1.0, -1.0]) / (2.0 * platen.l_s)
    mean_x, mean_y = np.array([0.5, 0.0, 0.5, 0.0]), np.array([0.0, 0.5, 0.0, 0.5])
    lo = platen.l_o * d_theta
    return d_theta, np.array([mean_y - lo, mean_x + lo, mean_y + lo, mean_x - lo])


def _reading_residual(
    platen: Platen, p_bar: np.ndarray, u: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residual ``p_bar + E - u`` (m, 4) and its Jacobian by ``p_bar`` (m, 4, 4)."""
    q_bar, theta_bar = raw_view(platen, p_bar)
    dtheta_dp, dq_dp = _raw_view_derivatives(platen)
    residual = np.empty_like(p_bar)
    jacobian = np.zeros(p_bar.shape + (4,))
    for i in range(4):
        value, d_v, d_theta, d_q = _segment_terms(
            platen, i, p_bar[:, i], q_bar[:, i], theta_bar, t
        )
        residual[:, i] = p_bar[:, i] + value - u[:, i]
        jacobian[:, i, :] = d_theta[:, None] * dtheta_dp + d_q[:, None] * dq_dp[i]
        jacobian[:, i, i] += 1.0 + d_v
    return residual, jacobian


def platen_readings(platen: Platen, poses: Poses, rng: np.random.Generator) -> np.ndarray:
    """Raw platen readings with noise and quantization, shape ``(n, 4)`` (mm)."""
    p_bar = noiseless_readings(platen, poses)
    if platen.noise > 0.0:
        p_bar = p_bar + platen.noise * rng.standard_normal(p_bar.shape)
    if platen.quantization > 0.0:
        p_bar = np.round(p_bar / platen.quantization) * platen.quantization
    return p_bar


def slips(platen: Platen, count: int, rng: np.random.Generator) -> np.ndarray:
    """The count slips of ``count`` observations (``(count, 4)``, mm): ``+-pitch/4`` where
    a segment slipped, else 0; draws are row-wise (a prefix for a smaller ``count``)."""
    out = np.zeros((count, 4))
    entries = platen.effects.count_slips
    if entries is None:
        return out
    draws = rng.uniform(size=(count, 4, 2))
    for i, entry in enumerate(entries):
        hit = draws[:, i, 0] < entry.fraction
        out[hit, i] = np.where(draws[hit, i, 1] < 0.5, -0.25, 0.25) * platen.pitch
    return out


def slipped_rows(scenario: Scenario, run: str, seed: int = 0,
                 n: int | None = None) -> dict[str, list[int]]:
    """The rows (from 0) of each segment whose reading slipped, in one simulated run.

    Parameters
    ----------
    scenario, run, seed, n
        As for :func:`simulate_run`.

    Returns
    -------
    dict
        Segment name → sorted row indices (empty without the ``count_slips`` effect).
    """
    _check_counts(seed, n)
    index = scenario.run_index(run)
    motion = scenario.runs[index].motion
    jumps = slips(scenario.platen, motion.n if n is None else n, stream(seed, index, "slips"))
    return {name: [int(r) for r in np.flatnonzero(jumps[:, i])]
            for i, name in enumerate(SEGMENTS)}


def coordination_displacement(coord: Coordination, poses: Poses) -> tuple[np.ndarray, np.ndarray]:
    """True ``c = R(t)^T ((x, y) - o) - l`` of eq. (11), before nonlinearity (mm)."""
    dx, dy = poses.x - coord.o_x, poses.y - coord.o_y
    cos_t, sin_t = np.cos(poses.theta), np.sin(poses.theta)
    return cos_t * dx + sin_t * dy - coord.l_x, -sin_t * dx + cos_t * dy - coord.l_y


def coordination_angles(
    coord: Coordination, poses: Poses, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Coordination-sensor angles ``(psi_x, psi_y)`` with nonlinearity and noise (rad)."""
    cx, cy = coordination_displacement(coord, poses)
    if coord.nonlinearity is not None:
        nx, ny = coord.nonlinearity
        cx = cx + nx.g * cx + nx.n2 * cx**2 + nx.n3 * cx**3
        cy = cy + ny.g * cy + ny.n2 * cy**2 + ny.n3 * cy**3
    psi_x, psi_y = np.arctan(cx / coord.h), np.arctan(cy / coord.h)
    if coord.noise > 0.0:
        z = rng.standard_normal((len(cx), 2))
        psi_x, psi_y = psi_x + coord.noise * z[:, 0], psi_y + coord.noise * z[:, 1]
    return psi_x, psi_y


# --------------------------------------------------------------------------- motions


def run_poses(scenario: Scenario, run: Run, rng: np.random.Generator, n: int | None,
              dwell_rng: np.random.Generator | None = None) -> Poses:
    """True poses of ``run`` (``n`` overrides its sample count); a scatter with ``dwell``
    draws which poses dwell at the ends of its angle range from ``dwell_rng``."""
    motion = run.motion
    count = motion.n if n is None else n
    if isinstance(motion, Line):
        sx, sy, theta = _line(motion, count, rng)
    else:
        low = (motion.x[0], motion.y[0], motion.theta[0])
        high = (motion.x[1], motion.y[1], motion.theta[1])
        draws = rng.uniform(low, high, size=(count, 3))
        sx, sy, theta = draws[:, 0].copy(), draws[:, 1].copy(), draws[:, 2].copy()
        if motion.dwell > 0.0:
            ends = (np.random.default_rng(0) if dwell_rng is None else dwell_rng).uniform(
                size=(count, 2))
            at_end = ends[:, 0] < motion.dwell
            theta[at_end] = np.where(ends[at_end, 1] < 0.5, motion.theta[0], motion.theta[1])
    if motion.rotate_about == "coordination":
        coord = scenario.coordination
        assert coord is not None  # guaranteed by the scenario loader
        cos_t, sin_t = np.cos(theta), np.sin(theta)
        sx = sx + cos_t * coord.l_x - sin_t * coord.l_y
        sy = sy + sin_t * coord.l_x + cos_t * coord.l_y
    t = run.t0 + run.dt * np.arange(count, dtype=float)
    return Poses(t=t, x=sx, y=sy, theta=theta)


def _line(
    motion: Line, count: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    frac = np.linspace(0.0, 1.0, count) if count > 1 else np.zeros(1)
    x = motion.start[0] + frac * (motion.end[0] - motion.start[0])
    y = motion.start[1] + frac * (motion.end[1] - motion.start[1])
    theta = np.full(count, motion.theta)
    if motion.theta_jitter > 0.0:
        theta = theta + motion.theta_jitter * rng.standard_normal(count)
    return x, y, theta


# --------------------------------------------------------------------------- public API


def stream(seed: int, run_index: int, name: str) -> np.random.Generator:
    """The random generator of stream ``name`` (see ``STREAMS``) of one run."""
    sequence = np.random.SeedSequence(seed, spawn_key=(run_index, STREAMS[name]))
    return np.random.default_rng(sequence)


def _check_counts(seed: int, n: int | None) -> None:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a whole number of at least 0, found {seed!r}")
    if n is not None and (isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1):
        raise ValueError(f"n must be a whole number of at least 1, found {n!r}")


def simulate_run(
    scenario: Scenario, run: str, seed: int = 0, n: int | None = None
) -> dict[str, np.ndarray]:
    """Simulate one run of a scenario.

    Parameters
    ----------
    scenario
        The scenario (from :func:`load_scenario`).
    run
        Name of the run.
    seed
        Base seed (>= 0); each run and each stream gets its own generator.
    n
        Number of samples, overriding the run's ``n``.

    Returns
    -------
    dict of str to numpy.ndarray
        Columns ``t, p1, p2, p3, p4, [psi_x, psi_y,] x_ref, y_ref, theta_ref`` in this
        order, 1-D float64 arrays (``psi_*`` only with a coordination sensor).

    Raises
    ------
    SpecError
        If there is no such run, or ``distortion_at: reading`` does not converge.
    ValueError
        If ``seed`` or ``n`` is not a valid count.
    """
    _check_counts(seed, n)
    index = scenario.run_index(run)
    poses = run_poses(scenario, scenario.runs[index], stream(seed, index, "pose"), n,
                      stream(seed, index, "dwell"))
    readings = platen_readings(scenario.platen, poses, stream(seed, index, "platen"))
    readings = readings + slips(scenario.platen, len(poses.t), stream(seed, index, "slips"))
    out = {"t": poses.t}
    for i in range(4):
        out[f"p{i + 1}"] = np.ascontiguousarray(readings[:, i])
    if scenario.coordination is not None:
        rng = stream(seed, index, "coordination")
        out["psi_x"], out["psi_y"] = coordination_angles(scenario.coordination, poses, rng)
    out.update(_reference_columns(scenario, poses, stream(seed, index, "reference")))
    return {key: np.asarray(out[key], dtype=np.float64) for key in columns(scenario)}


def _reference_columns(
    scenario: Scenario, poses: Poses, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    ref = scenario.reference
    x, y, theta = poses.x, poses.y, poses.theta
    if ref.position_noise > 0.0 or ref.angle_noise > 0.0:
        z = rng.standard_normal((len(x), 3))
        x = x + ref.position_noise * z[:, 0]
        y = y + ref.position_noise * z[:, 1]
        theta = theta + ref.angle_noise * z[:, 2]
    return {"x_ref": x, "y_ref": y, "theta_ref": theta}


def simulate(
    scenario: Scenario, seed: int = 0, n: int | None = None
) -> dict[str, dict[str, np.ndarray]]:
    """Simulate every run of a scenario: ``{run name: columns}`` (see :func:`simulate_run`)."""
    return {name: simulate_run(scenario, name, seed, n) for name in scenario.run_names}


def truth(scenario: Scenario, seed: int | None = None, n: int | None = None) -> dict:
    """The true parameters and effects of a scenario, as a plain YAML-able dict.

    Parameters
    ----------
    scenario
        The scenario.
    seed, n
        With a seed (and the ``n`` that overrides each run's count, as for
        :func:`simulate_run`), ``effects.count_slips.values.rows`` lists the slipped rows
        of every run and segment (:func:`slipped_rows`).

    Returns
    -------
    dict
        ``scenario`` (name), ``parameters`` in the calibration models' names
        (``s1.k0`` .. ``s1.k8`` of eq. 3 for every segment, ``s1.k9``/``s1.k10`` of eq. 9
        when the lateral effect is on, and ``h, l_x, l_y, o_x, o_y`` of eq. 11 with a
        coordination sensor), ``constants`` (``pitch, l_s, l_o``), ``effects`` (every
        effect with ``on``, a formula in words and its numbers) and ``noise``.
    """
    platen = scenario.platen
    parameters: dict[str, float] = {}
    lateral = platen.effects.lateral
    for i, name in enumerate(SEGMENTS):
        for key, value in zip(FOURIER_KEYS, platen.segments[i], strict=True):
            parameters[f"{name}.{key}"] = float(value)
        if lateral is not None:
            parameters[f"{name}.k9"] = float(lateral[i].k9)
            parameters[f"{name}.k10"] = float(lateral[i].k10)
    coord = scenario.coordination
    if coord is not None:
        for key in ("h", "l_x", "l_y", "o_x", "o_y"):
            parameters[key] = float(getattr(coord, key))
    return {
        "scenario": scenario.name,
        "parameters": parameters,
        "constants": {"pitch": platen.pitch, "l_s": platen.l_s, "l_o": platen.l_o},
        "effects": _effects_truth(scenario, seed, n),
        "noise": _noise_truth(scenario),
    }


def _per_segment_values(entries: tuple, keys: tuple[str, ...]) -> dict[str, dict[str, float]]:
    return {
        name: {key: float(getattr(entry, key)) for key in keys}
        for name, entry in zip(SEGMENTS, entries, strict=True)
    }


def _effects_truth(scenario: Scenario, seed: int | None = None, n: int | None = None) -> dict:
    platen = scenario.platen
    eff = platen.effects
    out: dict[str, dict] = {
        "distortion_at": {
            "value": platen.distortion_at,
            "doc": "eq. (3) evaluated at the true tooth coordinate in the segment's "
                   "counter frame, u - k0 (physics)"
            if platen.distortion_at == "true_position"
            else "readings solve p_bar + e(p_bar) = p* (the calibration model is exact)",
        },
        "geometry": {
            "value": platen.geometry,
            "doc": "exact rotation of the pinwheel: p1 - p3 = l_s sin t + 2 l_o (1 - cos t)"
            if platen.geometry == "exact"
            else "linearised rotation: p1 - p3 = l_s t exactly (eq. 4 is exact)",
        },
    }
    out["lateral"] = _switch(
        eff.lateral, "k9 sin(f q) + k10 cos(f q), q the lateral coordinate (eq. 9 phase)",
        lambda v: _per_segment_values(v, ("k9", "k10")),
    )
    out["angle"] = _switch(
        eff.angle, "a t + b t sin(f u) + c t cos(f u), t the courier angle (mm/rad)",
        lambda v: _per_segment_values(v, ("a", "b", "c")),
    )
    out["harmonics"] = _switch(
        eff.harmonics, "sum over n of sin_n sin(n f u) + cos_n cos(n f u) (mm)",
        lambda v: {
            name: [{"n": h.n, "sin": h.sin, "cos": h.cos} for h in hs]
            for name, hs in zip(SEGMENTS, v, strict=True)
        },
    )
    out["drift"] = _switch(
        eff.drift, "rate t + quadratic t^2, t the time column (mm/s, mm/s^2)",
        lambda v: _per_segment_values(v, ("rate", "quadratic")),
    )
    out["pitch_variation"] = _switch(
        eff.pitch_variation,
        "tooth coordinate u = p* + w(p*), w = sum amplitude sin(2 pi p / wavelength + phase)",
        lambda v: {
            axis: [{"amplitude": w.amplitude, "wavelength": w.wavelength, "phase": w.phase}
                   for w in getattr(v, axis)]
            for axis in ("x", "y")
        },
    )
    out["count_slips"] = _switch(
        eff.count_slips, "on a share 'fraction' of the observations the reading is off by "
        "+-pitch/4 (a glitch of that observation)",
        lambda v: {"fraction": {name: e.fraction for name, e in zip(SEGMENTS, v, strict=True)},
                   **({} if seed is None else {"rows": {
                       run: slipped_rows(scenario, run, seed, n)
                       for run in scenario.run_names}})})
    coord = scenario.coordination
    out["psd_nonlinearity"] = _switch(
        None if coord is None else coord.nonlinearity,
        "c -> c + g c + n2 c^2 + n3 c^3 per axis before psi = atan(c / h)",
        lambda v: {axis: {"g": nl.g, "n2": nl.n2, "n3": nl.n3}
                   for axis, nl in zip("xy", v, strict=True)},
    )
    return out


def _switch(value: object, formula: str, numbers: object) -> dict:
    if value is None:
        return {"on": False, "formula": formula}
    return {"on": True, "formula": formula, "values": numbers(value)}  # type: ignore[operator]


def _noise_truth(scenario: Scenario) -> dict[str, float]:
    out = {
        "platen_sigma": scenario.platen.noise,
        "platen_quantization": scenario.platen.quantization,
        "reference_position_sigma": scenario.reference.position_noise,
        "reference_angle_sigma": scenario.reference.angle_noise,
    }
    if scenario.coordination is not None:
        out["psi_sigma"] = scenario.coordination.noise
    return out


def input_noise(scenario: Scenario) -> dict[str, float]:
    """Standard deviation of each simulated column's noise (mm, rad), by column name.

    A platen reading has ``sqrt(sigma^2 + q^2 / 12)`` (quantization as uniform error), a
    coordination angle the scenario's ``coordination.noise``, a reference column its
    reference noise; the time column is exact (0).  Every column's noise is independent
    of every other's.
    """
    platen = scenario.platen
    s = math.sqrt(platen.noise**2 + platen.quantization**2 / 12.0)
    out = {"t": 0.0, "p1": s, "p2": s, "p3": s, "p4": s}
    if scenario.coordination is not None:
        out["psi_x"] = out["psi_y"] = scenario.coordination.noise
    ref = scenario.reference
    out.update(x_ref=ref.position_noise, y_ref=ref.position_noise, theta_ref=ref.angle_noise)
    return out


def noise_floor(scenario: Scenario) -> dict[str, float]:
    """Standard deviations that noise alone leaves, for comparing residuals with.

    Every value is a standard deviation in mm or rad, assuming independent readings and
    quantization as uniform error (``q^2 / 12``), evaluated at ``psi = 0``, ``theta = 0``:

    - ``platen_reading_std`` ``s = sqrt(sigma^2 + q^2 / 12)``: one raw reading;
    - ``g_p_std`` ``2 s``: eq. (5) of four readings;
    - ``p_x_std``, ``p_y_std`` ``s / sqrt 2``: average of a pair;
    - ``theta_pair_std`` ``sqrt 2 s / l_s``: eq. (4) of one pair;
    - ``theta_std`` ``s / l_s``: the average of both pairs;
    - with a coordination sensor, ``psi_std`` (``sigma_psi``), ``c_std`` (``h sigma_psi``),
      ``g_x_std`` ``sqrt(p_x_std^2 + c_std^2 + (l_y theta_std)^2)`` and
      ``g_y_std`` ``sqrt(p_y_std^2 + c_std^2 + (l_x theta_std)^2)`` (eq. 11);
    - ``reference_position_std``, ``reference_angle_std``.
    """
    platen = scenario.platen
    s = math.sqrt(platen.noise**2 + platen.quantization**2 / 12.0)
    theta_std = s / platen.l_s
    out = {
        "platen_reading_std": s,
        "g_p_std": 2.0 * s,
        "p_x_std": s / math.sqrt(2.0),
        "p_y_std": s / math.sqrt(2.0),
        "theta_pair_std": math.sqrt(2.0) * s / platen.l_s,
        "theta_std": theta_std,
    }
    coord = scenario.coordination
    if coord is not None:
        c_std = coord.h * coord.noise
        p_var = s * s / 2.0
        out["psi_std"] = coord.noise
        out["c_std"] = c_std
        out["g_x_std"] = math.sqrt(p_var + c_std**2 + (coord.l_y * theta_std) ** 2)
        out["g_y_std"] = math.sqrt(p_var + c_std**2 + (coord.l_x * theta_std) ** 2)
    out["reference_position_std"] = scenario.reference.position_noise
    out["reference_angle_std"] = scenario.reference.angle_noise
    return out
