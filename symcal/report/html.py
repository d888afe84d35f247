"""One self-contained HTML page of a diagnosis document.

The page needs no external resource and no JavaScript: styles are inline and every figure
is a PNG embedded as a ``data:`` URI. All text from the document is escaped. Like
:mod:`symcal.report.plots`, this module only presents the document; it computes nothing.

The page opens with the verdict: the lines given, else the document's ``verdict``, else
the last ``Verdict`` block of the text report (what :func:`symcal.report.text.text_report` and
:func:`symcal.report.text.diagnosis_report` print first).
"""

from __future__ import annotations

import base64
import math
from collections.abc import Mapping, Sequence
from html import escape
from pathlib import Path
from typing import Any

from symcal.base.files import atomic_write_bytes
from symcal.base.units import symbol
from symcal.report.plots import Doc, figure_captions, render_png

TOP_DETAILED = 3

_STYLE = """
body { font-family: sans-serif; margin: 2em auto; max-width: 70em; padding: 0 1em;
       color: #222; line-height: 1.4; }
h1 { font-size: 1.6em; } h2 { font-size: 1.3em; margin-top: 2em; } h3 { font-size: 1.1em; }
table { border-collapse: collapse; margin: 0.5em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; vertical-align: top; }
th { background: #f0f0f0; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
tr.significant td { background: #eef5ff; }
pre { background: #f7f7f7; border: 1px solid #ddd; padding: 0.7em; overflow-x: auto;
      font-size: 0.88em; }
figure { margin: 1.5em 0; }
figure img { max-width: 100%; height: auto; border: 1px solid #eee; }
figcaption { font-size: 0.9em; color: #444; }
.meta { color: #555; }
section.verdict { background: #f4f8ff; border: 1px solid #b9cdf0; padding: 0.4em 1em;
                  margin: 1em 0; }
section.verdict h2 { margin-top: 0.4em; }
section.verdict li.bad, tr.worse td { color: #a40000; }
section.verdict li.bad { font-weight: bold; }
""".strip()


def html_report(doc: Doc, text_report: str, title: str | None = None,
                verdict: Sequence[str] | None = None) -> str:
    """Render the diagnosis as one self-contained HTML page.

    Parameters
    ----------
    doc
        The diagnosis document.
    text_report
        The plain-text report, shown in full at the end of the page.
    title
        Page title; ``"symcal diagnosis: <problem>"`` by default.
    verdict
        The verdict's lines (default: the document's ``verdict``, else the last
        ``Verdict`` block of ``text_report``).

    Returns
    -------
    str
        The HTML page: the verdict, residual summary (with noise floors and regressions
        where the document has them), ranked candidates (with text and YAML of the top
        three), every figure of :func:`symcal.report.plots.figure_names` as an embedded PNG with a
        caption, and the text report.
    """
    problem = str(doc.get("problem") or "problem")
    title = title if title is not None else f"symcal diagnosis: {problem}"
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en">',
        "<head>",
        '<meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{escape(title)}</title>",
        f"<style>\n{_STYLE}\n</style>",
        "</head>",
        "<body>",
        f"<h1>{escape(title)}</h1>",
        *_meta(doc, problem),
        *_verdict(_verdict_lines(doc, text_report, verdict)),
        *_residual_table(doc),
        *_left(doc),
        *_candidates(doc),
        *_figures(doc),
        "<h2>Text report</h2>",
        f"<pre>{escape(text_report)}</pre>",
        "</body>",
        "</html>",
        "",
    ]
    return "\n".join(parts)


def write_html(
    doc: Doc, text_report: str, path: str | Path, title: str | None = None,
    verdict: Sequence[str] | None = None,
) -> Path:
    """Write :func:`html_report` to ``path`` atomically.

    Parameters
    ----------
    doc
        The diagnosis document.
    text_report
        The plain-text report.
    path
        Destination; its directory is created if missing. The page is written to a
        temporary file in the same directory and renamed over ``path``.
    title, verdict
        As for :func:`html_report`.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    path = Path(path)
    page = html_report(doc, text_report, title, verdict)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, page.encode("utf-8"))
    return path


# ----------------------------------------------------------------------------- sections


def _num(x: Any, fmt: str = ".4g") -> str:
    if x is None or isinstance(x, bool) or not isinstance(x, int | float):
        return "—" if x is None else escape(str(x))
    if isinstance(x, float) and not math.isfinite(x):
        return "—"
    return format(x, fmt)


def _int(x: Any) -> str:
    return str(x) if isinstance(x, int) and not isinstance(x, bool) else _num(x)


def _cell(text: str, num: bool = False) -> str:
    return f'<td class="num">{text}</td>' if num else f"<td>{text}</td>"


def _head(*names: str) -> str:
    return "<tr>" + "".join(f"<th>{escape(n)}</th>" for n in names) + "</tr>"


def _meta(doc: Doc, problem: str) -> list[str]:
    datasets = [d for d in doc.get("datasets") or [] if isinstance(d, Mapping)]
    shown = ", ".join(escape(str(d.get("name", "?")))
                      + (f" ({_int(d['n'])} rows)" if d.get("n") is not None else "")
                      for d in datasets)
    out = [f'<p class="meta">Problem <strong>{escape(problem)}</strong>']
    if shown:
        out.append(f"; datasets: {shown}")
    if doc.get("alpha") is not None:
        out.append(f"; significance level α = {_num(doc.get('alpha'), 'g')}")
    out.append(".</p>")
    return ["".join(out)]


def _verdict_lines(doc: Doc, text_report: str,
                   verdict: Sequence[str] | None) -> list[str]:
    if verdict is not None:
        return [str(v) for v in verdict]
    given = doc.get("verdict")
    if isinstance(given, Sequence) and not isinstance(given, str):
        return [str(v) for v in given]
    blocks: list[list[str]] = []
    inside = False
    for line in text_report.splitlines():
        if line.strip() == "Verdict":
            blocks.append([])
            inside = True
        elif inside and line.strip():
            blocks[-1].append(line.strip())
        else:
            inside = False
    return blocks[-1] if blocks else []


def _verdict(lines: list[str]) -> list[str]:
    if not lines:
        return []
    items = []
    for line in lines:
        bad = line.startswith("FAILED") or " worse: " in line
        items.append(f'<li class="bad">{escape(line)}</li>' if bad
                     else f"<li>{escape(line)}</li>")
    return ['<section class="verdict">', "<h2>Verdict</h2>", "<ul>", *items, "</ul>",
            "</section>"]


def _unit_text(unit: Any) -> str:
    return escape(symbol(None if unit == "(internal)" else str(unit or "")))


def _residual_table(doc: Doc) -> list[str]:
    rows = [r for r in doc.get("residuals") or [] if isinstance(r, Mapping)]
    out = ["<h2>Residuals</h2>"]
    if not rows:
        return [*out, "<p>No residuals.</p>"]
    worse = {(str(g.get("dataset")), str(g.get("name")))
             for g in doc.get("regressions") or [] if isinstance(g, Mapping)}
    floors = any(isinstance(r.get("noise_floor"), int | float) for r in rows)
    head = ["dataset", "name", "kind", "std before", "std after", "unit"]
    out += ["<table>", _head(*head, *(["noise floor", "std/floor"] if floors else []),
                             *(["after calibration"] if worse else []))]
    for r in rows:
        cells = [
            _cell(escape(str(r.get("dataset", "")))),
            _cell(escape(str(r.get("name", "")))),
            _cell(escape(str(r.get("kind", "")))),
            _cell(_num(r.get("std_before")), num=True),
            _cell(_num(r.get("std_after")), num=True),
            _cell(_unit_text(r.get("unit"))),
        ]
        if floors:
            floor, after = r.get("noise_floor"), r.get("std_after")
            ratio = (after / floor if isinstance(floor, int | float) and floor > 0
                     and isinstance(after, int | float) else None)
            cells += [_cell("" if floor is None else _num(floor), num=True),
                      _cell("" if ratio is None else _num(ratio, ".3g"), num=True)]
        bad = (str(r.get("dataset")), str(r.get("name"))) in worse
        if worse:
            cells.append(_cell("worse" if bad else ""))
        out.append(('<tr class="worse">' if bad else "<tr>") + "".join(cells) + "</tr>")
    out.append("</table>")
    return out


def _left(doc: Doc) -> list[str]:
    """What is left above the noise floor, per residual (the document's ``left``)."""
    lines = [str(x) for x in doc.get("left") or []]
    if not lines:
        return []
    return ["<h2>What is left above the noise floor</h2>", "<ul>",
            *(f"<li>{escape(x)}</li>" for x in lines), "</ul>"]


def _units(doc: Doc) -> dict[str, str]:
    return {f"{r.get('dataset')}/{r.get('name')}": str(r.get("unit") or "")
            for r in doc.get("residuals") or [] if isinstance(r, Mapping)}


def _candidates(doc: Doc) -> list[str]:
    cands = [c for c in doc.get("candidates") or [] if isinstance(c, Mapping)]
    out = ["<h2>Candidate effects</h2>"]
    if not cands:
        return [*out, "<p>No candidate effect is significant.</p>"]
    out += ["<table>", _head("rank", "label", "share of RSS removed", "F", "p", "significant",
                             "indistinguishable from")]
    for k, c in enumerate(cands, start=1):
        share = c.get("delta_rss_share")
        share_text = (f"{100 * share:.1f} %" if isinstance(share, int | float)
                      and math.isfinite(share) else _num(share))
        sig = bool(c.get("significant"))
        twins = ", ".join(str(t) for t in c.get("indistinguishable") or [])
        out.append(f'<tr class="{"significant" if sig else "other"}">' + "".join([
            _cell(_int(c.get("rank", k)), num=True),
            _cell(escape(str(c.get("label", "")))),
            _cell(share_text, num=True),
            _cell(_num(c.get("f_stat")), num=True),
            _cell(_num(c.get("p_value"), ".3g"), num=True),
            _cell("yes" if sig else "no"),
            _cell(escape(twins)),
        ]) + "</tr>")
    out.append("</table>")
    units = _units(doc)
    for k, c in enumerate(cands[:TOP_DETAILED], start=1):
        out += _candidate_detail(c, k, units)
    return out


def _candidate_detail(c: Mapping[str, Any], k: int, units: dict[str, str]) -> list[str]:
    out = [f"<h3>{escape(str(c.get('rank', k)))}. {escape(str(c.get('label', '')))}</h3>"]
    if c.get("text"):
        out.append(f"<p>{escape(str(c['text']))}</p>")
    reduction = c.get("reduction")
    if isinstance(reduction, Mapping) and reduction:
        items = []
        for key, pair in reduction.items():
            before, after = (list(pair) + [None, None])[:2] if pair is not None else (None, None)
            unit = units.get(str(key), "")
            items.append(f"<li>{escape(str(key))}: RMS {_num(before)} → {_num(after)}"
                         f"{' ' + _unit_text(unit) if unit else ''}</li>")
        out += ["<p>Residual RMS if this effect were added:</p>", "<ul>", *items, "</ul>"]
    if c.get("yaml"):
        out += ["<p>YAML to add:</p>", f"<pre>{escape(str(c['yaml']))}</pre>"]
    return out


def _figures(doc: Doc) -> list[str]:
    captions = figure_captions(doc)
    out = ["<h2>Figures</h2>"]
    for name, caption in captions.items():
        data = base64.b64encode(render_png(doc, name)).decode("ascii")
        out += [
            f'<figure id="fig-{escape(name)}">',
            f'<img src="data:image/png;base64,{data}" alt="{escape(caption)}">',
            f"<figcaption><strong>{escape(name)}</strong>: {escape(caption)}</figcaption>",
            "</figure>",
        ]
    return out
