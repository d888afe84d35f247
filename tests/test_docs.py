"""The documentation (issue 21 item 8) stays true to the code.

The README is short and links the site; every page of ``docs/`` is in the site's nav;
Python blocks use public names only; every ``symcal`` command line uses options its
command has; quoted error messages are the bad-input corpus's; quoted reports are what
symcal prints; and the worked examples run as written.  ``make docs`` (part of
``make test``) builds the site with ``mkdocs build --strict``, which fails on a broken
link or anchor, a page left out of the nav, or an API name that no longer exists.  The
examples' walkthroughs (examples/*/README.md, included in the site) are run by
tests/test_example.py and tests/test_planar_arm.py.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml
from conftest import ROOT

import symcal
from symcal.cli import _parser, main

DOCS = ROOT / "docs"
README = ROOT / "README.md"
PAGES = sorted(DOCS.rglob("*.md"))
EXAMPLES = sorted(ROOT.glob("examples/*/README.md"))
CORPUS = ROOT / "tests" / "bad_inputs"


def _text(path: Path) -> str:
    return path.read_text(encoding="utf-8")


def _blocks(text: str, lang: str) -> list[str]:
    """The fenced code blocks of one language, in order (indented ones too)."""
    found = re.findall(rf"^( *)```{lang}\n(.*?)^\1```", text, re.MULTILINE | re.DOTALL)
    return ["\n".join(ln[len(indent):] for ln in body.splitlines()) for indent, body in found]


def _command_lines(block: str) -> list[str]:
    """The lines of a shell block, continuation lines (after a backslash, or a synopsis's
    indented ``[...]``) joined, comments dropped."""
    joined = re.sub(r"\\\n\s*|\n\s+(?=\[)", " ", block)
    return [ln.split("  #")[0].strip() for ln in joined.splitlines()
            if ln.strip() and not ln.lstrip().startswith("#")]


def _squash(text: str) -> str:
    return " ".join(text.split())


def _quoted_in(excerpt: str, output: str) -> list[str]:
    """The lines of ``excerpt`` that are not in ``output``: each piece between ``...``
    must appear in it, whitespace aside."""
    flat = _squash(output)
    return [line for line in excerpt.splitlines()
            if any(_squash(piece) not in flat for piece in line.split("...")
                   if piece.strip())]


def test_the_readme_is_short_and_links_the_documentation() -> None:
    text = _text(README)
    assert len(text.splitlines()) < 150
    for command in ("make demo", "make test", "make test-fast"):
        assert command in text
    linked = set(re.findall(r"\]\(([^)#]+)", text))
    for target in linked:
        if not target.startswith("http"):
            assert (ROOT / target).is_file(), target
    assert {"docs/getting-started.md", "docs/api.md", "docs/python.md"} <= linked


def test_every_page_is_in_the_nav() -> None:
    config = yaml.safe_load(_text(ROOT / "mkdocs.yml"))

    def entries(nav: object) -> list[str]:
        if isinstance(nav, str):
            return [nav]
        if isinstance(nav, list):
            return [e for item in nav for e in entries(item)]
        if isinstance(nav, dict):
            return [e for value in nav.values() for e in entries(value)]
        return []

    nav = entries(config["nav"])
    assert len(nav) == len(set(nav))
    pages = {str(p.relative_to(DOCS)) for p in PAGES}
    assert pages - set(nav) == set()
    assert "python.md" in nav
    assert config["site_dir"].startswith("build/")   # git-ignored


def test_python_blocks_use_public_names_only() -> None:
    for path in [README, *PAGES]:
        for block in _blocks(_text(path), "python"):
            compile(block, str(path), "exec")
            assert not re.search(r"^\s*(from symcal[.\w]* import|import symcal\.)", block,
                                 re.MULTILINE), path
            unknown = set(re.findall(r"\bsymcal\.(\w+)", block)) - set(symcal.__all__)
            assert unknown == set(), (path, unknown)


def test_the_api_reference_documents_every_public_name() -> None:
    documented = re.findall(r"^::: symcal\.(\w+)$", _text(DOCS / "api.md"), re.MULTILINE)
    assert sorted(documented) == sorted(symcal.__all__)


def _commands() -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in _parser()._actions
                  if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def test_every_command_line_uses_options_its_command_has() -> None:
    """Every ``symcal`` line of a shell block, a ``$ symcal`` line of a transcript and a
    ``symcal ...`` span of prose names a command and options it has; a complete line
    (no ``[...]`` placeholders) parses as a whole."""
    commands = _commands()
    checked = 0
    for path in [README, *PAGES, *EXAMPLES]:
        text = _text(path)
        lines = [ln for b in _blocks(text, "sh") for ln in _command_lines(b)]
        lines += [ln[2:] for b in _blocks(text, "text") for ln in _command_lines(b)
                  if ln.startswith("$ symcal ")]
        spans = re.findall(r"`(symcal [^`]+)`", re.sub(r"\n\s*", " ", text))
        for line in lines + spans:
            words = [w for w in line.split() if w not in ("--debug", "--help")]
            if words[0] != "symcal" or len(words) < 2 or not words[1].isalpha():
                continue
            assert words[1] in commands, (path, line)
            known = commands[words[1]]._option_string_actions
            for option in re.findall(r"(?:^|[\s\[])(--?[a-z][\w-]*)", line):
                assert option in known, (path, line, option)
            if line in lines and not re.search(r"\[|\.\.\.|\|", line):
                _parser().parse_args(shlex.split(line)[1:])   # raises on a usage error
            checked += 1
    assert checked >= 50


def _corpus_messages() -> set[str]:
    messages = set()
    for expected in CORPUS.glob("*/expected"):
        lines = _text(expected).splitlines()[1:]
        messages.add(_squash(" ".join(ln for ln in lines if not ln.startswith("stdout: "))))
    return messages


def test_quoted_error_messages_are_the_corpus_messages() -> None:
    corpus = _corpus_messages()
    quoted = []
    for path in [README, *PAGES]:
        for block in _blocks(_text(path), "text"):
            for chunk in re.split(r"\n\s*\n|\n(?=\$ )", block):
                lines = [ln for ln in chunk.splitlines() if not ln.startswith("$ ")]
                if lines and lines[0].startswith("symcal: error:"):
                    quoted.append((path.name, _squash(" ".join(lines))))
    assert len(quoted) >= 4
    assert [q for q in quoted if q[1] not in corpus] == []


# -- runs: the worked examples as written, from a folder beside the repository's files --


@pytest.fixture
def beside_repo(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    for name in ("problems", "models", "examples"):
        (tmp_path / name).symlink_to(ROOT / name)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _run_block(block: str, capsys: pytest.CaptureFixture[str]) -> list[tuple[str, str]]:
    """Run a shell block line by line: ``symcal`` through the CLI's ``main`` (exit 0),
    anything else in a shell.  Each line with its standard output."""
    outputs = []
    for line in _command_lines(block):
        if line.startswith("symcal "):
            assert main(shlex.split(line)[1:]) == 0, line
            out = capsys.readouterr().out
        else:
            done = subprocess.run(line, shell=True, capture_output=True, text=True,
                                  timeout=300, check=False)
            assert done.returncode == 0, (line, done.stderr)
            out = done.stdout
        outputs.append((line, out))
    return outputs


def _run_python(block: str) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(block, "<docs>", "exec"), {"__name__": "__docs__"})  # noqa: S102
    return out.getvalue()


@pytest.mark.slow
def test_the_readme_example_runs_as_written(beside_repo: Path, capsys) -> None:
    text = _text(README)
    (block,) = _blocks(text, "sh")[1:]
    outputs = _run_block(block, capsys)
    solved, diagnosed = outputs[1][1], outputs[2][1]
    verdict, lead = _blocks(text, "text")
    assert _quoted_in(verdict, solved) == []
    assert _quoted_in(lead, diagnosed) == []
    (python,) = _blocks(text, "python")
    printed = _run_python(python)
    assert _quoted_in(verdict, printed) == [] and _quoted_in(lead, printed) == []
    value, se, unit = _parameter_line(printed)
    assert unit == "mm" and 0 < float(se) < abs(float(value))


def _parameter_line(printed: str) -> list[str]:
    """The line ``value se unit`` the README's Python block prints for s2.k1."""
    return next(ln.split() for ln in printed.splitlines()
                if re.fullmatch(r"\S+ \S+ mm", ln.strip()))


@pytest.mark.slow
def test_getting_started_runs_as_written(beside_repo: Path, capsys) -> None:
    text = _text(DOCS / "getting-started.md")
    block = next(b for b in _blocks(text, "sh") if b.startswith("symcal simulate"))
    outputs = dict(_run_block(block, capsys))
    assert (beside_repo / "out" / "result.json").is_file()
    assert '"symcal_result"' in next(o for c, o in outputs.items() if c.endswith("--json"))
    (python,) = _blocks(text, "python")
    printed = _run_python(python)
    assert "what to add:" in printed and "Verdict" in printed
    assert symcal.Result.load("out/result.json").success


@pytest.mark.slow
def test_the_quoted_reports_are_what_symcal_prints(capsys, monkeypatch) -> None:
    monkeypatch.chdir(ROOT)
    blocks = _blocks(_text(DOCS / "report.md"), "text")
    platen = next(b for b in blocks if b.startswith("Verdict"))
    dual = next(b for b in blocks if b.lstrip().startswith("2. coordination"))
    for problem, excerpt in (("platen_self_calibration", platen),
                             ("dual_sensor_calibration", dual)):
        assert main(["solve", f"problems/{problem}.yaml"]) == 0
        assert _quoted_in(excerpt, capsys.readouterr().out) == [], problem


@pytest.mark.slow
def test_the_implicit_comparison_runs_as_written(beside_repo: Path, capsys) -> None:
    (block,) = _blocks(_text(DOCS / "implicit.md"), "sh")
    said = [float(x) for x in re.findall(r"# ([\d.]+) µm", block)]
    outputs = _run_block(block, capsys)
    found = [float(re.search(r"calibration  g_p +\S+ +(\S+)", out).group(1))
             for _, out in outputs[1:]]
    assert found == pytest.approx(said, abs=0.005)


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None,
                    reason="no C compiler")
def test_the_firmware_commands_run_as_written(beside_repo: Path, capsys) -> None:
    (block,) = _blocks(_text(DOCS / "firmware.md"), "sh")
    outputs = _run_block(block, capsys)
    assert "residual  g_x = " in outputs[-1][1]
