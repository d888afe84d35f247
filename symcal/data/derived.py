"""Derived columns: columns a problem computes from others when a dataset is loaded.

A column declared ``rate_of: SOURCE`` (``columns: {psi_x_rate: {rate_of: psi_x, unit:
rad/s}}``) is the time derivative of ``SOURCE`` against the problem's time column
(``role: time``), by central differences on the actual time stamps (second order, also
where the spacing varies) and one-sided differences at the first and last rows.  Time must
increase strictly; a dataset where it does not is refused, naming the first row where it
does not.  Values are in the rate column's declared unit.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from symcal.base.errors import DataError
from symcal.base.units import size
from symcal.data.dataset import Dataset, rows_text
from symcal.language.problem_file import ColumnSpec


def rate_columns(specs: Mapping[str, ColumnSpec]) -> dict[str, ColumnSpec]:
    """The derived columns (``rate_of``) among ``specs``, by name."""
    return {k: c for k, c in specs.items() if c.rate_of}


def time_column(specs: Mapping[str, ColumnSpec]) -> ColumnSpec | None:
    """The column declared ``role: time``, or None."""
    return next((c for c in specs.values() if c.role == "time"), None)


def sources(specs: Mapping[str, ColumnSpec], names: list[str]) -> list[str]:
    """``names`` with every derived column replaced by what it is computed from (its
    source and the time column), each once, in order."""
    rates = rate_columns(specs)
    time = time_column(specs)
    out: list[str] = []
    for name in names:
        spec = rates.get(name)
        for col in ([spec.rate_of, time.name] if spec is not None and time is not None
                    else [name]):
            if col not in out:
                out.append(col)
    return out


#: The rate of a column with declared noise is smoothed until the noise it carries is at
#: most this share of its variance: a delay fitted to it is then attenuated by at most
#: about this much (errors in variables: central differences of a GNSS height with 0.5 m
#: noise at 10 Hz left a third of a 0.3 s delay).
ATTENUATION = 0.01
#: The widest window a rate is smoothed over, as a share of the rows.
WIDEST = 0.1


def rate(values: np.ndarray, time: np.ndarray, noise: float | None = None) -> np.ndarray:
    """d values / d time, in the units of ``values`` per unit of ``time``: central
    differences (one-sided at the ends), or, where the column's declared ``noise`` (its
    standard deviation, in the units of ``values``) would leave the rate with more than
    :data:`ATTENUATION` of its variance in noise, the least-squares slope over the
    narrowest window of rows about each row (shifted to fit at the ends) that does not,
    at most :data:`WIDEST` of the rows.

    Raises
    ------
    ValueError
        With fewer than two rows.
    """
    return rate_and_noise(values, time, noise)[0]


def rate_and_noise(values: np.ndarray, time: np.ndarray, noise: float | None = None
                   ) -> tuple[np.ndarray, float]:
    """:func:`rate`, and the root mean square of the noise ``noise`` leaves in it (0
    without a declared noise): ``noise / sqrt(Σ(t - mean)²)`` of each row's window,
    ``noise / (√2 dt)`` for central differences at a constant step."""
    if len(values) < 2:
        raise ValueError("a rate needs at least two rows")
    v = np.asarray(values, dtype=float)
    t = np.asarray(time, dtype=float)
    central = np.gradient(v, t, edge_order=1)
    n = len(v)
    if noise is None or not noise > 0 or not np.all(np.isfinite(v)):
        return central, 0.0
    if n < 7:
        return central, float(noise * np.sqrt(np.mean(2 / np.diff(t) ** 2)) / 2)
    widest = max(3, int(WIDEST * n) | 1)
    half = 1
    while True:
        slope, spread = _slope(v, t, half)
        left = float(np.mean(noise**2 / spread))
        if left <= ATTENUATION * float(np.var(slope)):
            return (central if half == 1 else slope), float(np.sqrt(left))
        if 2 * half + 1 >= widest:
            return slope, float(np.sqrt(left))
        half = min(max(half + 1, int(half * 1.5)), (widest - 1) // 2)


def _slope(v: np.ndarray, t: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares slope of ``v`` against ``t`` over a window of ``2 half + 1``
    rows about each row (shifted to fit at the ends), and each window's Σ(t - mean)²
    (the slope's noise variance is the column's over it)."""
    n, w = len(v), 2 * half + 1
    tc = t - float(np.mean(t))
    start = np.clip(np.arange(n) - half, 0, n - w)

    def window(x: np.ndarray) -> np.ndarray:
        c = np.concatenate([[0.0], np.cumsum(x)])
        return c[start + w] - c[start]

    st, sv = window(tc), window(v)
    spread = window(tc * tc) - st * st / w
    return (window(tc * v) - st * sv / w) / spread, spread


def with_derived(specs: Mapping[str, ColumnSpec], data: Dataset,
                 needed: list[str] | None = None,
                 noise: Mapping[str, float] | None = None) -> Dataset:
    """``data`` with every derived column it can compute (its source is in the data)
    computed anew; unchanged without derived columns.

    Parameters
    ----------
    specs
        The problem's columns (``Problem.column_specs``).
    data
        A loaded dataset.
    needed
        Columns the problem reads: a derived one among them whose source is absent is
        refused (the others are computed where they can be).
    noise
        The declared noise of source columns (standard deviation, in the column's unit):
        their rates are smoothed where it would leave them noisy (:func:`rate`).

    Raises
    ------
    DataError
        A needed source missing, no time column in the data, time that does not
        increase strictly, fewer than two rows, or a rate that is not finite.
    """
    rates = rate_columns(specs)
    if not rates:
        return data
    time = time_column(specs)
    columns = dict(data.columns)
    computed = False
    for name, spec in rates.items():
        want = needed is None or name in needed
        if spec.rate_of not in columns or time is None or time.name not in columns:
            if want and needed is not None and name not in columns:
                missing = spec.rate_of if spec.rate_of not in columns else \
                    (time.name if time is not None else "(no time column)")
                raise DataError(f"{data.source}: column '{name}' is the rate of "
                                f"'{spec.rate_of}' against time '{time.name if time else ''}'"
                                f", but the data have no column '{missing}'")
            continue
        t = np.asarray(columns[time.name], dtype=float)
        steps = np.diff(t)
        if len(t) < 2:
            raise DataError(f"{data.source}: column '{name}' is a rate, which needs at least "
                            "two rows")
        if not np.all(steps > 0):
            bad = np.flatnonzero(~(steps > 0)) + 1
            raise DataError(f"{data.source}: column '{name}' is the rate of '{spec.rate_of}' "
                            f"in time '{time.name}', but time does not increase at "
                            f"{rows_text(columns, bad)}: a rate needs time-ordered rows")
        # in the rate column's unit: source's and time's sizes over the rate's
        factor = size(columns_unit(specs, spec.rate_of)) / size(time.unit) / size(spec.unit)
        values = rate(columns[spec.rate_of], t, (noise or {}).get(spec.rate_of)) * factor
        if not np.all(np.isfinite(values)):
            bad = np.flatnonzero(~np.isfinite(values))
            raise DataError(f"{data.source}: the rate '{name}' is not finite at "
                            f"{rows_text(columns, bad)}")
        values.setflags(write=False)
        columns[name] = values
        computed = True
    if not computed:
        return data
    return Dataset(data.name, data.source, columns, data.dropped)


def columns_unit(specs: Mapping[str, ColumnSpec], name: str) -> str:
    """The declared unit of column ``name`` ("" when none is declared)."""
    spec = specs.get(name)
    return spec.unit if spec is not None else ""
