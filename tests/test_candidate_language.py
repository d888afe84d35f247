"""What the candidate search needs from the language and the compiler (issue 23): column
roles, the ``candidates:`` sections, constants as candidates (their δ open in the
diagnostic view only), model constants bound to problem expressions, and rate columns."""

from __future__ import annotations

import textwrap
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import symcal
from symcal.base.errors import DataError, SpecError
from symcal.data.dataset import Dataset
from symcal.data.derived import rate, with_derived
from symcal.data.loading import load_datasets

ROOT = Path(__file__).resolve().parents[1]

MODEL = """\
model: sensor
doc: a sensor read against a scale of pitch P, with a lever arm k
constants:
  k: {value: 2.0, unit: mm, doc: lever arm}
  P: {value: 4.0, unit: mm, doc: scale pitch}
inputs:
  p: {unit: mm, period: P, noise: 1 um, doc: raw reading}
parameters:
  b: {value: 0, unit: mm, scale: 0.01, doc: offset}
  g: {value: 1, scale: 1, doc: gain}
  h: {value: 0, unit: mm, scale: 0.01, doc: first harmonic}
expressions:
  f: 2*pi/P
  e: b + (g - 1)*p + h*sin(f*p)
outputs:
  p_hat: {expr: p + e, unit: mm, doc: calibrated reading}
  q: {expr: k*sin(f*p), unit: mm, doc: lever tip}
candidates:
  variables: [p, f]
  kinds: [harmonic, linear]
  harmonics: 3
"""

PROBLEM = """\
problem: toy
columns:
  t: {unit: s, role: time}
  a: {unit: mm, role: axis}
  b: {unit: mm}
  T: {unit: K, role: state}
  pose: {role: label}
  n: {role: index}
  ref: {unit: mm, role: reference}
  ref2: {unit: mm}
constants:
  L: {value: 3.0, unit: mm, doc: spacing}
parameters:
  c: {value: 0, scale: 1}
instances:
  s1: {model: sensor.yaml, inputs: {p: a}}
  s2:
    model: sensor.yaml
    inputs: {p: b}
    candidates: {variables: [p, T, s1.p, mid], kinds: [linear, product], harmonics: [2, 1]}
expressions:
  mid: {expr: (a + b)/2, unit: mm}
  d: {expr: s1.p_hat - s2.p_hat, unit: mm}
constraints:
  g: s1.p_hat - s2.p_hat - c*L/3
comparisons:
  cmp: {estimate: s1.p_hat, reference: ref2, unit: mm}
datasets:
  calibration: {path: d.csv}
"""


def _data(n: int = 50, seed: int = 1) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.05, 0.15, n))
    a = rng.uniform(0, 8, n)
    return {"t": t, "a": a, "b": a + 0.01 * rng.normal(size=n), "T": 290 + t,
            "pose": np.arange(n) // 10, "n": np.arange(n), "ref": a, "ref2": a}


def _write(tmp: Path, model: str = MODEL, problem: str = PROBLEM) -> Path:
    (tmp / "sensor.yaml").write_text(textwrap.dedent(model))
    (tmp / "prob.yaml").write_text(textwrap.dedent(problem))
    cols = _data()
    lines = [",".join(cols)] + [",".join(repr(float(cols[c][i])) for c in cols)
                                for i in range(len(cols["t"]))]
    (tmp / "d.csv").write_text("\n".join(lines) + "\n")
    return tmp / "prob.yaml"


@pytest.fixture
def toy(tmp_path: Path, monkeypatch) -> symcal.Problem:
    monkeypatch.chdir(tmp_path)
    _write(tmp_path)
    return symcal.load_problem("prob.yaml")


def _error(tmp_path: Path, monkeypatch, model: str = MODEL, problem: str = PROBLEM) -> str:
    monkeypatch.chdir(tmp_path)
    _write(tmp_path, model, problem)
    with pytest.raises(SpecError) as err:
        symcal.load_problem("prob.yaml")
    return str(err.value)


def _line(text: str, needle: str) -> int:
    return next(i for i, ln in enumerate(text.splitlines(), 1) if needle in ln)


# --------------------------------------------------------------------------- roles


def test_column_roles_and_the_columns_that_are_never_effects(toy) -> None:
    roles = {c: toy.column_role(c) for c in ("t", "a", "b", "T", "pose", "n", "ref", "zz")}
    assert roles == {"t": "time", "a": "axis", "b": "", "T": "state", "pose": "label",
                     "n": "index", "ref": "reference", "zz": ""}
    # label, index, reference, and the column a comparison uses as its reference
    assert toy.never_effects == {"pose", "n", "ref", "ref2"}
    courier = symcal.load_problem(ROOT / "problems" / "platen_self_calibration.yaml")
    assert {c for c in courier.column_specs if courier.column_role(c) == "reference"} == {
        "x_ref", "y_ref", "theta_ref"}
    assert {"x_ref", "y_ref", "theta_ref"} <= courier.never_effects


def test_an_unknown_role_is_refused_with_a_suggestion(tmp_path, monkeypatch) -> None:
    problem = PROBLEM.replace("role: reference}", "role: refrence}")
    assert _error(tmp_path, monkeypatch, problem=problem) == (
        f"prob.yaml:{_line(problem, 'refrence')}: columns.ref.role: unknown role 'refrence' "
        "(did you mean 'reference'?); choose from: time, axis, label, index, reference, state")


# --------------------------------------------------------------------------- spaces


def test_declared_spaces_resolve_to_the_problems_names(toy) -> None:
    s1, s2 = toy.instances["s1"].candidates, toy.instances["s2"].candidates
    assert s1 is not None and s2 is not None
    assert (s1.variables, s1.kinds, s1.harmonics, s1.declared_in) == (
        ("s1.p", "s1.f"), ("harmonic", "linear"), (1, 2, 3), "model")
    assert s1.origin == f"the space declared at sensor.yaml:{_line(MODEL, 'candidates:')}"
    assert (s2.variables, s2.kinds, s2.harmonics, s2.declared_in) == (
        ("s2.p", "T", "s1.p", "mid"), ("linear", "product"), (1, 2), "instance")
    assert s2.origin == (f"the space declared at prob.yaml:"
                         f"{_line(PROBLEM, 'candidates: {variables')}")
    assert not s1.none and not s2.none
    # a model expression a space names is a signal the search can evaluate
    signal = next(q for q in toy.signals if q.name == "s1.f")
    fn = ca.Function("f", [toy.theta, toy.u], [signal.sx])
    assert float(fn(np.zeros(toy.theta.shape[0]), np.zeros(toy.u.shape[0]))) == \
        pytest.approx(2 * np.pi / 4.0)
    assert "s2.f" not in {q.name for q in toy.signals}   # s2's own space does not name it


@pytest.mark.parametrize("entry", ["{none: true}", "{kinds: []}"])
def test_none_means_no_term_for_this_sensor(tmp_path, monkeypatch, entry) -> None:
    problem = PROBLEM.replace("candidates: {variables: [p, T, s1.p, mid], kinds: [linear, "
                              "product], harmonics: [2, 1]}", f"candidates: {entry}")
    monkeypatch.chdir(tmp_path)
    _write(tmp_path, problem=problem)
    space = symcal.load_problem("prob.yaml").instances["s2"].candidates
    assert space is not None and space.none and space.kinds == ()
    assert space.variables is None and space.harmonics is None


def test_no_space_declared_is_none(tmp_path, monkeypatch) -> None:
    model = MODEL.split("candidates:")[0]
    monkeypatch.chdir(tmp_path)
    _write(tmp_path, model=model)
    problem = symcal.load_problem("prob.yaml")
    assert problem.instances["s1"].candidates is None
    assert problem.instances["s2"].candidates is not None


@pytest.mark.parametrize(("old", "new", "where", "message"), [
    ("kinds: [linear, product]", "kinds: [linar, product]", "prob.yaml:{line}: "
     "instances.s2.candidates.kinds.0",
     "unknown kind of candidate 'linar' (did you mean 'linear'?); kinds: linear, quadratic, "
     "cubic, harmonic, drift, product, power, gain, coupling, angle_harmonic, latency, "
     "constant, zero"),
    ("[p, T, s1.p, mid]", "[p, T, s1.pp, mid]", "prob.yaml:{line}: "
     "instances.s2.candidates.variables.2",
     "'s1.pp' is not a name of instance 's2' (an input, output or expression of model "
     "'sensor'), a column, a problem expression or another instance's signal (did you mean "
     "'s1.p'?)"),
    ("[p, T, s1.p, mid]", "[p, T, ref2]", "prob.yaml:{line}: "
     "instances.s2.candidates.variables.2",
     "'ref2' is the reference of a comparison: it is never an effect on a sensor"),
    ("[p, T, s1.p, mid]", "[pose]", "prob.yaml:{line}: instances.s2.candidates.variables.0",
     "'pose' is a label column (role: label): it is never an effect on a sensor"),
    ("[p, T, s1.p, mid]", "[p, d]", "prob.yaml:{line}: instances.s2.candidates.variables.1",
     "'d' is computed from the outputs of 's2' itself: a term in it would feed back into "
     "itself"),
    ("harmonics: [2, 1]", "harmonics: [0]", "prob.yaml:{line}: "
     "instances.s2.candidates.harmonics.0", "expected a whole number of at least 1, found 0"),
    ("kinds: [linear, product]", "kinds: [linear], none: true", "prob.yaml:{line}: "
     "instances.s2.candidates.none",
     "'none: true' says no term is ever added to this sensor, but 'kinds' names some: keep "
     "one of them"),
])
def test_instance_spaces_are_checked(tmp_path, monkeypatch, old, new, where,
                                     message) -> None:
    problem = PROBLEM.replace(old, new)
    line = _line(problem, "candidates: {")
    assert _error(tmp_path, monkeypatch, problem=problem) == \
        f"{where.format(line=line)}: {message}"


def test_a_models_space_names_its_own_names(tmp_path, monkeypatch) -> None:
    model = MODEL.replace("variables: [p, f]", "variables: [p, ff]")
    assert _error(tmp_path, monkeypatch, model=model) == (
        f"sensor.yaml:{_line(model, 'variables: [p, ff]')}: candidates.variables.1: 'ff' is "
        "not an input, output or expression of model 'sensor' (did you mean 'f'?); a model's "
        "candidates use its own names: p, p_hat, q, f, e")


def test_an_extending_model_inherits_or_replaces_the_space(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    _write(tmp_path)
    (tmp_path / "child.yaml").write_text("model: child\nextends: sensor.yaml\n"
                                         "parameters: {w: {value: 0, unit: mm}}\n"
                                         "expressions: {e: base.e + w}\n")
    (tmp_path / "other.yaml").write_text("model: other\nextends: sensor.yaml\n"
                                         "candidates: {variables: [e], harmonics: [5]}\n")
    for name, variables, harmonics in (("child", ("s1.p", "s1.f"), (1, 2, 3)),
                                       ("other", ("s1.e",), (5,))):
        (tmp_path / "p2.yaml").write_text(
            f"problem: p2\nextends: prob.yaml\ninstances: {{s1: {{model: {name}.yaml}}}}\n")
        space = symcal.load_problem("p2.yaml").instances["s1"].candidates
        assert space is not None and (space.variables, space.harmonics) == (variables,
                                                                            harmonics)


def test_the_problems_constants_and_fixed_parameters_to_test(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    _write(tmp_path, problem=PROBLEM.replace(
        "  s1: {model: sensor.yaml, inputs: {p: a}}",
        "  s1: {model: sensor.yaml, inputs: {p: a}, parameters: {g: {fixed: true}}}"))
    everything = symcal.load_problem("prob.yaml")
    assert everything.candidates.where is None
    assert everything.candidates.constants == ("L", "s1.k", "s1.P", "s2.k", "s2.P")
    assert everything.candidates.fixed == ("s1.g",)
    assert all(c.tested for c in everything.constants)
    for section, constants, fixed in (
            ("{constants: false}", (), ("s1.g",)),
            ("{constants: ['s?.k', L], fixed: false}", ("L", "s1.k", "s2.k"), ()),
            ("{fixed: [s1.g]}", ("L", "s1.k", "s1.P", "s2.k", "s2.P"), ("s1.g",))):
        (tmp_path / "p2.yaml").write_text(f"problem: p2\nextends: prob.yaml\n"
                                          f"candidates: {section}\n")
        problem = symcal.load_problem("p2.yaml")
        assert (problem.candidates.constants, problem.candidates.fixed) == (constants, fixed)
        assert problem.candidates.where is not None
        assert {c.key for c in problem.constants if c.tested} == set(constants)
    (tmp_path / "p2.yaml").write_text("problem: p2\nextends: prob.yaml\n"
                                      "candidates: {constants: ['s?.rh']}\n")
    with pytest.raises(SpecError) as err:
        symcal.load_problem("p2.yaml")
    assert str(err.value) == (
        "p2.yaml:3: candidates.constants.0: 's?.rh' matches no constant; constants: L, s1.k, "
        "s1.P, s2.k, s2.P")


# --------------------------------------------------------------------------- constants


def test_constants_are_listed_with_their_declarations(toy) -> None:
    info = {c.key: c for c in toy.constants}
    assert list(info) == ["L", "s1.k", "s1.P", "s2.k", "s2.P"]
    p = info["s2.P"]
    assert (p.name, p.instance, p.value, p.unit, p.doc) == ("P", "s2", 4.0, "mm",
                                                            "scale pitch")
    assert p.model_file == Path("sensor.yaml").resolve()
    assert (p.where.file, p.where.line) == ("sensor.yaml", _line(MODEL, "P: {value: 4.0"))
    top = info["L"]
    assert (top.instance, top.model_file, top.doc, top.where.line) == (
        None, None, "spacing", _line(PROBLEM, "L: {value"))
    # a constant in a period still gives a number
    assert next(q for q in toy.signals if q.name == "s1.p").period == 4.0


def _free_symbols(problem: symcal.Problem) -> set[str]:
    exprs = [*(q.sx for q in problem.constraints), *(q.sx for q in problem.expressions),
             *(q.sx for q in problem.signals),
             *(x for c in problem.comparisons for x in (c.estimate, c.reference))]
    return {v.name() for e in exprs for v in ca.symvar(e)}


def test_the_constants_symbols_are_open_in_the_diagnostic_view_only(toy) -> None:
    symbols = {c.symbol.name() for c in toy.constants}
    assert symbols == {"const:L", "const:s1.k", "const:s1.P", "const:s2.k", "const:s2.P"}
    assert symbols <= _free_symbols(toy.diagnostic)
    for view in (toy, toy.noisy):
        assert not symbols & _free_symbols(view)
    # the diagnostic view's symbols are the very ones Problem.constants holds
    diag = {v.name(): v for v in ca.symvar(toy.diagnostic.constraints[0].sx)}
    assert all(ca.is_equal(diag[c.symbol.name()], c.symbol) for c in toy.constants
               if c.symbol.name() in diag)


def test_a_constants_symbol_is_the_derivative_by_that_constant(toy) -> None:
    """∂g/∂δ of s1's pitch P, from the diagnostic view, against the derivative of
    g = ... + h sin(2π p/P) written by hand."""
    hp = toy.diagnostic
    deltas = [c.symbol for c in toy.constants]
    hooks = list(hp.hooks.values())
    g = hp.constraint("g").sx
    pitch = next(c.symbol for c in toy.constants if c.key == "s1.P")
    fn = ca.Function("d", [hp.theta, hp.u, ca.vertcat(*hooks, *deltas)],
                     [g, ca.jacobian(g, pitch)])
    data = _data()
    theta = np.array([{"s1.h": 0.02, "s2.h": -0.01, "s1.g": 1.001}.get(n, p.value)
                      for n, p in zip(toy.parameter_names, toy.parameters, strict=True)])
    for a, b in zip(data["a"][:5], data["b"][:5], strict=True):
        u = [{"a": a, "b": b}.get(c, 0.0) for c in hp.columns]
        value, slope = fn(theta, u, np.zeros(len(hooks) + len(deltas)))
        expected = 0.02 * np.cos(2 * np.pi * a / 4.0) * (-2 * np.pi * a / 4.0 ** 2)
        assert float(slope) == pytest.approx(expected, rel=1e-12, abs=1e-15)
        use = ca.Function("g", [toy.theta, toy.u], [toy.constraint("g").sx])
        assert float(use(theta, u)) == float(value)     # δ at zero: the problem in use


@pytest.mark.parametrize("name", ["platen_self_calibration.yaml",
                                  "platen_self_calibration_implicit.yaml",
                                  "dual_sensor_calibration.yaml",
                                  "dual_sensor_calibration_implicit.yaml"])
def test_bundled_problems_are_unchanged_by_the_constants_symbols(name) -> None:
    """The problem in use is the diagnostic view with the hooks and the constants'
    symbols at zero, expression for expression (CasADi's own text of each), and no other
    view holds a constant's symbol."""
    problem = symcal.load_problem(ROOT / "problems" / name)
    hp = problem.diagnostic
    closing = [*hp.hooks.values(), *(c.symbol for c in problem.constants)]
    zeros = [ca.SX(0)] * len(closing)
    for use, diag in ((problem.constraints, hp.constraints), (problem.signals, hp.signals),
                      (problem.expressions, hp.expressions)):
        for q, d in zip(use, diag, strict=True):
            assert str(q.sx) == str(ca.substitute([d.sx], closing, zeros)[0]), q.name
    symbols = {c.symbol.name() for c in problem.constants}
    views = [problem, problem.noisy] + ([problem.explicit] if problem.explicit else [])
    for view in views:
        assert not symbols & _free_symbols(view)
        for check in view.implicit:
            assert not symbols & {v.name() for v in ca.symvar(check.derivative)}


# --------------------------------------------------------------------------- bound constants


def test_an_instance_binds_a_model_constant_to_a_problem_expression(tmp_path,
                                                                     monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    _write(tmp_path)
    (tmp_path / "p2.yaml").write_text(
        "problem: p2\nextends: prob.yaml\n"
        "parameters: {pitch: {value: 4.0, unit: mm, doc: scale pitch (was a constant)}}\n"
        "instances:\n  s1: {constants: {P: pitch}}\n  s2: {constants: {P: pitch}}\n")
    base, bound = symcal.load_problem("prob.yaml"), symcal.load_problem("p2.yaml")
    assert bound.instances["s1"].constants == {"P": "pitch"}
    assert [c.key for c in bound.constants] == ["L", "s1.k", "s2.k"]
    assert next(q for q in bound.signals if q.name == "s1.p").period == 4.0   # at its start
    data = _data()
    for problem in (base, bound):
        theta = np.array([0.01 if n.endswith(".h") else p.value
                          for n, p in zip(problem.parameter_names, problem.parameters,
                                          strict=True)])
        fn = ca.Function("g", [problem.theta, problem.u], [problem.constraint("g").sx])
        u = np.array([data[c] for c in problem.columns])
        values = np.array(fn(theta, u)).ravel()
        if problem is base:
            expected = values
    np.testing.assert_array_equal(values, expected)   # at its start: the same numbers
    # the parameter moves every instance's pitch: g depends on it
    assert ca.depends_on(bound.constraint("g").sx, bound.theta[bound.index["pitch"]])


@pytest.mark.parametrize(("binding", "extra", "message"), [
    ("{PP: L}", "", "instances.s1.constants.PP: 'PP' is not a constant of model 'sensor' "
     "(did you mean 'P'?); it has: k, P"),
    ("{P: a}", "", "instances.s1.constants.P: constant 'P' of model 'sensor' is bound to "
     "'a', which varies with a: a constant is bound to an expression of parameters and "
     "constants"),
    ("{P: ang}", "parameters: {ang: {value: 1, unit: rad}}\n",
     "instances.s1.constants.P: constant 'P' of model 'sensor' is in "),
])
def test_a_bound_constant_is_checked(tmp_path, monkeypatch, binding, extra,
                                     message) -> None:
    monkeypatch.chdir(tmp_path)
    _write(tmp_path)
    text = f"problem: p2\nextends: prob.yaml\n{extra}instances:\n  s1: {{constants: {binding}}}\n"
    (tmp_path / "p2.yaml").write_text(text)
    with pytest.raises(SpecError) as err:
        symcal.load_problem("p2.yaml")
    assert str(err.value).startswith(f"p2.yaml:{_line(text, 'constants:')}: {message}")


def test_an_overlay_makes_a_problem_constant_a_parameter(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    _write(tmp_path)
    (tmp_path / "p2.yaml").write_text(
        "problem: p2\nextends: prob.yaml\n"
        "parameters: {L: {value: 3.0, unit: mm, doc: spacing (was a constant)}}\n")
    problem = symcal.load_problem("p2.yaml")
    assert "L" in problem.index and "L" not in {c.key for c in problem.constants}
    (tmp_path / "p3.yaml").write_text(
        "problem: p3\nextends: p2.yaml\nconstants: {L: {value: 3.0, unit: mm}}\n")
    again = symcal.load_problem("p3.yaml")            # and back: a parameter fixed as before
    assert "L" not in again.index and "L" in {c.key for c in again.constants}


def test_an_output_redefined_in_the_short_form_keeps_its_unit(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    _write(tmp_path)
    (tmp_path / "ext.yaml").write_text("model: ext\nextends: sensor.yaml\n"
                                       "parameters: {w: {value: 0}}\n"
                                       "outputs: {q: base.q + w*p}\n")
    (tmp_path / "p2.yaml").write_text("problem: p2\nextends: prob.yaml\n"
                                      "instances: {s1: {model: ext.yaml}}\n")
    signal = next(q for q in symcal.load_problem("p2.yaml").signals if q.name == "s1.q")
    assert (signal.unit, signal.doc) == ("mm", "lever tip")


# --------------------------------------------------------------------------- rates


def test_a_rate_is_a_central_difference_on_the_time_stamps() -> None:
    """Against the derivative of sin: second order inside (also where the spacing
    varies), first order at the ends."""
    errors = []
    for n in (200, 400):
        t = np.linspace(0, 2, n) ** 1.2           # uneven steps
        r = rate(np.sin(t), t)
        errors.append(np.max(np.abs(r[1:-1] - np.cos(t[1:-1]))))
        assert abs(r[0] - (np.sin(t[1]) - np.sin(t[0])) / (t[1] - t[0])) < 1e-12
    assert errors[1] < errors[0] / 3.5                # second order: a quarter per halving
    assert errors[1] < 1e-4


RATE = "  a_rate: {rate_of: a, unit: um/s}\n"


def test_a_rate_column_is_computed_when_data_are_loaded(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    _write(tmp_path, problem=PROBLEM.replace("  b: {unit: mm}\n", "  b: {unit: mm}\n" + RATE)
           .replace("g: s1.p_hat - s2.p_hat - c*L/3", "g: s1.p_hat - s2.p_hat - c*L/3 + "
                                                      "0*a_rate"))
    problem = symcal.load_problem("prob.yaml")
    assert problem.column_specs["a_rate"].rate_of == "a"
    data = load_datasets(problem)["calibration"]
    cols = _data()
    expected = np.gradient(cols["a"], cols["t"], edge_order=1) * 1000   # mm/s in um/s
    np.testing.assert_allclose(data.columns["a_rate"], expected, rtol=1e-12)
    # a dataset given in Python gets it too; time that does not increase is refused
    given = Dataset("calibration", "given", {k: v for k, v in cols.items()})
    assert "a_rate" in load_datasets(problem, {"calibration": given})["calibration"].columns
    back = dict(cols, t=cols["t"][::-1].copy())
    with pytest.raises(DataError) as err:
        with_derived(problem.column_specs, Dataset("calibration", "d.csv", back), ["a_rate"])
    assert str(err.value) == ("d.csv: column 'a_rate' is the rate of 'a' in time 't', but "
                              "time does not increase at rows 2, 3, 4, 5, 6, ...: a rate "
                              "needs time-ordered rows")


@pytest.mark.parametrize(("columns", "message"), [
    ("  a_rate: {rate_of: aa}\n", "columns.a_rate.rate_of: 'aa' is not another column of "
     "the problem (did you mean 'a'?); 'rate_of' names the column whose time derivative "
     "'a_rate' is"),
    ("  a_rate: {rate_of: a, unit: mm}\n", "columns.a_rate.unit: 'a_rate' is the rate of 'a' "
     "(mm per s), but its unit 'mm' measures something else"),
    ("  a_rate: {rate_of: t}\n", "columns.a_rate.rate_of: 't' is the time column: its rate "
     "is 1"),
])
def test_a_rate_column_is_checked(tmp_path, monkeypatch, columns, message) -> None:
    problem = PROBLEM.replace("  b: {unit: mm}\n", "  b: {unit: mm}\n" + columns)
    text = _error(tmp_path, monkeypatch, problem=problem)
    assert text == f"prob.yaml:{_line(problem, 'a_rate')}: {message}"


def test_a_rate_needs_one_time_column(tmp_path, monkeypatch) -> None:
    problem = PROBLEM.replace("t: {unit: s, role: time}", "t: {unit: s}").replace(
        "  b: {unit: mm}\n", "  b: {unit: mm}\n  a_rate: {rate_of: a}\n")
    assert _error(tmp_path, monkeypatch, problem=problem).endswith(
        "columns.a_rate.rate_of: the rate of 'a' is computed against the problem's time "
        "column, and no column declares 'role: time': declare exactly one, e.g. columns: "
        "{t: {unit: s, role: time}}")


def test_a_latency_correction_keeps_the_columns_noise(tmp_path, monkeypatch) -> None:
    """``p: a + tau*a_rate`` reads the column ``a``: the model input's noise stays the
    column's (not a noise of its own beside the column's)."""
    monkeypatch.chdir(tmp_path)
    _write(tmp_path, problem=PROBLEM.replace("  b: {unit: mm}\n",
                                             "  b: {unit: mm}\n  a_rate: {rate_of: a, "
                                             "noise: 0}\n"))
    (tmp_path / "p2.yaml").write_text(
        "problem: p2\nextends: prob.yaml\nparameters: {tau: {value: 0, unit: s}}\n"
        "instances: {s1: {inputs: {p: a + tau*a_rate}}}\n")
    base, late = symcal.load_problem("prob.yaml"), symcal.load_problem("p2.yaml")
    assert {r.name: r.kind for r in base.readings} == {"a": "column", "b": "column"}
    assert {r.name: r.kind for r in late.readings} == {"a": "column", "b": "column",
                                                       "a_rate": "column"}
    assert next(r for r in late.readings if r.name == "a").sigma == pytest.approx(1e-3)
