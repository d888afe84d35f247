"""Figures of a diagnosis document.

The input is the plain-data diagnosis document (dicts, lists, floats, strings) that
``symcal diagnose`` produces (:func:`symcal.report.text.diagnosis_document`). Plots never
solve: every number drawn here is read from the document; the only transforms are the
ones drawing needs (``None`` to NaN, picking the top entries of a ranked list, locating a
peak's ordinate for its annotation, and drawing a variable in its display unit: a
variable's values are in internal units and its ``unit`` says what it was declared in, so
an angle in rad is drawn in mrad; see :func:`symcal.base.units.axis_unit`).

A residual is never shown to vary with a variable it contains whole (its ``contains``
list, else its own name): a comparison ``theta_x`` against the expression ``theta_x``.

matplotlib is imported lazily, inside the functions that draw, so ``import symcal.report.plots``
does not import it. Figures are plain :class:`matplotlib.figure.Figure` objects drawn on an
Agg canvas: they never touch pyplot, its global state or the user's chosen backend, so they
work headless and nothing is left open after saving.
"""

from __future__ import annotations

import io
import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from symcal.base.files import atomic_write_bytes
from symcal.base.units import DISPLAY_UNITS, axis_unit, symbol

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

FORMATS = ("png", "svg", "pdf")
DPI = 110
MAX_CANDIDATES = 10
MAX_NAMED_PARAMETERS = 40
MAX_LABEL = 70
RASTERIZE_ABOVE = 5000
MAX_X_TICKS = 6
BEFORE_COLOUR = "0.72"
AFTER_COLOUR = "tab:blue"
REFERENCE_COLOUR = "tab:red"
SIGNIFICANT_COLOUR = "tab:blue"
NOT_SIGNIFICANT_COLOUR = "0.65"
UNDEFINED_COLOUR = "0.82"
NO_CANDIDATE_TEXT = "no candidate effect is significant"

Doc = Mapping[str, Any]


@dataclass(frozen=True)
class _Spec:
    """One figure: its file name, a caption, and how to draw it."""

    name: str
    caption: str
    build: Callable[[], Figure]


# ----------------------------------------------------------------------------- public API


def figure_names(doc: Doc) -> list[str]:
    """Names of the figures :func:`save_figures` would write for ``doc``.

    Parameters
    ----------
    doc
        The diagnosis document.

    Returns
    -------
    list of str
        Figure names, already sanitised to ``[A-Za-z0-9_-]``, in drawing order. A file is
        ``<name>.<format>``.
    """
    return [s.name for s in _specs(doc)]


def figure_captions(doc: Doc) -> dict[str, str]:
    """One-sentence caption of each figure of ``doc``, keyed by figure name.

    Parameters
    ----------
    doc
        The diagnosis document.

    Returns
    -------
    dict
        Figure name to caption (plain text, not escaped), in the order of
        :func:`figure_names`.
    """
    return {s.name: s.caption for s in _specs(doc)}


def build_figure(doc: Doc, name: str) -> Figure:
    """Draw one figure of ``doc`` and return it (for inspection or custom saving).

    Parameters
    ----------
    doc
        The diagnosis document.
    name
        One of :func:`figure_names`.

    Returns
    -------
    matplotlib.figure.Figure
        A figure on an Agg canvas, not registered with pyplot.

    Raises
    ------
    ValueError
        If ``doc`` has no figure called ``name``.
    """
    specs = {s.name: s for s in _specs(doc)}
    if name not in specs:
        raise ValueError(f"unknown figure '{name}'; choose from: {', '.join(specs)}")
    return specs[name].build()


def save_figures(
    doc: Doc, outdir: str | Path, formats: Sequence[str] = ("png",),
) -> dict[str, list[Path]]:
    """Write every figure of ``doc`` in every format to ``outdir``.

    Parameters
    ----------
    doc
        The diagnosis document.
    outdir
        Directory for the files; created if missing. Each file is written through a
        temporary file and a rename.
    formats
        Any of :data:`FORMATS` (case-insensitive; repeats are written once).

    Returns
    -------
    dict
        Figure name to the paths written for it, in the order of ``formats``.

    Raises
    ------
    ValueError
        For a format not in :data:`FORMATS`, before anything is written.
    """
    fmts = _check_formats(formats)
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    written: dict[str, list[Path]] = {}
    for spec in _specs(doc):
        fig = spec.build()
        try:
            paths = []
            for fmt in fmts:
                path = outdir / f"{spec.name}.{fmt}"
                atomic_write_bytes(path, _render(fig, fmt))
                paths.append(path)
            written[spec.name] = paths
        finally:
            fig.clear()
    return written


def render_png(doc: Doc, name: str) -> bytes:
    """Render one figure of ``doc`` as PNG bytes (for embedding in HTML).

    Parameters
    ----------
    doc
        The diagnosis document.
    name
        One of :func:`figure_names`.

    Returns
    -------
    bytes
        The PNG file's content.

    Raises
    ------
    ValueError
        If ``doc`` has no figure called ``name``.
    """
    fig = build_figure(doc, name)
    try:
        return _render(fig, "png")
    finally:
        fig.clear()


# ----------------------------------------------------------------------------- helpers


def _check_formats(formats: Sequence[str]) -> list[str]:
    if isinstance(formats, str):
        formats = [formats]
    out: list[str] = []
    for fmt in formats:
        key = str(fmt).lower()
        if key not in FORMATS:
            raise ValueError(f"unknown plot format '{fmt}'; choose from: {', '.join(FORMATS)}")
        if key not in out:
            out.append(key)
    return out


def _render(fig: Figure, fmt: str) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format=fmt, dpi=DPI, metadata=_metadata(fmt))
    return buf.getvalue()


def _metadata(fmt: str) -> dict[str, Any]:
    # No creation dates, so the same document gives the same bytes.
    if fmt == "svg":
        return {"Date": None}
    if fmt == "pdf":
        return {"CreationDate": None, "ModDate": None}
    return {}


def sanitise(name: str) -> str:
    """``name`` with every character outside ``[A-Za-z0-9_-]`` replaced by ``_``."""
    return re.sub(r"[^A-Za-z0-9_-]", "_", str(name)) or "_"


def _text(value: Any, limit: int | None = None) -> str:
    """Document text made safe for matplotlib (no mathtext), optionally shortened."""
    s = str(value)
    if limit is not None and len(s) > limit:
        s = s[: limit - 1] + "…"
    return s.replace("$", r"\$")


def _floats(values: Any) -> Any:
    """A float array with ``None`` as NaN."""
    import numpy as np

    if values is None:
        return np.zeros(0)
    return np.array([np.nan if v is None else v for v in values], dtype=float).ravel()


def _num(x: Any, fmt: str = ".4g") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "—"
    return format(x, fmt)


def _new_figure(width: float, height: float) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _grid(fig: Figure, n: int, max_cols: int = 2) -> list[Axes]:
    ncols = 1 if n <= 3 else min(max_cols, n)
    nrows = math.ceil(n / ncols)
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel().tolist()
    for ax in axes[n:]:
        ax.set_visible(False)
    return axes[:n]


def _unit(row: Mapping[str, Any]) -> str:
    unit = row.get("unit")
    return "internal units" if not unit or unit == "(internal)" else symbol(str(unit))


def _axis_values(values: Any, name: Any, unit: Any) -> tuple[Any, str]:
    """A variable's values in its display unit, and the axis label that says it."""
    xs = _floats(values)
    shown = axis_unit(str(unit) if unit else "")
    if shown in ("", "1"):
        return xs, _text(name, 60)
    return xs / DISPLAY_UNITS[shown], f"{_text(name, 60)} [{symbol(shown)}]"


def _findings(row: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    """The row's binned structure but along variables it contains whole (and their
    phases)."""
    own = [str(n) for n in row.get("contains") or [row.get("name")]]

    def contained(variable: str) -> bool:
        return variable in own or any(variable.startswith(f"phase of {n} (") for n in own)

    return [b for b in row.get("binned") or []
            if isinstance(b, Mapping) and not contained(str(b.get("variable")))]


def _few_x_ticks(ax: Axes) -> None:
    """At most :data:`MAX_X_TICKS` ticks on the x axis, so labels never overlap."""
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(nbins=MAX_X_TICKS, steps=[1, 2, 2.5, 5, 10]))


def _where(row: Mapping[str, Any]) -> str:
    return f"{row.get('dataset', '?')}/{row.get('name', '?')}"


def _has_series(row: Mapping[str, Any]) -> bool:
    series = row.get("series")
    if not isinstance(series, Mapping):
        return False
    x = series.get("x")
    return (isinstance(x, Mapping) and bool(x.get("values"))
            and bool(series.get("after") or series.get("before")))


def _datasets(doc: Doc) -> list[str]:
    names = [str(d.get("name")) for d in doc.get("datasets") or [] if isinstance(d, Mapping)]
    for row in doc.get("residuals") or []:
        if str(row.get("dataset")) not in names:
            names.append(str(row.get("dataset")))
    return names


def _unique(name: str, taken: set[str]) -> str:
    base, k = sanitise(name), 2
    out = base
    while out in taken:
        out, k = f"{base}_{k}", k + 1
    taken.add(out)
    return out


def _specs(doc: Doc) -> list[_Spec]:
    """The figures ``doc`` calls for, in drawing order."""
    specs: list[_Spec] = []
    taken: set[str] = set()
    residuals = [r for r in doc.get("residuals") or [] if isinstance(r, Mapping)]
    worse = frozenset((str(g.get("dataset")), str(g.get("name")))
                      for g in doc.get("regressions") or [] if isinstance(g, Mapping))
    for ds in _datasets(doc):
        mine = [r for r in residuals if str(r.get("dataset")) == ds and _has_series(r)]
        cons = [r for r in mine if r.get("kind", "constraint") != "comparison"]
        comp = [r for r in mine if r.get("kind") == "comparison"]
        if cons:
            specs.append(_Spec(
                _unique(f"residuals_{ds}", taken),
                f"Dataset {ds}: constraint residuals before (grey) and after (colour) "
                "calibration along the variable each moves along most.",
                partial(_residuals_figure, ds, cons, worse)))
        if comp:
            specs.append(_Spec(
                _unique(f"reference_{ds}", taken),
                f"Dataset {ds}: error against the reference sensor before (grey) and after "
                "(colour) calibration.",
                partial(_reference_figure, ds, comp, worse)))
    binned = [r for r in residuals if _findings(r)]
    if binned:
        specs.append(_Spec(
            _unique("structure", taken),
            "Mean residual (± standard error) in bins of the variable along which each "
            "residual shows most structure (never a variable the residual contains whole); "
            "η² is the share of variance the bin means explain.",
            partial(_structure_figure, binned)))
    periodic = [r for r in residuals if isinstance(r.get("periodogram"), Mapping)
                and r["periodogram"].get("frequency")]
    if periodic:
        specs.append(_Spec(
            _unique("periodograms", taken),
            "Normalised periodogram of each residual, with its strongest peak marked.",
            partial(_periodogram_figure, periodic)))
    cands = [c for c in doc.get("candidates") or [] if isinstance(c, Mapping)]
    specs.append(_Spec(
        _unique("candidates", taken),
        f"Share of the residual sum of squares each of the top {MAX_CANDIDATES} candidate "
        "effects would remove; significant candidates in colour." if cands
        else "No candidate effect to rank.",
        partial(_candidates_figure, cands)))
    sv = doc.get("singular_values") or []
    if len(sv):
        specs.append(_Spec(
            _unique("singular_values", taken),
            "Singular values of the scaled Jacobian at the estimate, largest first.",
            partial(_singular_values_figure, sv)))
    corr = doc.get("correlation")
    if isinstance(corr, Mapping) and corr.get("names"):
        specs.append(_Spec(
            _unique("correlation", taken),
            "Correlation matrix of the parameter estimates (grey where undefined).",
            partial(_correlation_figure, corr)))
    return specs


# ----------------------------------------------------------------------------- figures


def _series_axes(ax: Axes, row: Mapping[str, Any], after_colour: str, legend: str,
                 worse: bool = False) -> None:
    series = row["series"]
    x, xlabel = _axis_values(series["x"].get("values"), series["x"].get("name", "x"),
                             series["x"].get("unit"))
    raster = len(x) > RASTERIZE_ABOVE
    unit = _unit(row)
    for key, colour, std in (("before", BEFORE_COLOUR, row.get("std_before")),
                             ("after", after_colour, row.get("std_after"))):
        y = _floats(series.get(key))
        if len(y) != len(x) or not len(y):
            continue
        note = "; worse than before" if worse and key == "after" else ""
        ax.plot(x, y, ".", ms=2.5, color=colour, rasterized=raster,
                label=f"{key} (std {_num(std)} {_text(unit)}{note})")
    ax.axhline(0.0, color="0.3", lw=0.6)
    ax.set_xlabel(xlabel)
    _few_x_ticks(ax)
    ax.set_ylabel(f"{_text(legend)} [{_text(unit)}]")
    # above the axes, not over the points
    ax.legend(loc="lower right", bbox_to_anchor=(1.0, 1.0), ncol=2, fontsize="small",
              markerscale=3, frameon=False, borderaxespad=0.1)
    ax.grid(True, alpha=0.3)


def _worse(row: Mapping[str, Any], worse: frozenset[tuple[str, str]]) -> bool:
    return (str(row.get("dataset")), str(row.get("name"))) in worse


def _residuals_figure(ds: str, rows: list[Mapping[str, Any]],
                      worse: frozenset[tuple[str, str]] = frozenset()) -> Figure:
    fig = _new_figure(7.5, 0.8 + 2.3 * len(rows))
    axes = fig.subplots(len(rows), 1, squeeze=False)[:, 0]
    for ax, row in zip(axes, rows, strict=True):
        _series_axes(ax, row, AFTER_COLOUR, str(row.get("name", "?")), _worse(row, worse))
    fig.suptitle(_text(f"Dataset {ds}: constraint residuals before and after calibration"))
    return fig


def _reference_figure(ds: str, rows: list[Mapping[str, Any]],
                      worse: frozenset[tuple[str, str]] = frozenset()) -> Figure:
    fig = _new_figure(7.5, 0.8 + 2.3 * len(rows))
    axes = fig.subplots(len(rows), 1, squeeze=False)[:, 0]
    for ax, row in zip(axes, rows, strict=True):
        _series_axes(ax, row, REFERENCE_COLOUR, f"{row.get('name', '?')} − reference",
                     _worse(row, worse))
    fig.suptitle(_text(f"Dataset {ds}: error against the reference"))
    return fig


def _structure_figure(rows: list[Mapping[str, Any]]) -> Figure:
    ncols = 1 if len(rows) <= 3 else 2
    fig = _new_figure(6.5 if ncols == 1 else 10.0, 0.6 + 2.5 * math.ceil(len(rows) / ncols))
    for ax, row in zip(_grid(fig, len(rows)), rows, strict=True):
        top = _findings(row)[0]
        centers, xlabel = _axis_values(top.get("centers"), top.get("variable", "?"),
                                       top.get("unit"))
        mean, sem = (_floats(top.get(k)) for k in ("mean", "sem"))
        yerr = sem if len(sem) == len(mean) else None
        ax.errorbar(centers, mean, yerr=yerr, fmt="o-", ms=3.5, lw=1, capsize=2,
                    color=AFTER_COLOUR)
        ax.axhline(0.0, color="0.3", lw=0.6)
        ax.set_title(_text(f"{_where(row)} (η² = {_num(top.get('eta2'), '.2f')})", 60),
                     fontsize="medium")
        ax.set_xlabel(xlabel)
        _few_x_ticks(ax)
        ax.set_ylabel(f"mean residual [{_text(_unit(row))}]")
        ax.grid(True, alpha=0.3)
    fig.suptitle("Structure left in the residuals")
    return fig


def _periodogram_figure(rows: list[Mapping[str, Any]]) -> Figure:
    import numpy as np

    ncols = 1 if len(rows) <= 3 else 2
    fig = _new_figure(6.5 if ncols == 1 else 10.0, 0.6 + 2.3 * math.ceil(len(rows) / ncols))
    for ax, row in zip(_grid(fig, len(rows)), rows, strict=True):
        pg = row["periodogram"]
        f, p = _floats(pg.get("frequency")), _floats(pg.get("power"))
        if len(f) == len(p):
            ax.plot(f, p, "-", lw=1, color=AFTER_COLOUR)
        peak = pg.get("peak")
        if isinstance(peak, Mapping) and peak.get("frequency") is not None and len(f) == len(p):
            fp = float(peak["frequency"])
            i = int(np.nanargmin(np.abs(f - fp))) if np.isfinite(f).any() else 0
            yp = p[i] if np.isfinite(p[i]) else 0.0
            ax.axvline(fp, color="tab:red", lw=0.8, ls="--")
            finite = f[np.isfinite(f)]
            right = bool(len(finite)) and fp > 0.5 * (float(finite.min()) + float(finite.max()))
            ax.annotate(_text(peak.get("text", f"peak at {fp:g}"), 60), xy=(fp, yp),
                        xytext=(-8 if right else 8, -4), textcoords="offset points",
                        va="top", ha="right" if right else "left", fontsize="small",
                        color="tab:red")
        ax.set_title(_text(f"{_where(row)} along {pg.get('variable', '?')}", 90),
                     fontsize="medium")
        unit_text = str(pg.get("unit_text") or "")
        ax.set_xlabel(_text(f"cycles {unit_text}" if unit_text.startswith("per ")
                            else unit_text or "frequency", 70))
        ax.set_ylabel("normalised power")
        ax.set_ylim(bottom=0.0)
        ax.grid(True, alpha=0.3)
    fig.suptitle("Periodograms of the residuals")
    return fig


def _candidates_figure(cands: list[Mapping[str, Any]]) -> Figure:
    top = cands[:MAX_CANDIDATES]
    if not top:
        fig = _new_figure(6.0, 2.0)
        ax = fig.subplots()
        ax.set_axis_off()
        ax.text(0.5, 0.5, NO_CANDIDATE_TEXT, ha="center", va="center", fontsize="large",
                transform=ax.transAxes)
        return fig
    fig = _new_figure(8.5, 1.0 + 0.38 * len(top))
    ax = fig.subplots()
    shares = _floats([c.get("delta_rss_share") for c in top])
    labels = [_text(f"{c.get('rank', k + 1)}. {c.get('label', '?')}", MAX_LABEL)
              for k, c in enumerate(top)]
    colours = [SIGNIFICANT_COLOUR if c.get("significant") else NOT_SIGNIFICANT_COLOUR
               for c in top]
    ypos = list(range(len(top)))
    ax.barh(ypos, shares, color=colours, height=0.7)
    ax.set_yticks(ypos, labels, fontsize="small")
    ax.invert_yaxis()
    for y, s in zip(ypos, shares, strict=True):
        if math.isfinite(s):
            ax.text(s, y, f" {100 * s:.1f} %", va="center", fontsize="x-small")
    ax.set_xlim(0.0, max(1.0, float(max((s for s in shares if math.isfinite(s)), default=0))))
    ax.set_xlabel("share of the residual sum of squares removed")
    ax.set_title("Candidate effects (colour: significant, grey: not)")
    ax.grid(True, axis="x", alpha=0.3)
    return fig


def _singular_values_figure(values: Sequence[Any]) -> Figure:
    import numpy as np

    sv = _floats(values)
    sv = np.where(sv > 0, sv, np.nan)
    fig = _new_figure(6.0, 3.2)
    ax = fig.subplots()
    ax.semilogy(np.arange(1, len(sv) + 1), sv, "o-", ms=3.5, lw=1, color=AFTER_COLOUR)
    ax.set_xlabel("index")
    ax.set_ylabel("singular value")
    ax.set_title("Singular values of the scaled Jacobian")
    ax.grid(True, which="both", alpha=0.3)
    return fig


def _correlation_matrix(corr: Mapping[str, Any], n: int) -> Any:
    import numpy as np

    m = np.full((n, n), np.nan)
    for i, row in enumerate((corr.get("matrix") or [])[:n]):
        vals = _floats(row)[:n]
        m[i, : len(vals)] = vals
    return np.ma.masked_invalid(m)


def _correlation_figure(corr: Mapping[str, Any]) -> Figure:
    import matplotlib

    names = [str(n) for n in corr["names"]]
    n = len(names)
    m = _correlation_matrix(corr, n)
    side = min(11.0, 4.0 + 0.17 * n)
    fig = _new_figure(side + 1.2, side)
    ax = fig.subplots()
    cmap = matplotlib.colormaps["RdBu_r"].with_extremes(bad=UNDEFINED_COLOUR)
    im = ax.imshow(m, cmap=cmap, vmin=-1.0, vmax=1.0, interpolation="nearest")
    fig.colorbar(im, ax=ax, shrink=0.8, label="correlation")
    if n <= MAX_NAMED_PARAMETERS:
        size = 8 if n <= 20 else 6
        ticks = list(range(n))
        ax.set_xticks(ticks, [_text(s, 24) for s in names], rotation=90, fontsize=size)
        ax.set_yticks(ticks, [_text(s, 24) for s in names], fontsize=size)
    else:
        ax.set_xlabel("parameter index")
        ax.set_ylabel("parameter index")
    ax.set_title("Correlation of the estimates")
    return fig


# ----------------------------------------------------------------------- experiment design


def design_figure(motions: Mapping[str, Mapping[str, Any]],
                  units: Mapping[str, str] | None = None) -> Figure:
    """The designed motion beside the given one (``symcal design``).

    Parameters
    ----------
    motions
        ``{"given": states, "designed": states}``, each with every state of the run per
        observation, in its unit.
    units
        The unit of each state (for the axes).

    Returns
    -------
    Figure
        One panel per state that changes over the run: the histogram of its values in
        both motions.
    """
    import numpy as np

    units = dict(units or {})
    given = next(iter(motions.values()))
    moving = [k for k in given
              if any(np.ptp(_floats(m[k])) > 0 for m in motions.values() if len(m[k]))]
    moving = moving[:6] or list(given)[:1]
    fig = _new_figure(3.7 * len(moving), 3.6)
    axes = np.atleast_1d(fig.subplots(1, len(moving)))
    for ax, key in zip(axes, moving, strict=True):
        values = [_floats(m[key]) for m in motions.values()]
        low = min(float(np.min(v)) for v in values if v.size)
        high = max(float(np.max(v)) for v in values if v.size)
        if high <= low:
            low, high = low - 0.5, high + 0.5
        for (label, poses), colour in zip(motions.items(), (BEFORE_COLOUR, AFTER_COLOUR),
                                          strict=False):
            ax.hist(_floats(poses[key]), bins=30, range=(low, high), alpha=0.7,
                    color=colour, label=_text(f"{label} ({len(poses[key])})"))
        unit = units.get(key, "")
        ax.set_xlabel(_text(f"{key} ({unit})" if unit else key))
        ax.set_ylabel("observations")
        ax.legend()
    return fig


def save_design_figure(motions: Mapping[str, Mapping[str, Any]], path: str | Path,
                       units: Mapping[str, str] | None = None) -> Path:
    """Write :func:`design_figure` to ``path`` (its suffix is the format: png, svg, pdf)."""
    fmt = _check_formats([Path(path).suffix.lstrip(".") or "png"])[0]
    fig = design_figure(motions, units)
    try:
        return atomic_write_bytes(path, _render(fig, fmt))
    finally:
        fig.clear()
