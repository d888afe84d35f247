"""The distributions the noise-floor tests read their bands from.

χ² (its quantiles, by a regularised lower incomplete gamma and Newton's method), the
normal, the beta (a ratio of quadratic forms), and the band of the ratio of a variance to
a floor estimated by successive differences (von Neumann's ratio, normal approximation,
with the estimate's share mixed in: a mixture over the share's quantiles, evaluated with
SciPy's incomplete gamma and beta functions over all its nodes at once): plain functions
of numbers, no problem or data.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from statistics import NormalDist

import numpy as np

#: The level of every band: a χ²/dof inside its central 95 % interval is at the floor.
LEVEL = 0.95


def normal_quantile(p: float) -> float:
    """The standard normal quantile of ``p``."""
    return NormalDist().inv_cdf(p)


def _lower_gamma(a: float, x: float) -> float:
    """The regularised lower incomplete gamma function P(a, x) (its power series below
    a + 1, else one minus the continued fraction of Q, evaluated by Lentz's method)."""
    if x <= 0:
        return 0.0
    log_front = a * math.log(x) - x - math.lgamma(a)
    if x < a + 1.0:
        term = total = 1.0 / a
        k = a
        while abs(term) > 1e-16 * abs(total):
            k += 1.0
            term *= x / k
            total += term
        return min(1.0, total * math.exp(log_front))
    tiny = 1e-300
    b = x + 1.0 - a
    c, d = 1.0 / tiny, 1.0 / b
    h = d
    for i in range(1, 10_000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        h *= d * c
        if abs(d * c - 1.0) < 1e-16:
            break
    return max(0.0, 1.0 - math.exp(log_front) * h)


def _chi2_density(x: float, nu: float) -> float:
    """The density of χ²_ν at ``x`` > 0."""
    k = nu / 2.0
    return math.exp((k - 1.0) * math.log(x) - x / 2.0 - k * math.log(2.0) - math.lgamma(k))


@functools.lru_cache(maxsize=4096)
def chi2_quantile(p: float, nu: float) -> float:
    """The ``p`` quantile of χ²_ν, to 1e-12 relative (in Python: a declared floor's band
    needs no SciPy import):
    Newton's method on the distribution function from the Wilson–Hilferty
    approximation, kept inside a bracket (bisection where a step leaves it).  Kept per
    (p, ν): a result's bands are asked for again by its report and its document."""
    if nu <= 0:
        return 0.0
    lo, hi = 0.0, max(nu, 1.0)
    while _lower_gamma(nu / 2.0, hi / 2.0) < p:
        lo, hi = hi, 2.0 * hi
    h = 2.0 / (9.0 * nu)
    x = nu * max(1.0 - h + normal_quantile(p) * math.sqrt(h), 1e-3) ** 3
    if not lo < x < hi:
        x = 0.5 * (lo + hi)
    for _ in range(200):
        f = _lower_gamma(nu / 2.0, x / 2.0) - p
        if f < 0:
            lo = x
        else:
            hi = x
        density = _chi2_density(x, nu)
        step = f / density if density > 0 else math.inf
        new = x - step
        if not lo < new < hi:
            new = 0.5 * (lo + hi)
        if abs(new - x) <= 1e-13 * new or hi - lo <= 1e-12 * hi:
            return new
        x = new
    return x


def chi2_band(nu: float, level: float = LEVEL) -> tuple[float, float]:
    """The central ``level`` interval of χ²_ν / ν."""
    tail = (1.0 - level) / 2.0
    return chi2_quantile(tail, nu) / nu, chi2_quantile(1.0 - tail, nu) / nu


def normal_band(sd: float, level: float = LEVEL) -> tuple[float, float]:
    """``1 ± z·sd`` (the central ``level`` interval of a ratio with that spread)."""
    z = normal_quantile(0.5 + level / 2.0)
    return max(1.0 - z * sd, 0.0), 1.0 + z * sd



def _log_beta_front(x: float, a: float, b: float) -> float:
    return (math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x)
            + b * math.log1p(-x))


def _beta_fraction(x: float, a: float, b: float) -> float:
    """The continued fraction of the incomplete beta function (modified Lentz)."""
    tiny = 1e-300
    c, d = 1.0, 1.0 - (a + b) * x / (a + 1.0)
    d = 1.0 / (tiny if abs(d) < tiny else d)
    h = d
    for m in range(1, 100_000):
        for num in (m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m)),
                    -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))):
            d = 1.0 + num * d
            d = 1.0 / (tiny if abs(d) < tiny else d)
            c = 1.0 + num / c
            c = tiny if abs(c) < tiny else c
            h *= d * c
        if abs(d * c - 1.0) < 1e-15:
            break
    return h


def beta_cdf(x: float, a: float, b: float) -> float:
    """The regularised incomplete beta function I_x(a, b) (its continued fraction on the
    side where it converges fast)."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    front = math.exp(_log_beta_front(x, a, b))
    if x < (a + 1.0) / (a + b + 2.0):
        return front * _beta_fraction(x, a, b) / a
    return 1.0 - front * _beta_fraction(1.0 - x, b, a) / b


def f_log_sf(f: float, d1: float, d2: float) -> float:
    """The natural log of the F(d1, d2) distribution's upper tail at ``f``, computed in
    log space: ``log I_x(d2/2, d1/2)`` with ``x = d2 / (d2 + d1 f)``.  It stays finite
    far beyond where the tail itself underflows (scipy's ``f.logsf`` gives −inf there, so
    every very significant test looked alike)."""
    if not f > 0.0:
        return 0.0
    if math.isinf(f):
        return -math.inf
    a, b = d2 / 2.0, d1 / 2.0
    x, y = d2 / (d2 + d1 * f), d1 * f / (d2 + d1 * f)        # y = 1 - x, without rounding
    if x <= 0.0:
        return -math.inf
    if y <= 0.0:
        return 0.0
    if x < (a + 1.0) / (a + b + 2.0):
        return _log_beta_front(x, a, b) + math.log(_beta_fraction(x, a, b) / a)
    # the tail is not small here: one minus the lower side's (its continued fraction
    # converges on the other side)
    lower = math.exp(_log_beta_front(y, b, a)) * _beta_fraction(y, b, a) / b
    return math.log1p(-min(lower, 1.0)) if lower < 1.0 else -math.inf


def beta_quantile(p: float, a: float, b: float) -> float:
    """The ``p`` quantile of Beta(a, b) (a, b > 1): Newton's method on its distribution
    function from the normal approximation, inside a bracket that bisection narrows."""
    mean = a / (a + b)
    sd = math.sqrt(a * b / ((a + b) ** 2 * (a + b + 1.0)))
    lo, hi = 0.0, 1.0
    x = min(max(mean + normal_quantile(p) * sd, 1e-12), 1.0 - 1e-12)
    for _ in range(200):
        f = beta_cdf(x, a, b) - p
        if f < 0:
            lo = x
        else:
            hi = x
        density = math.exp(_log_beta_front(x, a, b)) / (x * (1.0 - x))
        new = x - f / density if density > 0 else 0.5 * (lo + hi)
        if not lo < new < hi:
            new = 0.5 * (lo + hi)
        if abs(new - x) <= 1e-14 * max(new, 1e-300) or hi - lo <= 1e-14:
            return new
        x = new
    return x


def increasing_root(f: Callable[[float], float], low: float, high: float, f_low: float,
                    f_high: float, tol: float) -> float:
    """The root of an increasing ``f`` in ``[low, high]`` (``f_low = f(low) ≤ 0 ≤ f_high
    = f(high)``) to within ``tol``: regula falsi, the Illinois way (the value kept at a
    bracket's end twice in a row is halved, so both ends close in, superlinearly).  The
    bands' distribution functions are smooth mixtures of 64 betas: 5–9 evaluations here
    where bisection took about 25."""
    if f_low == 0.0:
        return low
    if f_high == 0.0:
        return high
    kept = 0                         # which end stayed last time: -1 low, +1 high
    x, last = 0.5 * (low + high), math.inf
    for _ in range(200):
        x = high - f_high * (high - low) / (f_high - f_low) if f_high > f_low else x
        if not low < x < high:
            x = 0.5 * (low + high)
        fx = f(x)
        if fx == 0.0:
            return x
        if fx < 0.0:
            low, f_low = x, fx
            if kept == 1:
                f_high *= 0.5
            kept = 1
        else:
            high, f_high = x, fx
            if kept == -1:
                f_low *= 0.5
            kept = -1
        if high - low <= tol or abs(x - last) <= tol:   # converging superlinearly: a
            break                                         # step below tol ends it
        last = x
    return x


def _ratio_moments(n: int, centred: bool) -> tuple[float, float, float]:
    """``(c, E η, Var η)`` of von Neumann's ratio ``η = Σ(Δr)² / Σr²`` (``Σ(r - r̄)²``
    when ``centred``) of ``n`` independent normal residuals, and the constant ``c`` with
    ``χ²/dof = c / η`` for the test of a floor estimated by successive differences.

    The ratio of a quadratic form to the sum of squares is independent of that sum, so
    its moments are ratios of the forms' moments: with ``A = DᵀD`` (D the differences),
    ``tr A = 2(n - 1)`` and ``tr A² = 6n - 8`` over ``k = n`` dimensions, ``k = n - 1``
    about the mean (A removes it): ``E η = tr A / k``, ``E η² = (tr² A + 2 tr A²) / (k (k
    + 2))``."""
    k = float(n - 1 if centred else n)
    tr_a, tr_a2 = 2.0 * (n - 1), 6.0 * n - 8.0
    m1 = tr_a / k
    m2 = (tr_a**2 + 2.0 * tr_a2) / (k * (k + 2.0))
    return 2.0 * (n - 1) / k, m1, max(m2 - m1 * m1, 1e-300)


def ratio_band(n: int, centred: bool = False, level: float = LEVEL) -> tuple[float, float]:
    """The central ``level`` interval of ``χ²/dof`` of a residual whose floor was estimated
    by successive differences on the same ``n`` rows, when the residual is white noise.

    The floor estimate is uncertain (about ``2n/3`` degrees of freedom) and correlated
    with the spread it divides (both are sums of the same squared residuals), so the
    statistic is neither χ²/ν nor an F ratio: it is ``c / η``, η von Neumann's ratio,
    whose distribution is close to a beta on [0, 4] with η's exact mean and variance
    (Durbin and Watson's approximation; :func:`_ratio_moments`).  Its right tail is
    longer than a normal band's: measured on white noise, 2.4–2.7 % beyond each end of
    the 95 % band for n = 150 to 1000 (a normal band: 3.3–4.7 % above it).
    """
    c, m1, var = _ratio_moments(n, centred)
    mu, v = m1 / 4.0, var / 16.0
    k = mu * (1.0 - mu) / v - 1.0
    a, b = mu * k, (1.0 - mu) * k
    tail = (1.0 - level) / 2.0
    return c / (4.0 * beta_quantile(1.0 - tail, a, b)), c / (4.0 * beta_quantile(tail, a, b))


def ratio_sd(n: int, centred: bool = False) -> float:
    """The relative standard deviation of that ``χ²/dof`` (first order in η's spread)."""
    c, m1, var = _ratio_moments(n, centred)
    return c * math.sqrt(var) / (m1 * m1)


#: Equal-probability nodes of the estimate's share in :func:`shared_ratio_band`.
SHARE_NODES = 64


def shared_ratio_band(n: int, centred: bool, dof: float, sd: float,
                      level: float = LEVEL) -> tuple[float, float]:
    """The central ``level`` interval of ``χ²/dof`` of a residual whose floor was
    estimated by successive differences on its ``n`` rows, when the residual also carries
    the estimate's share (:func:`_estimated_test`).

    χ² (the spread over the estimated floor squared) is then the white noise's part,
    ``k X`` (k = n, or n - 1 ``centred``; X = ``c / η`` of :func:`ratio_band`, η/4 a
    beta), plus the share's ``Y``, of mean ``dof - k`` and variance ``(sd·dof)² -
    (k·sd_X)²`` (``sd`` the statistic's relative standard deviation, ``sd_X``
    :func:`ratio_sd`).  On held-out rows ``Y = Q + 2 eᵀJδθ``: ``Q = δθᵀGδθ``, a quadratic
    form in the estimate's error (drawn from the fitted rows' noise) concentrated in a
    few directions, and a cross term with the rows' own noise, of variance ``4 E Q =
    4 (dof - k)``; on the fitted rows (a negative mean) no cross term.  Q is taken as a
    scaled χ² of its mean and variance (Satterthwaite: ``a χ²_f``, ``a f = mean``,
    ``2 a² f = var``; ``a < 0`` on the fitted rows): its long right tail and its mass
    near zero are what a normal band misses.  Given Q, the cross term is normal of
    variance 4Q and widens the noise's part: ``k + λ (k X - k)``, ``λ² = 1 + 4 Q /
    (k sd_X)²``.  The distribution of the sum is the convolution ``P(χ² ≤ t) =
    E_Q[P(k X ≤ k + (t - Q - k)/λ)]``, the mean over :data:`SHARE_NODES`
    equal-probability nodes of Q; its quantiles by bisection.  Exact when either part
    is alone."""
    k = float(n - 1 if centred else n)
    lo, hi = ratio_band(n, centred, level)
    mean_y = dof - k
    var_x = (k * ratio_sd(n, centred)) ** 2
    var_y = (sd * dof) ** 2 - var_x
    if var_y <= 1e-12 * k * k or abs(mean_y) <= 1e-9 * k:
        return max(k * lo + mean_y, 0.0) / dof, (k * hi + mean_y) / dof
    cross = min(4.0 * max(mean_y, 0.0), var_y) / max(mean_y, 1e-300)   # per unit of Q
    var_q = var_y - cross * max(mean_y, 0.0)
    c, m1, var = _ratio_moments(n, centred)
    mu, v = m1 / 4.0, var / 16.0
    kk = mu * (1.0 - mu) / v - 1.0
    a, b = mu * kk, (1.0 - mu) * kk
    # SciPy's incomplete gamma and beta functions, for all the nodes in one call each:
    # node by node in Python (chi2_quantile, beta_cdf's continued fraction; a band
    # evaluates the 64 betas some 20 times, a few thousand terms each where the rows
    # are many) they took about 50 times as long, to the same accuracy
    from scipy.special import betaincc, gammaincinv

    if var_q <= 1e-12 * k * k:
        share = np.array([mean_y])
    else:
        f, scale = 2.0 * mean_y**2 / var_q, var_q / (2.0 * mean_y)
        # the χ²_f quantiles of the nodes' probabilities (j + ½)/SHARE_NODES, scaled
        share = scale * 2.0 * gammaincinv(f / 2.0, (np.arange(SHARE_NODES) + 0.5)
                                          / SHARE_NODES)
    widen = np.sqrt(1.0 + cross * np.maximum(share, 0.0) / var_x)

    def cdf(t: float) -> float:
        noise = k + (t - share - k) / widen
        noise = noise[noise > 0]
        return float(np.sum(betaincc(a, b, np.minimum(c * k / (4.0 * noise), 1.0)))
                     / share.size)

    def quantile(p: float) -> float:
        # a bracket one standard deviation either side of the normal approximation's
        # quantile (widened, doubling, where the tail is longer), where the distribution
        # function is nearly straight and the root is found in a few steps
        step = sd * dof
        if not 0.0 < step < math.inf:      # no spread to bracket with (NaN): no band,
            return math.nan                # where widening the bracket never ends
        guess = dof + normal_quantile(p) * step
        low, high = guess - step, guess + step
        at_low, at_high = cdf(low), math.nan
        while at_low > p:
            high, at_high, step = low, at_low, 2.0 * step
            low -= step
            at_low = cdf(low)
        if math.isnan(at_high):
            at_high = cdf(high)
        while at_high < p:
            low, at_low, step = high, at_high, 2.0 * step
            high += step
            at_high = cdf(high)
        return increasing_root(lambda t: cdf(t) - p, low, high, at_low - p, at_high - p,
                               1e-7 * dof)

    tail = (1.0 - level) / 2.0
    return max(quantile(tail), 0.0) / dof, quantile(1.0 - tail) / dof
