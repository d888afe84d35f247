"""What the noise floor cannot vouch for: effects the tests would miss that move a
parameter far (Baarda's external reliability, per candidate).

A diagnosis that finds every residual at its floor and no candidate significant says the
data show no missing effect *of a size the tests can see*.  A candidate the parameters
nearly absorb (a coupling on a reading proportional to what the sensor's gain multiplies;
a constant whose change a gain takes) is seen only through the small part of it they do
not absorb: below its minimal detectable size it can still move a parameter by hundreds
of its standard errors.  Such candidates are named, with the parameters they reach, so
that "quiet" is not read as "these parameters are right".

A term's reach depends on how it is written: ``c*T`` moves a bias by ``c`` times the
mean of T, which ``c*(T - mean)`` does not.  The reach stated is the smaller of the term
as proposed and the term beyond its lower orders (a linear term without its constant, a
quadratic without its affine part, a product without its linear terms and constant):
what holds however the term is written, where the two writings are one term to its test
(what the lower orders removed hold, the parameters absorb: ``_written_alike``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from symcal.analysis.discovery import Candidate, Design, unexplained, unseen_bias
from symcal.revise.library import Entry, Raw

#: A candidate is named where a term of it the test misses could move a parameter by
#: more than this many of its standard errors.  An ordinary candidate reaches a few
#: (the square root of its test's non-centrality, 4-5, times its correlation with the
#: parameters over what is left of it); 20 is a correlation above about 0.97 with what
#: the parameters already do, the near-absorption :data:`~symcal.revise.centres.NEARLY`
#: speaks of.
UNSEEN = 20.0
#: At most this many parameters are named per candidate.
NAMED = 3


def mark_unseen(own: Design, entries: Sequence[Entry], ranked: Sequence[Candidate],
                regressor: Callable[[Raw], np.ndarray], level: float,
                physical: Sequence[str],
                restates: Callable[[Candidate], bool] = lambda c: False,
                suspected: Callable[[Candidate], bool] = lambda c: False,
                kept: Callable[[Candidate], frozenset[str]] = lambda c: frozenset()
                ) -> None:
    """Fill :attr:`Candidate.unseen` of the tested candidates that are not significant:
    the physical parameters (``physical``: the free ones, not the comparisons' offsets)
    a term of theirs the test at ``level`` misses could move by more than
    :data:`UNSEEN` standard errors; of an absorbed candidate the user asked about
    (``suspected``: a term in another sensor's reading, in a declared ``candidates:``
    space), the parameters of its own sensor it would bias, by any amount (infinite: a
    coupling its gain takes; one another sensor's parameters take is the constraints'
    own equivalence, a courier segment's harmonic seen through its neighbour's).  Candidates that
    only restate a parameter (``restates``: a term linear in a sensor's own reading is
    its gain, written again) are left out: that the gain absorbs them is what
    calibrating it means; nor is a coefficient an earlier round added to the candidate's
    own sensor (``kept``) named for it: once a magnetometer's gain varying with T was
    kept, the product of its raw reading and T, that gain again but for its small bias
    times T, "would move mag.gain_T 140 SE".  Other absorbed candidates (a model's own
    harmonics, a constant a gain multiplies) are equivalences of the model's own terms:
    the report lists them as absorbed, the verdict does not repeat them."""
    by_label = {e.candidate.label: e for e in entries}
    wanted = set(physical)
    for cand in ranked:
        if cand.absorbed and cand.biases and suspected(cand) and not restates(cand):
            mine = cand.output.split(".", 1)[0] + "."     # its own sensor's parameters
            cand.unseen = tuple((name, float("inf")) for name in cand.biases
                                if name in wanted and name.startswith(mine))[:NAMED]
            continue
        if cand.significant or cand.absorbed or cand.reopens or \
                cand.label not in by_label or cand.reach <= UNSEEN or restates(cand):
            continue            # (reach bounds every parameter's: none can go further)
        entry = by_label[cand.label]
        x = regressor(entry.raw)
        lower = [regressor(part) for part in (entry.lower, entry.extra) if part is not None]
        reach = unseen_bias(own, x, level)
        # a curve is proposed about the point the model's parameters mean (its zero, or
        # its own centre: the diagnosis chose it to keep that meaning), so its reach as
        # written is what it would move them by: a new user's load cell, whose
        # sensitivity is its slope at zero load, ended quiet 20-24 SE off under a
        # quadratic just below the test's level, unnamed: without its affine part it
        # reached the sensitivity by less
        if lower and cand.basis.kind not in CURVES:
            beyond = _beyond(x, np.hstack(lower))
            if _written_alike(own, x, beyond):
                reach = np.minimum(reach, unseen_bias(own, beyond, level))
        order = np.argsort(-reach)
        named = wanted - kept(cand)
        cand.unseen = tuple((own.nuisance_names[k], float(reach[k])) for k in order
                            if reach[k] > UNSEEN and own.nuisance_names[k] in named
                            )[:NAMED]


#: Two writings of a term are one term to its test where the part of their difference
#: the parameters do not absorb is at most this share of what the test sees of the term.
ALIKE = 0.1


def _written_alike(own: Design, x: np.ndarray, beyond: np.ndarray) -> bool:
    """Whether ``x`` and ``beyond`` (``x`` without its lower orders) are the same term
    written two ways: their difference is what the parameters absorb (``c*T`` and
    ``c*(T - mean)`` where an offset is free).  Where the lower orders removed hold a
    part the test sees (a temperature's linear part where nothing absorbs it), the term
    beyond them is another term, and its smaller reach says nothing of this one's: a
    turbine's K-factor growing with the temperature, which the density's expansion
    coefficient absorbs whole, reached it by 1.8 SE 'beyond its lower orders' and by
    1482 SE as written; the loop ended quiet with that coefficient 51 SE off, unnamed."""
    seen = float(np.linalg.norm(unexplained(own, x)))
    moved = float(np.linalg.norm(unexplained(own, x - beyond)))
    return moved <= ALIKE * seen


def _beyond(x: np.ndarray, lower: np.ndarray) -> np.ndarray:
    """``x`` without its least-squares part in the ``lower`` columns (whitened alike)."""
    coef, *_ = np.linalg.lstsq(lower, x, rcond=None)
    return x - lower @ coef


#: A variable takes two values in a dataset where splitting its sorted values in two
#: leaves at most this share of its variance within the halves.
TWO_LEVELS = 1e-3


#: Shapes in one variable that are curved in it: on data that hold the variable at two
#: values, each is an offset and a slope in it, plus that variable's noise.
CURVES = ("quadratic", "cubic", "harmonic")


def two_levels(values: np.ndarray) -> bool:
    """Whether ``values`` cluster at two levels (every draw of a design at the two ends of
    its range): a quadratic in it is then an offset and a gain on these data."""
    x = np.sort(np.asarray(values, dtype=float).ravel())
    n = x.size
    total = float(np.sum((x - x.mean()) ** 2)) if n else 0.0
    if n < 4 or total <= 0.0:
        return False
    s1, s2 = np.cumsum(x), np.cumsum(x * x)
    k = np.arange(1, n)                                   # the first k values, the rest
    left = s2[:-1] - s1[:-1] ** 2 / k
    right = (s2[-1] - s2[:-1]) - (s1[-1] - s1[:-1]) ** 2 / (n - k)
    return float(np.min(left + right)) <= TWO_LEVELS * total


def mark_two_level(ranked: Sequence[Candidate], physical: Sequence[str],
                   values: Callable[[str], np.ndarray]) -> None:
    """Name, in :attr:`Candidate.unseen`, the parameters of its own sensor that a
    quadratic absorbed only because its variable takes two values in the fitted data
    would bias, by any amount: no model's own terms make a quadratic an offset and a gain,
    these data do.  A new user's pressure transducer designed at 100 and 700 kPa alone
    ended quiet with its gain 130 SE off under a quadratic the two levels absorbed; the
    verdict named the offsets only."""
    wanted = set(physical)
    for cand in ranked:
        if not (cand.absorbed and cand.biases and not cand.unseen
                and cand.basis.kind in CURVES and two_levels(values(cand.basis.variable))):
            continue
        mine = cand.output.split(".", 1)[0] + "."
        cand.unseen = tuple((name, float("inf")) for name in cand.biases
                            if name in wanted and name.startswith(mine))[:NAMED]

