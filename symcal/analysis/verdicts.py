"""What a noise-floor test says: one residual's test (:class:`FloorTest`), a dataset's
global test (:class:`DatasetTest`), their verdicts (at, above or below the floor) and
the family of a result's datasets tested together (Šidák's level)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from symcal.analysis.bands import (
    LEVEL,
    chi2_band,
    chi2_quantile,
    normal_band,
    ratio_band,
    shared_ratio_band,
)

#: How a floor was found.
PROPAGATED = "propagated"
DIFFERENCES = "successive differences"
UNKNOWN = "unknown"


class _Statistic:
    """χ²/ν, its square root and the verdict of a test with ``chi2``, ``dof`` and
    ``band`` (:class:`FloorTest`, :class:`DatasetTest`)."""

    chi2: float | None
    dof: float | None
    band: tuple[float, float] | None

    @property
    def chi2_dof(self) -> float | None:
        """χ²/ν, or None when unknown."""
        if self.chi2 is None or not self.dof:
            return None
        return self.chi2 / self.dof

    @property
    def ratio(self) -> float | None:
        """√(χ²/ν): how many times the floor the spread is."""
        value = self.chi2_dof
        return None if value is None else math.sqrt(max(value, 0.0))

    @property
    def verdict(self) -> str | None:
        """``"at"``, ``"above"`` or ``"below"`` the floor; None when unknown."""
        return verdict_of(self.chi2_dof, self.band)


@dataclass(frozen=True)
class FloorTest(_Statistic):
    """The noise floor of one residual or comparison on one dataset, and its test.

    Attributes
    ----------
    floor
        The standard deviation noise alone leaves (internal units), None when unknown.
    method
        :data:`PROPAGATED`, :data:`DIFFERENCES` or :data:`UNKNOWN`.
    chi2, dof
        The test statistic and its expectation (effective degrees of freedom); None
        when unknown.
    band
        The central 95 % interval of ``chi2 / dof`` when at the floor.
    sd
        The relative standard deviation of ``chi2 / dof`` (to combine tests).
    chi2_before
        The same statistic with the initial parameters (same weights), when known.
    rows
        For a floor estimated by successive differences whose test carries the
        estimate's share (:func:`shared_ratio_band`): the rows it was estimated on.
    """

    floor: float | None
    method: str
    chi2: float | None = None
    dof: float | None = None
    band: tuple[float, float] | None = None
    sd: float | None = None
    chi2_before: float | None = None
    rows: int | None = None

    @property
    def worse(self) -> bool:
        """Whether calibration made the residual worse by more than its noise allows: it
        is above its floor, and its χ²/dof grew from the initial parameters by more than
        noise moves a χ²/dof at the floor (its band's upper half-width)."""
        value = self.chi2_dof
        if value is None or self.chi2_before is None or self.band is None or not self.dof:
            return False
        return (self.verdict == "above"
                and value - self.chi2_before / self.dof > self.band[1] - 1.0)

    def to_dict(self, scale: float = 1.0) -> dict[str, Any]:
        """Plain data, the floor in a unit of size ``scale``."""
        return {"floor": None if self.floor is None else self.floor / scale,
                "method": self.method, "chi2": self.chi2, "dof": self.dof,
                "band": None if self.band is None else list(self.band), "sd": self.sd,
                "chi2_before": self.chi2_before, "worse": self.worse, "rows": self.rows}

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any], scale: float = 1.0) -> FloorTest:
        """Inverse of :meth:`to_dict`."""
        floor = doc.get("floor")
        band = doc.get("band")
        return cls(None if floor is None else float(floor) * scale, str(doc["method"]),
                   doc.get("chi2"), doc.get("dof"),
                   None if band is None else (float(band[0]), float(band[1])), doc.get("sd"),
                   doc.get("chi2_before"), doc.get("rows"))


def verdict_of(value: float | None, band: tuple[float, float] | None) -> str | None:
    """Where ``value`` lies against ``band``: ``"below"``, ``"at"``, ``"above"``, None."""
    if value is None or band is None or math.isnan(value):
        return None
    if math.isinf(value):
        return "above"
    if value > band[1]:
        return "above"
    if value < band[0]:
        return "below"
    return "at"


@dataclass(frozen=True)
class DatasetTest(_Statistic):
    """The global test of the model on one dataset: its constraints' χ² against the
    floor their readings' noise sets (:class:`FloorTest` without a floor of its own).

    ``method`` is :data:`PROPAGATED` (the joint test, correlations between constraints
    included), ``combined`` (each constraint's own test, summed: some floors were
    estimated from the data) or :data:`UNKNOWN`.  ``band`` is the dataset's own 95 %
    band; ``distribution`` says what it is the band of, so that it can be taken at
    another level (:meth:`band_at`, as :func:`at_floor` does for the datasets together):
    ``chi2`` (χ²_ν / ν, ν = ``dof``, or ``2/sd²`` where the statistic spreads more than
    χ²_dof: :func:`held_out_test`), ``ratio`` (one constraint whose floor was estimated
    by successive differences on ``dof`` rows, :func:`ratio_band`) or ``normal``
    (several such constraints summed: ``1 ± z·sd``).
    """

    dataset: str
    constraints: tuple[str, ...]
    method: str
    chi2: float | None = None
    dof: float | None = None
    band: tuple[float, float] | None = None
    distribution: str = "chi2"
    sd: float | None = None
    rows: int | None = None

    def band_at(self, level: float) -> tuple[float, float] | None:
        """The central ``level`` interval of ``chi2 / dof`` at the floor (None when
        unknown, or when a stored test does not say its distribution)."""
        if self.band is None or not self.dof:
            return None
        if level == LEVEL:
            return self.band
        if self.distribution == "chi2":
            return chi2_band(self.dof if self.sd is None else 2.0 / self.sd**2, level)
        if self.distribution == "ratio" and self.rows is not None and self.sd is not None:
            return shared_ratio_band(self.rows, False, self.dof, self.sd, level)
        if self.distribution == "ratio":
            return ratio_band(int(round(self.dof)), False, level)
        if self.distribution == "normal" and self.sd is not None:
            return normal_band(self.sd, level)
        return None

    def to_dict(self) -> dict[str, Any]:
        """Plain data (``floor_tests`` of ``result.json``)."""
        return {"dataset": self.dataset, "constraints": list(self.constraints),
                "method": self.method, "chi2": self.chi2, "dof": self.dof,
                "chi2_dof": self.chi2_dof,
                "band": None if self.band is None else list(self.band),
                "verdict": self.verdict, "distribution": self.distribution, "sd": self.sd,
                "rows": self.rows}

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> DatasetTest:
        """Inverse of :meth:`to_dict`."""
        band = doc.get("band")
        return cls(str(doc["dataset"]), tuple(doc["constraints"]), str(doc["method"]),
                   doc.get("chi2"), doc.get("dof"),
                   None if band is None else (float(band[0]), float(band[1])),
                   # a document from before distributions were stored: a propagated
                   # test's is χ²; a combined one's cannot be known
                   str(doc.get("distribution", "chi2" if doc["method"] == PROPAGATED
                               else "")), doc.get("sd"), doc.get("rows"))


def family_level(count: int, level: float = LEVEL) -> float:
    """The level of each of ``count`` tests whose joint level is ``level`` (Šidák:
    ``level^(1/count)``)."""
    return level ** (1.0 / max(count, 1))


def family_bands(tests: tuple[DatasetTest, ...], level: float = LEVEL
                 ) -> tuple[tuple[float, float] | None, ...]:
    """Each dataset's band in the family-wise test of :func:`at_floor`: its own band at
    the Šidák level of the datasets whose test is known (None where unknown)."""
    known = [t for t in tests if t.verdict is not None]
    each = family_level(len(known), level)
    return tuple(t.band_at(each) if t.verdict is not None else None for t in tests)


def family_verdicts(tests: tuple[DatasetTest, ...], level: float = LEVEL
                    ) -> tuple[str | None, ...]:
    """Each dataset's verdict against its family-wise band (:func:`family_bands`); a
    stored test that cannot give that band keeps its own verdict."""
    bands = family_bands(tests, level)
    return tuple(t.verdict if b is None else verdict_of(t.chi2_dof, b)
                 for t, b in zip(tests, bands, strict=True))


def family_document(tests: tuple[DatasetTest, ...], level: float = LEVEL) -> dict[str, Any]:
    """How :func:`at_floor` decided, as plain data: ``{"correction": "Sidak", "level":
    0.95, "each": LEVEL_OF_EACH, "bands": {DATASET: [lo, hi] or None}}``."""
    known = sum(t.verdict is not None for t in tests)
    return {"correction": "Sidak", "level": level, "each": family_level(known, level),
            "bands": {t.dataset: None if b is None else list(b)
                      for t, b in zip(tests, family_bands(tests, level), strict=True)}}


#: The family-wise level of the constraints' own tests beside the datasets' joint tests
#: (:func:`alone_above`).
ALONE_LEVEL = 0.01


def alone_above(tests: Sequence[FloorTest], level: float = ALONE_LEVEL
                ) -> tuple[float | None, ...]:
    """For each constraint's own test (propagated floors), the upper bound its χ²/dof
    passed at ``level`` over them all (Bonferroni, the upper tail alone), or None where
    it did not.  A dataset's joint test weighs its constraints by their noise's
    correlation: a signal shared by constraints that share most of their noise (a load
    cell's creep, in the tare-plus-test-mass and the tare-plus-crane constraints that both
    read the cells) lies along their common noise and is diluted there, so that a new
    user's platform ended quiet with both constraints at 1.2 times their own floors on
    600 rows (p ≈ 1e-5 each) and the joint test inside its band.  A constraint far above
    its own floor is then not at the floor, whatever the joint test says."""
    known = [t for t in tests if t.method == PROPAGATED and t.chi2 is not None and t.dof]
    out: list[float | None] = []
    for t in tests:
        value = t.chi2_dof
        if not any(t is k for k in known) or value is None:
            out.append(None)
            continue
        nu = 2.0 / t.sd**2 if t.sd else float(t.dof or 0.0)
        upper = chi2_quantile(1.0 - level / len(known), nu) / nu
        out.append(upper if value > upper else None)
    return tuple(out)


def at_floor(tests: tuple[DatasetTest, ...], alone: Sequence[FloorTest] = ()
             ) -> bool | None:
    """Whether every dataset is at its floor, one decision at the level :data:`LEVEL` for
    the datasets together: False when one is above or below its family-wise band, or
    when a constraint's own test (``alone``) is above its floor at :data:`ALONE_LEVEL`
    over them all (:func:`alone_above`); None when one is unknown and none is off it.

    Each dataset's global test has its own 95 % band; with several datasets an exact
    model would fall outside one of them more often than one time in twenty (1 - 0.95^k
    for k independent datasets).  The decision takes each dataset's band at the level
    ``0.95^(1/k)`` (Šidák), k the datasets whose test is known: exact for independent
    tests, which the datasets' χ² nearly are (their noise is drawn apart and they share
    only the estimate, whose share each test's expectation already carries), and a
    little narrower than Bonferroni's ``1 - 0.05/k``, which is valid whatever the
    dependence but conservative.  The datasets are the family: each dataset's test
    already combines its constraints into one statistic (the joint χ² of their
    propagated covariance, or their own tests summed)."""
    verdicts = family_verdicts(tests)
    if any(v in ("above", "below") for v in verdicts) or \
            any(b is not None for b in alone_above(alone)):
        return False
    if not verdicts or any(v is None for v in verdicts):
        return None
    return True
