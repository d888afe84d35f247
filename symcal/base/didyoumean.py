"""Did-you-mean suggestions for misspelt names."""

from __future__ import annotations

import difflib
from collections.abc import Iterable

from symcal.base.errors import excerpt

CUTOFF = 0.5


def did_you_mean(name: str, candidates: Iterable[str]) -> str:
    """Return ``" (did you mean 'x'?)"`` for the closest candidate, or ``""``.

    Parameters
    ----------
    name
        The name the user wrote.
    candidates
        The names that would have been valid at that place, in their declared order;
        among equally close candidates the first is suggested.
    """
    pool = list(dict.fromkeys(str(c) for c in candidates))
    best, best_score = None, CUTOFF
    for cand in pool:
        if cand.lower() == name.lower():
            return f" (did you mean '{excerpt(cand)}'?)"
        score = difflib.SequenceMatcher(None, name, cand).ratio()
        if score > best_score or (best is None and score >= best_score):
            best, best_score = cand, score
    return f" (did you mean '{excerpt(best)}'?)" if best is not None else ""
