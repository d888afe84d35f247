"""Property tests: arbitrary input files raise only symcal's documented error types."""

from __future__ import annotations

from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import symcal
from symcal.data import read_table
from symcal.errors import SymcalError

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
                from symcal.language.model import load_model

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
