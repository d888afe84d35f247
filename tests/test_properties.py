"""Property tests: arbitrary input files raise only symcal's documented error types."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import symcal
from symcal.base.errors import SymcalError
from symcal.data.dataset import read_table

SETTINGS = settings(max_examples=150, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture])

keys = st.sampled_from(["problem", "instances", "constraints", "datasets", "model", "inputs",
                        "parameters", "expressions", "outputs", "value", "expr", "unit",
                        "stages", "implicit", "x"])
scalars = st.one_of(st.none(), st.booleans(), st.integers(-5, 5), st.floats(allow_nan=True),
                    st.text(max_size=12))
documents = st.recursive(scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=3), st.dictionaries(keys, inner, max_size=4)), max_leaves=12)


def _yaml(doc: object) -> str:
    import yaml

    return yaml.safe_dump(doc, allow_unicode=True)


@SETTINGS
@given(text=st.text(max_size=300))
def test_random_text_as_problem(tmp_path: Path, text: str) -> None:
    path = tmp_path / "p.yaml"
    path.write_text(text, encoding="utf-8")
    try:
        symcal.load_problem(path)
    except SymcalError:
        pass


@pytest.mark.slow
@SETTINGS
@given(doc=documents)
def test_random_structures_as_problem_and_model(tmp_path: Path, doc: object) -> None:
    (tmp_path / "m.yaml").write_text(_yaml(doc), encoding="utf-8")
    problem = {"problem": "p", "instances": {"s": {"model": "m.yaml", "inputs": doc}},
               "constraints": {"g": "s.y"}, "datasets": {"calibration": {"path": "d.csv"}}}
    (tmp_path / "p.yaml").write_text(_yaml(problem), encoding="utf-8")
    for path in ("m.yaml", "p.yaml"):
        try:
            if path == "m.yaml":
                from symcal.language.model_file import load_model

                load_model(tmp_path / path)
            else:
                symcal.load_problem(tmp_path / path)
        except SymcalError:
            pass


@SETTINGS
@given(text=st.text(alphabet=st.sampled_from(list("0123456789.,-e\nabn") + [",", "\n"]),
                    max_size=200))
def test_random_text_as_csv(tmp_path: Path, text: str) -> None:
    path = tmp_path / "d.csv"
    path.write_text(text)
    try:
        columns = read_table(path)
    except SymcalError:
        return
    lengths = {len(v) for v in columns.values()}
    assert len(lengths) <= 1


# --------------------------------------------------------------------------- every command
# Random bytes, random YAML and random CSV/NPZ through every command of the command line,
# each run under a time limit (SIGALRM) and a memory limit (tracemalloc's peak): the
# answer is an exit code of 0, 1 or 2 and, on failure, one escaped line on stderr.

BASE = Path(__file__).parent / "bad_inputs" / "bad_max_iter"
SCENARIO = Path(__file__).resolve().parent.parent / "problems" / "scenarios" / "courier_platen.yaml"
#: Seconds and bytes (of Python and NumPy allocations) one command may take.
TIME_LIMIT = 60
MEMORY_LIMIT = 512 << 20
#: Examples per command-line property (``SYMCAL_PROPERTY_EXAMPLES`` for a longer run).
CLI_EXAMPLES = int(os.environ.get("SYMCAL_PROPERTY_EXAMPLES", "30"))
CLI_SETTINGS = settings(max_examples=CLI_EXAMPLES, deadline=None,
                        suppress_health_check=[HealthCheck.function_scoped_fixture,
                                               HealthCheck.too_slow])
#: Where a hostile file goes, and the command lines that read it there.
TARGETS = {
    "prob.yaml": [["solve", "prob.yaml", "--quiet"], ["diagnose", "prob.yaml", "--quiet"],
                  ["compare", "prob.yaml", "prob.yaml"], ["codegen", "prob.yaml", "-o", "c"]],
    "seg.yaml": [["solve", "prob.yaml", "--quiet", "--json"], ["codegen", "prob.yaml", "-o", "c"]],
    "data.csv": [["solve", "prob.yaml", "--quiet"], ["diagnose", "prob.yaml", "--quiet"],
                 ["compare", "prob.yaml", "prob.yaml"],
                 ["solve", "prob.yaml", "--data", "calibration=data.csv", "--out", "r"]],
    "data.npz": [["solve", "prob.yaml", "--quiet", "--data", "calibration=data.npz"],
                 ["diagnose", "prob.yaml", "--quiet", "--data", "calibration=data.npz"]],
    "s.yaml": [["simulate", "s.yaml", "-o", "sim.csv", "-n", "50"]],
    "result.json": [["codegen", "prob.yaml", "--result", "result.json", "-o", "c"]],
}


class _TooSlowError(Exception):
    pass


def _alarm(signum: int, frame: object) -> None:
    raise _TooSlowError(f"a command took more than {TIME_LIMIT} s")


def _run_hostile(name: str, content: bytes, args: list[str], capsys) -> None:
    """Run ``args`` in a fresh copy of the corpus's toy problem with ``name`` replaced by
    ``content``; check the exit code, stderr, time and memory."""
    import signal
    import tempfile
    import tracemalloc

    from symcal.cli import main

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for base in ("prob.yaml", "seg.yaml", "data.csv"):
            (folder / base).write_bytes((BASE / base).read_bytes())
        (folder / "s.yaml").write_bytes(SCENARIO.read_bytes())
        (folder / name).write_bytes(content)
        old_dir = os.getcwd()
        old_alarm = signal.signal(signal.SIGALRM, _alarm)
        tracemalloc.start()
        try:
            os.chdir(folder)
            signal.alarm(TIME_LIMIT)
            try:
                code = main(args)
            except SystemExit as exc:
                code = exc.code
        finally:
            signal.alarm(0)
            signal.signal(signal.SIGALRM, old_alarm)
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
            os.chdir(old_dir)
    out = capsys.readouterr()
    assert code in (0, 1, 2), (code, out.err)
    assert "Traceback" not in out.err and "internal error" not in out.err, out.err
    assert all(ch == "\n" or ch.isprintable() for ch in out.err), repr(out.err)
    if code == 2:
        assert out.err.splitlines()[-1].startswith("symcal: error: ")
    if "--json" in args:
        json.loads(out.out)  # a document, also for errors
    assert peak < MEMORY_LIMIT, f"{peak >> 20} MiB"


magics = st.sampled_from([b"", b"\x1f\x8b", b"PK\x03\x04", b"\x93NUMPY", b"\xef\xbb\xbf",
                          b"problem: toy\n", b"t,p1,p2\n", b"\x00"])
hostile_bytes = st.builds(lambda a, b: a + b, magics, st.binary(max_size=600))


@pytest.mark.slow
@CLI_SETTINGS
@given(target=st.sampled_from(sorted(TARGETS)), pick=st.integers(0, 3), content=hostile_bytes)
def test_random_bytes_through_every_command(capsys, target: str, pick: int,
                                            content: bytes) -> None:
    commands = TARGETS[target]
    _run_hostile(target, content, commands[pick % len(commands)], capsys)


yaml_text = st.lists(st.sampled_from(list("ab01:-[]{}&*!|>#'\", \n\t.e~%@")
                                     + ["problem: ", "model: ", "extends: ", "*a", "&a ",
                                        "<<: ", "\x1b", "\u202e", "!!float ", "!!binary "]),
                     max_size=80).map("".join)


@pytest.mark.slow
@CLI_SETTINGS
@given(target=st.sampled_from(["prob.yaml", "seg.yaml", "s.yaml"]), pick=st.integers(0, 3),
       doc=st.one_of(documents.map(_yaml), yaml_text))
def test_random_yaml_through_every_command(capsys, target: str, pick: int, doc: str) -> None:
    commands = TARGETS[target]
    _run_hostile(target, doc.encode("utf-8", "surrogatepass"), commands[pick % len(commands)],
                 capsys)


cells = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr),
                  st.sampled_from(["", "nan", "inf", "-inf", "1e999", "#", "x", "\x1b[2J", "1_0",
                                   '"1.5"', "0x10", " 2 ", "1,2"]))
headers = st.lists(st.sampled_from(["t", "p1", "p2", "p3", "", "#t", "p1 ", "\x1b[31mp1", "t"]),
                   min_size=1, max_size=5)


@st.composite
def csv_tables(draw: st.DrawFn) -> bytes:
    header = draw(headers)
    rows = draw(st.lists(st.lists(cells, min_size=len(header) - 1, max_size=len(header) + 1),
                         max_size=25))
    newline = draw(st.sampled_from(["\n", "\r\n"]))
    return (",".join(header) + newline + newline.join(",".join(r) for r in rows)).encode()


@pytest.mark.slow
@CLI_SETTINGS
@given(table=csv_tables(), pick=st.integers(0, 3))
def test_random_csv_through_every_command(capsys, table: bytes, pick: int) -> None:
    commands = TARGETS["data.csv"]
    _run_hostile("data.csv", table, commands[pick % len(commands)], capsys)


@st.composite
def npz_files(draw: st.DrawFn) -> bytes:
    import io

    import numpy as np

    n = draw(st.integers(0, 40))
    arrays = {}
    for name in draw(st.lists(st.sampled_from(["t", "p1", "p2", "x", "\x1b"]), min_size=1,
                              max_size=4, unique=True)):
        kind = draw(st.sampled_from(["float", "int", "complex", "bool", "datetime", "text",
                                     "2d", "scalar", "short", "object"]))
        values = np.linspace(0.0, 3.0, n) + draw(st.floats(-1, 1))
        arrays[name] = {
            "float": values, "int": np.arange(n, dtype=np.int32), "complex": values + 1j,
            "bool": values > 1, "datetime": np.arange(n).astype("datetime64[s]"),
            "text": values.astype(str), "2d": np.vstack([values, values]),
            "scalar": np.float64(1.0), "short": values[: n // 2],
            "object": np.array([None] * n, dtype=object),
        }[kind]
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


@pytest.mark.slow
@CLI_SETTINGS
@given(data=npz_files(), pick=st.integers(0, 1))
def test_random_npz_through_every_command(capsys, data: bytes, pick: int) -> None:
    _run_hostile("data.npz", data, TARGETS["data.npz"][pick], capsys)


# ------------------------------------------------------------------ JSON text

json_scalars = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.integers(-10 ** 30, 10 ** 30),
    st.booleans(), st.none(), st.text(max_size=8),
    st.sampled_from([", ", "[1,2]", '"', "\\", "NaN", "-Infinity", "é", "\u2028"]),
    st.floats(allow_nan=True).map(np.float64))
json_keys = st.one_of(st.text(max_size=5), st.sampled_from(["null", "true", "1", "NaN"]),
                      st.integers(-3, 3), st.floats(), st.booleans(), st.none())
json_documents = st.recursive(json_scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=6), st.lists(inner, max_size=6).map(tuple),
    st.dictionaries(json_keys, inner, max_size=5)), max_leaves=40)


@settings(max_examples=600, deadline=None)
@given(doc=json_documents)
@example(doc={"null": 1.0, None: [2, float("nan")], 1: {}, "1": ()})
def test_json_text_is_pythons_indented_json_of_the_plain_document(doc) -> None:
    """symcal's JSON writer (containers laid out in Python, leaves and lists of numbers
    by the C encoder) gives exactly ``json.dumps(json_plain(doc), indent=2)``: non-finite
    numbers as null, keys as JSON writes them, a later duplicate key winning."""
    from symcal.base.files import json_plain, json_text

    assert json_text(doc) == json.dumps(json_plain(doc), indent=2) + "\n"


def test_json_text_refuses_what_json_cannot_write() -> None:
    from symcal.base.files import json_text

    for doc in ({"a": [1.0, object()]}, [1, {2}], object()):
        with pytest.raises(TypeError, match="is not JSON serializable"):
            json_text(doc)


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 3), st.integers(1, 3),
       st.lists(st.floats(-1.0, 1.0), min_size=9, max_size=9), st.integers(-8, 8))
def test_top_singular_value_agrees_with_the_svd(rows, cols, values, power) -> None:
    """The largest canonical correlation's singular value (closed forms for one row or
    column and for 2 × 2) against numpy's SVD: to 1e-12 of its largest entry, to 1e-7
    where a 2 × 2's two singular values nearly coincide."""
    from symcal.analysis.discovery import top_singular_value

    c = np.array(values[:rows * cols]).reshape(rows, cols) * 10.0**power
    want = float(np.linalg.svd(c, compute_uv=False)[0])
    sv = np.linalg.svd(c, compute_uv=False)
    close = c.shape == (2, 2) and sv[0] - sv[-1] < 1e-3 * max(sv[0], 1e-300)
    scale = float(np.max(np.abs(c)))          # the norm within a factor 3, no underflow
    assert abs(top_singular_value(c) - want) <= (1e-7 if close else 1e-12) * scale
