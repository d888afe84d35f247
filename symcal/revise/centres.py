"""Where a product of two variables is written about: the centre that keeps the
parameters' meaning.

A product ``c*v*w`` of a sensor's own reading ``v`` and another variable ``w`` (a
temperature) is tested beyond its linear terms, so where it is written about does not
change the test; it changes what the parameters already there mean once it is added.
Written about ``w = 0`` (0 K for a temperature in kelvin) the sensor's gain becomes its
gain at 0 K: a load cell's sensitivity 16 standard errors from its value in the run's
18-28 degC, a glass scale's gain 591 from its value at 20 degC.  Where the parameters
absorb, or nearly, the product's part linear in ``v`` (a gain times ``v``), it is written
``c*v*(w - w0)``, ``w0`` the data's centre of ``w``: the gain then stays the gain at the
run's own conditions, the same fit.  Time itself stays uncentred (a gain that grows from
the start of the run: ``c*v*t``); the other variable of a product with time is centred
where a drift the parameters already have absorbs the part linear in time (an
oscillator's temperature coefficient that grows with its age, ``c*(T - T0)*t``: written
about ``T = 0`` its aging rate became the rate at 0 degC, 7-11 standard errors from the
rate at the run's 17-32 degC).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from symcal.analysis.discovery import Candidate, Design, absorbed, unexplained_share
from symcal.revise.blocks import Block
from symcal.revise.library import Entry, Raw, centre_of

#: What a term's centre moves between it and the rest is nearly absorbed where the
#: parameters leave less than this share of each of its columns unexplained (a gain
#: times a density that varies by a few per cent over the run; a thermistor's R25 over
#: 0-100 degC): the term is then written about the model's own centre, as where they
#: absorb it exactly, so that they keep their meaning.
NEARLY = 0.2


def centred_product(entry: Entry, own: Design, regressor: Callable[[Raw], np.ndarray],
                    block: Block) -> Entry:
    """``entry``'s product written about the data's centre of one variable where the
    parameters absorb (or nearly) the part linear in the other; itself elsewhere."""
    basis = entry.candidate.basis
    if basis.kind != "product" or basis.other is None or entry.extra is None or \
            entry.lower is None or basis.centre or basis.other_centre:
        return entry
    kinds = {v.name: v.kind for v in block.variables}
    timed = {k for k, name in (("w", basis.variable), ("v", basis.other))
             if kinds.get(name) == "drift"}      # keeping v centres w: never time
    extra, lower, raw = entry.extra, entry.lower, entry.raw
    cv = centre_of(block.values(basis.variable))
    cw = centre_of(block.values(basis.other))

    def linear(j: int, c: float) -> Raw:          # the uncentred variable on the output
        return lambda i: extra(i)[:, :, j:j + 1] + c * lower(i)

    for part, keep, c in ((linear(0, cv), "v", cw), (linear(1, cw), "w", cv)):
        if keep in timed:
            continue
        x = regressor(part)
        if not (absorbed(own, x) or unexplained_share(own, x[:, 0]) < NEARLY):
            continue

        def moved(i: int, part: Raw = part, c: float = c) -> np.ndarray:
            return raw(i) - c * part(i)

        shifted = (replace(basis, terms=("{v}*({w} - {other_centre})",), other_centre=c)
                   if keep == "v" else
                   replace(basis, terms=("({v} - {centre})*{w}",), centre=c))
        return Entry(Candidate(entry.candidate.output, shifted), moved, extra, lower)
    return entry
