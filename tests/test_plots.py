"""Figures and the HTML page of a diagnosis document (symcal.report.plots, symcal.report.html)."""

from __future__ import annotations

import base64
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from symcal.report import plots
from symcal.report.html import html_report, write_html

ROOT = Path(__file__).resolve().parent.parent
RHO = 1.016
PNG = b"\x89PNG\r\n\x1a\n"
TEXT_REPORT = "Diagnosis of platen_self_calibration\n  1. s1.p_hat += harmonic 1 of s2.p  62 %\n"


def _series(rng: np.random.Generator, n: int, amp: float, noise: float, x_name: str) -> dict:
    x = np.sort(rng.uniform(0, 10 * RHO, n))
    after = amp * np.sin(2 * np.pi * 3 * x / RHO) + rng.normal(0, noise, n)
    before = after + 25 * np.sin(2 * np.pi * x / RHO) + 5 * x
    return {"x": {"name": x_name, "values": x.tolist()},
            "before": before.tolist(), "after": after.tolist()}


def _binned(variable: str, amp: float, eta2: float) -> list[dict]:
    centers = np.linspace(0.05, 0.95, 10)
    return [{"variable": variable, "centers": centers.tolist(),
             "mean": (amp * np.sin(2 * np.pi * 3 * centers)).tolist(),
             "sem": np.full(10, 0.2).tolist(), "eta2": eta2}]


def _periodogram(variable: str) -> dict:
    f = np.arange(1, 21, dtype=float)
    power = np.exp(-((f - 3.0) ** 2)) + 0.05
    return {"variable": variable, "period": RHO,
            "unit_text": f"cycles per tooth pitch of {variable}",
            "frequency": f.tolist(), "power": (power / power.max()).tolist(),
            "peak": {"frequency": 3.0, "text": f"3 cycles per tooth pitch of {variable}"}}


def _candidate(rank: int, label: str, share: float, significant: bool) -> dict:
    return {"rank": rank, "label": label, "delta_rss_share": share, "f_stat": 500 * share,
            "p_value": 10.0 ** (-40 * share), "significant": significant,
            "reduction": {"calibration/g_p": [4.1, 4.1 * (1 - share) ** 0.5]},
            "indistinguishable": ["s4.p_hat += harmonic 1 of s4.p"] if rank == 1 else [],
            "text": f"Adding {label} to the model would remove {100 * share:.0f} % & more.",
            "yaml": f"model: segment\noutputs:\n  p_hat: p + k{rank} * sin(3*2*pi*p/{RHO})\n"}


def make_doc() -> dict:
    """A realistic diagnosis document, JSON-compatible, with every edge case but one dataset."""
    rng = np.random.default_rng(7)
    names = [f"s{i}.k{j}" for i in range(1, 5) for j in range(3)] + ["o_x", "l<x>"]
    corr = np.clip(rng.normal(0, 0.4, (len(names), len(names))), -1, 1)
    corr = (corr + corr.T) / 2
    np.fill_diagonal(corr, 1.0)
    matrix = corr.tolist()
    matrix[0][3] = matrix[3][0] = None
    labels = ["s1.p_hat += harmonic 1 of s2.p", "s2.p_hat += k*(y < 0) ramp",
              "s3.p_hat += cost in $x_$ (not mathtext)"] + [
        f"s{1 + k % 4}.p_hat += harmonic {k} of t" for k in range(3, 12)]
    shares = np.linspace(0.62, 0.01, len(labels))
    return {
        "problem": "platen_self_calibration",
        "alpha": 0.01,
        "datasets": [{"name": "calibration", "n": 1000}, {"name": "fly by", "n": 400}],
        "residuals": [
            {"dataset": "calibration", "name": "g_p", "kind": "constraint", "unit": "um",
             "std_before": 29.3, "std_after": 4.1,
             "series": _series(rng, 1000, 4.0, 1.0, "y_ref"),
             "binned": _binned("phase of s2.p (mod 1.016 mm)", 4.0, 0.45),
             "periodogram": _periodogram("s2.p")},
            {"dataset": "calibration", "name": "theta_x", "kind": "comparison", "unit": "mrad",
             "std_before": 2.7, "std_after": 0.5,
             "series": _series(rng, 1000, 0.4, 0.2, "y_ref"),
             "binned": [], "periodogram": None},
            {"dataset": "fly by", "name": "g_p", "kind": "constraint", "unit": "um",
             "std_before": 12.3, "std_after": 2.0,
             "series": _series(rng, 400, 1.5, 1.0, "x_ref"),
             "binned": _binned("y_ref", 1.5, 0.2), "periodogram": _periodogram("s1.p")},
            {"dataset": "fly by", "name": "position_y", "kind": "comparison", "unit": "um",
             "std_before": 8.2, "std_after": 2.2, "binned": [], "periodogram": None},
        ],
        "candidates": [_candidate(k + 1, lab, float(s), k < 3)
                       for k, (lab, s) in enumerate(zip(labels, shares, strict=True))],
        "singular_values": np.logspace(2, -6, 36).tolist(),
        "correlation": {"names": names, "matrix": matrix},
    }


def make_minimal() -> dict:
    """One dataset, no candidates, no series, no periodogram, no singular values."""
    return {
        "problem": "tiny",
        "alpha": 0.05,
        "datasets": [{"name": "calibration", "n": 10}],
        "residuals": [{"dataset": "calibration", "name": "g", "kind": "constraint",
                       "unit": None, "std_before": 1.0, "std_after": 0.5, "binned": [],
                       "periodogram": None}],
        "candidates": [],
        "singular_values": [],
        "correlation": {"names": ["a", "b"], "matrix": [[1.0, None], [None, 1.0]]},
    }


@pytest.fixture(scope="module")
def doc() -> dict:
    return make_doc()


@pytest.fixture(scope="module")
def minimal() -> dict:
    return make_minimal()


@pytest.fixture(scope="module")
def page(doc: dict) -> str:
    return html_report(doc, TEXT_REPORT)


def test_document_is_json_compatible(doc: dict) -> None:
    assert json.loads(json.dumps(doc)) == doc


def test_figure_names(doc: dict, minimal: dict) -> None:
    assert plots.figure_names(doc) == [
        "residuals_calibration", "reference_calibration", "residuals_fly_by",
        "structure", "periodograms", "candidates", "singular_values", "correlation"]
    assert plots.figure_names(minimal) == ["candidates", "correlation"]
    assert list(plots.figure_captions(doc)) == plots.figure_names(doc)


@pytest.mark.slow
def test_save_figures_writes_every_figure_in_every_format(doc: dict, tmp_path: Path) -> None:
    out = tmp_path / "new" / "plots"
    written = plots.save_figures(doc, out, formats=plots.FORMATS)
    names = plots.figure_names(doc)
    assert list(written) == names
    expected = {out / f"{n}.{f}" for n in names for f in plots.FORMATS}
    assert {p for paths in written.values() for p in paths} == expected
    assert set(out.iterdir()) == expected          # nothing else, no temporary files
    umask = os.umask(0o022)
    os.umask(umask)
    assert {p.stat().st_mode & 0o777 for p in expected} == {0o666 & ~umask}
    for path in expected:
        data = path.read_bytes()
        assert len(data) > 500
        if path.suffix == ".png":
            assert data.startswith(PNG)
        elif path.suffix == ".svg":
            assert b"<svg" in data
        else:
            assert data.startswith(b"%PDF")


@pytest.mark.slow
def test_save_figures_edge_cases(minimal: dict, tmp_path: Path) -> None:
    written = plots.save_figures(minimal, tmp_path, formats=["png"])
    assert {k: [p.name for p in v] for k, v in written.items()} == {
        "candidates": ["candidates.png"], "correlation": ["correlation.png"]}


def test_unknown_format(doc: dict, tmp_path: Path) -> None:
    with pytest.raises(ValueError) as err:
        plots.save_figures(doc, tmp_path / "x", formats=["png", "jpg"])
    assert str(err.value) == "unknown plot format 'jpg'; choose from: png, svg, pdf"
    assert not (tmp_path / "x").exists()


def test_render_png(doc: dict, minimal: dict) -> None:
    data = plots.render_png(doc, "candidates")
    assert data.startswith(PNG)
    assert plots.render_png(minimal, "correlation").startswith(PNG)
    with pytest.raises(ValueError, match="unknown figure 'nope'; choose from: candidates"):
        plots.render_png(minimal, "nope")


def test_candidates_figure(doc: dict, minimal: dict) -> None:
    fig = plots.build_figure(doc, "candidates")
    (ax,) = fig.axes
    (bars,) = ax.containers
    assert len(bars) == plots.MAX_CANDIDATES < len(doc["candidates"])
    widths = [b.get_width() for b in bars]
    assert widths == pytest.approx([c["delta_rss_share"] for c in doc["candidates"][:10]])
    grey = [b.get_facecolor()[:3] == pytest.approx((0.65,) * 3) for b in bars]
    assert grey == [not c["significant"] for c in doc["candidates"][:10]]
    labels = [t.get_text() for t in ax.get_yticklabels()]
    assert labels[1] == "2. s2.p_hat += k*(y < 0) ramp"
    assert labels[2] == r"3. s3.p_hat += cost in \$x_\$ (not mathtext)"

    empty = plots.build_figure(minimal, "candidates")
    texts = [t.get_text() for ax in empty.axes for t in ax.texts]
    assert texts == ["no candidate effect is significant"]
    assert not any(ax.containers for ax in empty.axes)


def test_series_figures(doc: dict) -> None:
    fig = plots.build_figure(doc, "residuals_calibration")
    (ax,) = [a for a in fig.axes if a.get_visible()]      # g_p only: theta_x is a comparison
    before, after = ax.get_lines()[:2]
    series = doc["residuals"][0]["series"]
    np.testing.assert_allclose(after.get_xdata(), series["x"]["values"])
    np.testing.assert_allclose(after.get_ydata(), series["after"])
    np.testing.assert_allclose(before.get_ydata(), series["before"])
    assert ax.get_ylabel() == "g_p [µm]" and ax.get_xlabel() == "y_ref"
    assert "29.3" in before.get_label() and "4.1" in after.get_label()

    ref = plots.build_figure(doc, "reference_calibration")
    (ax,) = ref.axes
    assert ax.get_ylabel() == "theta_x − reference [mrad]"
    # position_y on "fly by" has no series, so it has no reference figure
    assert "reference_fly_by" not in plots.figure_names(doc)


def test_structure_and_periodograms(doc: dict) -> None:
    fig = plots.build_figure(doc, "structure")
    assert len(fig.axes) == 2
    assert "η² = 0.45" in fig.axes[0].get_title()
    line = fig.axes[0].get_lines()[0]
    np.testing.assert_allclose(line.get_ydata(), doc["residuals"][0]["binned"][0]["mean"])

    fig = plots.build_figure(doc, "periodograms")
    assert len(fig.axes) == 2
    (note,) = fig.axes[0].texts
    assert note.get_text() == "3 cycles per tooth pitch of s2.p"
    assert note.xy == pytest.approx((3.0, 1.0))


def test_correlation_and_singular_values(doc: dict) -> None:
    fig = plots.build_figure(doc, "correlation")
    ax = fig.axes[0]
    (im,) = ax.get_images()
    arr = im.get_array()
    n = len(doc["correlation"]["names"])
    assert arr.shape == (n, n)
    assert arr.mask[0, 3] and arr.mask[3, 0] and arr.mask.sum() == 2
    assert arr[1, 2] == pytest.approx(doc["correlation"]["matrix"][1][2])
    assert [t.get_text() for t in ax.get_xticklabels()][-1] == "l<x>"
    assert len(fig.axes) == 2                              # the colourbar

    fig = plots.build_figure(doc, "singular_values")
    (line,) = fig.axes[0].get_lines()
    np.testing.assert_allclose(line.get_ydata(), doc["singular_values"])
    assert fig.axes[0].get_yscale() == "log"


@pytest.mark.slow
def test_html_report(doc: dict, page: str) -> None:
    names = plots.figure_names(doc)
    assert page.count('<img src="data:image/png;base64,') == len(names)
    for chunk in page.split('<img src="data:image/png;base64,')[1:]:
        assert base64.b64decode(chunk.split('"', 1)[0]).startswith(PNG)
    assert page.count("<figcaption>") == len(names)
    assert "<h1>symcal diagnosis: platen_self_calibration</h1>" in page
    assert "s2.p_hat += k*(y &lt; 0) ramp" in page
    assert "(y < 0)" not in page
    assert "l<x>" not in page
    yaml = doc["candidates"][0]["yaml"]
    assert f"<pre>{yaml}</pre>" in page
    assert f"<pre>{doc['candidates'][3]['yaml']}</pre>" not in page   # only the top three
    assert "would remove 62 % &amp; more." in page
    assert page.rstrip().endswith(f"<pre>{TEXT_REPORT}</pre>\n</body>\n</html>")
    assert "<td>fly by</td><td>position_y</td><td>comparison</td>" in page
    for bad in ("http://", "https://", "<script"):
        assert bad not in page


def test_html_report_minimal(minimal: dict) -> None:
    page = html_report(minimal, "x < y", title="My <title>")
    assert "<title>My &lt;title&gt;</title>" in page
    assert page.count('<img src="data:image/png;base64,') == 2
    assert "No candidate effect is significant." in page
    assert "<pre>x &lt; y</pre>" in page


@pytest.mark.slow
def test_write_html(doc: dict, page: str, tmp_path: Path) -> None:
    target = tmp_path / "out" / "report.html"
    assert write_html(doc, TEXT_REPORT, target) == target
    assert target.read_text(encoding="utf-8") == page
    assert list(target.parent.iterdir()) == [target]


def test_import_does_not_import_matplotlib() -> None:
    code = ("import sys, symcal.report.plots, symcal.report.html; "
            "sys.exit(1 if any(m.split('.')[0] == 'matplotlib' for m in sys.modules) else 0)")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
