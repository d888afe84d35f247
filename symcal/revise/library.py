"""The candidate effects a diagnosis tests: the search space and the library of shapes.

**The search space.**  By default a sensor instance's candidates use its own inputs (and
the columns they are bound to, where it evaluates its error), the problem's declared time
column (``role: time``) and state columns (``role: state``): never a reference column
(one a comparison reads as its reference, or ``role: reference``), never a label or an
index (``role: label|index``), never another sensor's reading, unless the problem declares
it (``candidates:`` on the instance, the model, or the problem: ``declared``).  A term
linear in another sensor's reading on an output of a sensor with the default variables
(crosstalk) is a family of its own (:func:`outside_entries`), tested apart where nothing
in the spaces is significant.

**The shapes** on each output of the instance: a harmonic of a periodic variable (orders 1
to :data:`HARMONICS`), a term linear in a variable, a quadratic, a cubic (odd about the
data's centre, ``(v - c)**3``, tested beyond the linear and quadratic terms below it),
a drift in time, the product of two of the instance's variables (tested beyond the two
linear terms it contains: it is tried after them), the power a resistive sensor dissipates
where a current (or a voltage) and a resistance among its variables both vary
(``I**2*R``, ``V**2/R``: self-heating, which a quadratic in the current stands in for only
where the resistance stays put), an angle times a harmonic (the orders
of the plain harmonics), the output's own gain varying with a variable that is not one of the
sensor's readings (``O*(w - c)``, tested beyond the term linear in ``w``: a sensitivity
that changes with the temperature, where the output is not its reading plus a small
error), and a share of another of the sensor's outputs (``Bx += k*By``: a triad's
cross-axis sensitivity, zero where that output is, where the output is not its reading
plus a small error).  Besides terms on outputs:

- **latency**: an instance's readings stamped late by a constant delay τ, the term
  ``τ·Σ_j ∂r/∂c_j · dc_j/dt`` over the columns it reads, where the rows are time-ordered
  and the columns move smoothly (the derivative by central differences in time);
- **a fixed parameter that is off**: the user fixed it but no gauge needs it fixed; its
  regressor is ``∂r/∂θ_k``;
- **a constant that is off**: its regressor is the derivative by the constant's offset;
- **a reading's zero that is off**: a data column the sensors read (not time, not a
  reference, not a rate) read with a constant offset, as a transducer or an ADC channel
  whose zero has moved; its regressor is the derivative by the column (every sensor that
  reads it), ``∂r/∂c``.  Not where a sensor that reads it has an offset of its own
  (:data:`OWN_OFFSET`); where the reading goes through the model nonlinearly (a voltage
  in a divider, a pressure under a square root) no term on the output stands in for it.

Every regressor is the change a coefficient of one makes in every residual (N × n_q × m),
evaluated at the adjusted readings where the noise is declared.  Each coefficient has a
*scale*: the coefficient that makes the term about one noise standard deviation of the
output it changes (internal units), from the data, whatever the units.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import numpy as np

from symcal.analysis.discovery import Basis, Candidate
from symcal.analysis.residuals import Variable
from symcal.base.errors import SymcalError
from symcal.base.units import DISPLAY_UNITS, parse_unit, registry
from symcal.data.derived import rate_and_noise
from symcal.language import expr
from symcal.language.common import ExprSpec
from symcal.language.model_file import ModelSpec
from symcal.problem.symbolic import Problem
from symcal.revise.blocks import Block, distinct_groups, references
from symcal.revise.effects import centre_variable

#: Harmonic orders tried by default.
HARMONICS = 8
#: Roles of columns that are never an effect's variable.
NEVER = ("label", "index", "reference")
#: Roles of columns every instance's candidates may use.
SHARED = ("time", "state")
#: A column moves smoothly in time where its mean square successive difference is below
#: this share of twice its variance (von Neumann's ratio: 1 for independent rows).
SMOOTH = 0.2

Raw = Callable[[int], np.ndarray]   # block index -> unwhitened regressor (N, n_q, m)


@dataclass
class Entry:
    """A candidate, its regressor, and what its test allows for first (``extra``: the
    simpler terms it contains, as more nuisance columns), None for nothing."""

    candidate: Candidate
    raw: Raw
    extra: Raw | None = None
    # what the term's centre moves between it and the rest (a linear term's constant; a
    # quadratic's constant and linear part): where the nuisance absorbs all of it, the term
    # is written uncentred, so that the parameters absorbing it keep their meaning
    lower: Raw | None = None


@dataclass(frozen=True)
class Space:
    """What one instance's candidates may use: variable names, kinds, harmonic orders and
    where that was decided (``origin``, for the report)."""

    instance: str
    variables: tuple[str, ...]
    kinds: tuple[str, ...] | None
    harmonics: tuple[int, ...]
    origin: str
    declared: bool = False       # whether ``variables`` is the instance's own list
    # declared variables no term uses: computed from another sensor's outputs
    unused: tuple[str, ...] = ()

    def describe(self) -> str:
        """The space in words."""
        kinds = "every kind" if self.kinds is None else ", ".join(self.kinds) or "nothing"
        text = (f"{self.instance}: {', '.join(self.variables) or 'no variable'} "
                f"({kinds}; {self.origin})")
        if self.unused:
            text += (f"; not used: {', '.join(self.unused)}, computed from another "
                     "sensor's outputs (a term in it would feed one sensor's output into "
                     "another's model): name the readings it is made of instead")
        return text


def own_names(problem: Problem, instance: str) -> set[str]:
    """The names of an instance's own readings: its inputs (``s1.p``), the columns they
    are bound to, and where it evaluates its error (``s1.u``)."""
    inst = problem.instances[instance]
    names = {f"{instance}.{k}" for k in inst.bindings}
    names |= {text for text in inst.bindings.values() if text in problem.column_specs}
    for k in inst.model.inputs:
        point = inst.model.evaluation_point(k)
        if point is not None:
            names.add(f"{instance}.{point}")
    return names


def excluded(problem: Problem) -> set[str]:
    """Columns that are never an effect's variable: references, labels and indices."""
    return set(problem.never_effects) | set(references(problem))


def spaces(problem: Problem) -> dict[str, Space]:
    """Each instance's search space: as its ``candidates:`` (instance entry, else model)
    declares it, the default for what it does not say."""
    shared = [c for c, spec in problem.column_specs.items() if spec.role in SHARED]
    out = {}
    for name, inst in problem.instances.items():
        declared = inst.candidates
        own = sorted(own_names(problem, name))
        default = tuple(dict.fromkeys(own + shared))   # a state column it reads: once
        if declared is None:
            out[name] = Space(name, default, None, tuple(range(1, HARMONICS + 1)),
                              "default: its own readings, time and state columns")
            continue
        out[name] = Space(
            name, default if declared.variables is None else tuple(declared.variables),
            declared.kinds,
            tuple(range(1, HARMONICS + 1)) if declared.harmonics is None
            else tuple(declared.harmonics), declared.origin, declared.variables is not None)
    return out


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if x.size else 0.0


def output_sigma(block: Block, h: int) -> float:
    """About one noise standard deviation of the output of hook ``h`` (internal units):
    the noise of the residual it moves most, divided by how much it moves it."""
    weight = np.sqrt(np.mean(np.square(block.hooks[:, :, h]), axis=0))
    if not np.any(weight > 0):
        return 1.0
    k = int(np.argmax(weight))
    return _residual_sigma(block, k) / float(weight[k])


def _residual_sigma(block: Block, k: int) -> float:
    if block.cov is not None:
        sigma = float(np.sqrt(np.mean(block.cov[:, k, k])))
        if sigma > 0:
            return sigma
    spread = float(np.std(block.after[:, k]))
    return spread if spread > 0 else 1.0


def column_scale(block: Block, x: np.ndarray) -> float:
    """The coefficient of a regressor column (N × n_q) that changes the residual it moves
    most by about one noise standard deviation."""
    weight = np.sqrt(np.mean(np.square(x), axis=0))
    if not np.any(weight > 0):
        return 1.0
    k = int(np.argmax(weight))
    return _residual_sigma(block, k) / float(weight[k])


def _scales(sigma: float, columns: np.ndarray) -> tuple[float, ...]:
    """Per column of φ (N × m): the coefficient that makes the term ``sigma`` RMS."""
    out = []
    for j in range(columns.shape[1]):
        size = _rms(columns[:, j])
        out.append(sigma / size if size > 0 else sigma)
    return tuple(float(f"{s:.3g}") for s in out)


def centre_of(values: np.ndarray) -> float:
    """The data's centre of a variable: its mean, to six significant digits (a term's
    ``centre`` in the files it is written to)."""
    return float(f"{float(np.mean(values)):.6g}")


@dataclass(frozen=True)
class _Shape:
    basis: Basis
    phi: Callable[[Block], np.ndarray]       # block -> (N, m)
    contains: tuple[str, ...] = ()           # variables of the linear terms it contains
    lower: Callable[[Block], np.ndarray] | None = None  # see Entry.lower
    beyond: Callable[[Block], np.ndarray] | None = None  # other simpler terms it is tested
    #                                                     beyond (block -> (N, k))


def _shapes(variables: list[Variable], block: Block, space: Space) -> list[_Shape]:
    """Every shape φ of one instance's space (values on ``block``, the fit's)."""
    kinds = space.kinds
    allowed = (lambda k: True) if kinds is None else (lambda k: k in kinds)
    out: list[_Shape] = []
    periodic = [v for v in variables if v.period]
    angles = [v for v in variables if v.kind == "angle"]
    plain = [v for v in variables if v.kind != "angle"]
    if allowed("harmonic"):
        for v in periodic:
            period = float(v.period or 1.0)
            shown = period / DISPLAY_UNITS[v.unit]
            for n in space.harmonics:
                w = 2 * np.pi * n / period
                out.append(_Shape(Basis(
                    "harmonic", v.name, f"harmonic {n} of {v.name} (period {shown:g} {v.unit})",
                    (f"h{n}_sin", f"h{n}_cos"),
                    (f"sin({2 * n}*pi*{{v}}/{{period}})", f"cos({2 * n}*pi*{{v}}/{{period}})"),
                    order=n, unit=v.unit, period=period), _harmonic(v.name, w)))
    for v in [*plain, *angles]:
        if v.kind == "drift":
            if allowed("drift"):
                out.append(_Shape(Basis("drift", v.name, f"a slow drift in time ({v.name})",
                                        ("drift",), ("{v}",), unit=v.unit),
                                  _linear(v.name, 0.0)))
            continue
        c = centre_of(block.values(v.name))
        if allowed("linear"):
            out.append(_Shape(Basis("linear", v.name, f"a term linear in {v.name}", ("lin",),
                                    ("({v} - {centre})",), unit=v.unit, centre=c),
                              _linear(v.name, c), lower=_ones))
        if allowed("quadratic"):
            out.append(_Shape(Basis("quadratic", v.name, f"a quadratic dependence on {v.name}",
                                    ("lin", "quad"), ("({v} - {centre})", "({v} - {centre})**2"),
                                    unit=v.unit, centre=c),
                              _quadratic(v.name, c), lower=_affine(v.name, c)))
        if allowed("cubic"):
            # odd about the data's centre (an amplifier's S-curve about mid-scale), tested
            # beyond the linear and quadratic terms below it (tried after them, as a
            # product is: a quadratic on skewed data also correlates with a cube, and a
            # new user's load cell kept the cube in its place, the cell's sensitivity 9 SE
            # off); a curve both odd and even is found in two rounds
            out.append(_Shape(Basis("cubic", v.name, f"a cubic dependence on {v.name}",
                                    ("cub",), ("({v} - {centre})**3",), unit=v.unit,
                                    centre=c),
                              _cubic(v.name, c), (v.name,), lower=_affine(v.name, c),
                              beyond=_square(v.name, c)))
    if allowed("product"):
        # uncentred: a gain growing with time is exactly c·v·t (centring would leave a
        # drift c·v̄·t behind); the linear terms it contains are allowed for in its test
        pool = sorted(variables, key=lambda v: v.kind == "drift")   # time goes second
        for i, v in enumerate(pool):
            for v2 in pool[i + 1:]:
                cv = cw = 0.0
                out.append(_Shape(Basis(
                    "product", v.name, f"the product of {v.name} and {v2.name}", ("prod",),
                    ("{v}*{w}",), unit=v.unit, centre=cv,
                    other=v2.name, other_unit=v2.unit, other_centre=cw),
                    _product(v.name, cv, v2.name, cw), (v.name, v2.name), lower=_ones))
    if allowed("power"):
        out += [shape for v in plain for r in plain
                if (shape := _power_shape(v, r)) is not None]
    if allowed("angle_harmonic"):
        for a in angles:
            for v in periodic:
                period = float(v.period or 1.0)
                for n in space.harmonics:
                    out.append(_Shape(Basis(
                        "angle_harmonic", v.name,
                        f"the angle {a.name} times harmonic {n} of {v.name}",
                        *_angle_columns(n), a.name, order=n,
                        unit=v.unit, angle_unit=a.unit, period=period),
                        _angle_harmonic(a.name, v.name, 2 * np.pi * n / period)))
    return out


#: An output is proportional to one of its sensor's own readings where a line through
#: the origin in that reading leaves less than this share of it (a position read as
#: itself plus a small error): a gain of the output that varies with a variable is then
#: the product of that reading and the variable, already a candidate.
PROPORTIONAL = 1e-2


def _gains(problem: Problem, output: str, groups: list[tuple[Variable, set[str]]],
           variables: list[Variable], block: Block, space: Space) -> list[_Shape]:
    """The output's gain varying with each variable of the space that is not one of the
    sensor's own readings: ``k*O*(w - c)``, ``O`` the output itself (at the adjusted
    readings), tested beyond the term linear in ``w``.  A Hall sensor's sensitivity that
    falls with the temperature is ``I*(T - c)``; the product of its raw reading and the
    temperature is the same term to the test but, written alone, adds an offset drift
    (its 2.5 V zero times the temperature) that is not there.  Only where the model
    writes the output itself (no error expression: there the output is its reading plus
    a small error, and the product of the reading is the gain) and where the output is
    not proportional to one of the sensor's own readings (:data:`PROPORTIONAL`)."""
    if space.kinds is not None and "gain" not in space.kinds:
        return []
    instance, local = output.split(".", 1)
    model = problem.instances[instance].model
    if model.error_expression(local) is not None or output not in {
            v.name for v in block.variables}:
        return []
    o = block.values(output)
    size = float(np.linalg.norm(o))
    if not np.all(np.isfinite(o)) or size == 0.0:
        return []
    own = own_names(problem, instance)
    readings = [var.values for var, names in groups if names & own]
    for r in readings:
        rr = float(r @ r)
        if rr > 0 and float(np.linalg.norm(o - (o @ r) / rr * r)) < PROPORTIONAL * size:
            return []
    out = []
    mine = {var.name for var, names in groups if names & own}
    for v in variables:
        if v.kind == "angle" or v.name in mine:
            continue
        c = 0.0 if v.kind == "drift" else centre_of(block.values(v.name))
        term = "{o}*({v} - {centre})" if c else "{o}*{v}"
        out.append(_Shape(Basis(
            "gain", v.name, f"{output} times {v.name} (a gain that varies with {v.name})",
            ("gain",), (term,), unit=v.unit, centre=c),
            _gain(output, v.name, c), (v.name,), lower=_value(output)))
    return out


def _couplings(problem: Problem, output: str, block: Block, space: Space) -> list[_Shape]:
    """A share of each other output of the same sensor added to ``output``: ``k*O2``, a
    triad's cross-axis sensitivity (``Bx += k*By``).  The same fit as a term linear in
    the reading ``O2`` is made of, but zero where ``O2`` is (zero field along y), not
    where that raw reading is: written on the raw reading, the term moves the output's
    own offset by ``k`` times the other axis's (``ox`` becomes ``ox - k*oy``).  Only
    where the model writes ``output`` itself (no error expression: there the output is
    its reading plus a small error, and its zero the reading's), of an output of the same
    unit (a field's share of a field: a temperature output is no axis, and the term
    linear in the temperature, about the run's centre, is that effect), never on an
    output that ``O2`` itself reads (no cycle), and where the instance declares its
    variables (``candidates: variables``), of the outputs it names only."""
    if space.kinds is not None and "coupling" not in space.kinds:
        return []
    instance, local = output.split(".", 1)
    model = problem.instances[instance].model
    if model.error_expression(local) is not None:
        return []
    have = {v.name: v for v in block.variables}
    out = []
    for other in model.outputs:
        name = f"{instance}.{other}"
        if other == local or name not in have or output not in have or \
                have[name].unit != have[output].unit or reads(model, other, local) or \
                (space.declared and name not in space.variables):
            continue
        o2 = block.values(name)
        if not np.all(np.isfinite(o2)) or np.ptp(o2) <= 0:
            continue
        out.append(_Shape(Basis(
            "coupling", name, f"a share of {name} (the outputs couple)", ("cpl",),
            ("{v}",), unit=have[name].unit), _value(name)))
    return out


def _own_powers(problem: Problem, output: str, variables: list[Variable], block: Block,
                space: Space) -> list[_Shape]:
    """The power a current or a voltage of the space dissipates in a resistance the
    sensor's model computes itself, another of its outputs (a thermistor in a divider:
    ``R: Rf*Vth/(Vs - Vth)``, ``T`` from ``R``): ``{v}**2/{R}`` on ``output``; never an
    output that reads ``output`` (no cycle).  A reviewer's divider kept five stand-ins and
    stopped at the round limit without it."""
    if space.kinds is not None and "power" not in space.kinds:
        return []
    instance, local = output.split(".", 1)
    model = problem.instances[instance].model
    have = {v.name: v for v in block.variables}
    out = []
    for other in model.outputs:
        name = f"{instance}.{other}"
        if other == local or name not in have or reads(model, other, local) or \
                (space.declared and name not in space.variables):
            continue
        r = Variable(name, block.values(name), have[name].unit)
        if not np.all(np.isfinite(r.values)) or np.ptp(r.values) <= 0:
            continue
        out += [shape for v in variables if v.kind != "angle"
                and (shape := _power_shape(v, r)) is not None]
    return out


def reads(model: ModelSpec, name: str, target: str) -> bool:
    """Whether the model's definition ``name`` (an output or expression) reads
    ``target``, directly or through other definitions."""
    defs = {**{k: v.node for k, v in model.expressions.items()},
            **{k: o.expr.node for k, o in model.outputs.items()}}
    seen, todo = set(), [name]
    while todo:
        node = defs.get(todo.pop())
        if node is None:
            continue
        for n in expr.names(node):
            if n.name == target:
                return True
            if n.name not in seen:
                seen.add(n.name)
                todo.append(n.name)
    return False


def _gain(output: str, name: str, centre: float) -> Callable[[Block], np.ndarray]:
    return lambda b: (b.values(output) * (b.values(name) - centre))[:, None]


def _value(output: str) -> Callable[[Block], np.ndarray]:
    return lambda b: b.values(output)[:, None]


def _angle_columns(n: int) -> tuple[tuple[str, str], tuple[str, str]]:
    """The coefficient names and YAML terms of the angle times harmonic ``n`` (order 1
    keeps its first names, ``ah_sin``, ``ah_cos``)."""
    tag = "ah" if n == 1 else f"ah{n}"
    factor = "2" if n == 1 else str(2 * n)
    return ((f"{tag}_sin", f"{tag}_cos"),
            (f"{{a}}*sin({factor}*pi*{{v}}/{{period}})",
             f"{{a}}*cos({factor}*pi*{{v}}/{{period}})"))


def _harmonic(name: str, w: float) -> Callable[[Block], np.ndarray]:
    return lambda b: np.column_stack([np.sin(w * b.values(name)), np.cos(w * b.values(name))])


def _linear(name: str, centre: float) -> Callable[[Block], np.ndarray]:
    return lambda b: (b.values(name) - centre)[:, None]


def _ones(b: Block) -> np.ndarray:
    return np.ones((b.hooks.shape[0], 1))


def _affine(name: str, centre: float) -> Callable[[Block], np.ndarray]:
    return lambda b: np.column_stack([np.ones(b.hooks.shape[0]), b.values(name) - centre])


def _quadratic(name: str, centre: float) -> Callable[[Block], np.ndarray]:
    return lambda b: np.column_stack([b.values(name) - centre, (b.values(name) - centre) ** 2])


def _square(name: str, centre: float) -> Callable[[Block], np.ndarray]:
    return lambda b: ((b.values(name) - centre) ** 2)[:, None]


def _cubic(name: str, centre: float) -> Callable[[Block], np.ndarray]:
    return lambda b: ((b.values(name) - centre) ** 3)[:, None]


def _product(v: str, cv: float, w: str, cw: float) -> Callable[[Block], np.ndarray]:
    return lambda b: ((b.values(v) - cv) * (b.values(w) - cw))[:, None]


@functools.cache
def _dimension(unit: str) -> str | None:
    """``current``, ``voltage`` or ``resistance`` where ``unit`` measures one, else None."""
    if not unit:
        return None
    try:
        dim = parse_unit(unit).dimensionality
    except (SymcalError, ValueError, TypeError):   # pragma: no cover - checked on load
        return None
    reg = registry()
    for name, ref in (("current", "ampere"), ("voltage", "volt"), ("resistance", "ohm")):
        if dim == reg.Unit(ref).dimensionality:
            return name
    return None


def _power_form(v: Variable, w: Variable) -> tuple[str, str] | None:
    """The term and its sign in words of the power ``v`` dissipates in the resistance
    ``w`` (``{v}**2*{w}`` for a current, ``{v}**2/{w}`` for a voltage), None where ``v``
    is neither or ``w`` is not a resistance, or either is time."""
    if "drift" in (v.kind, w.kind) or _dimension(w.unit) != "resistance":
        return None
    return {"current": ("{v}**2*{w}", "²·"), "voltage": ("{v}**2/{w}", "²/")}.get(
        _dimension(v.unit) or "")


def _power_shape(v: Variable, r: Variable) -> _Shape | None:
    """The power ``v`` dissipates in the resistance ``r`` as a shape (None: not a pair of
    :func:`_power_form`)."""
    form = _power_form(v, r)
    if form is None:
        return None
    return _Shape(Basis("power", v.name, f"the power dissipated, {v.name}{form[1]}{r.name} "
                        "(self-heating)", ("pow",), (form[0],), unit=v.unit, other=r.name,
                        other_unit=r.unit), _power(v.name, r.name, form[0]), lower=_ones)


def _power(v: str, w: str, form: str) -> Callable[[Block], np.ndarray]:
    if form.endswith("/{w}"):
        return lambda b: (b.values(v) ** 2 / b.values(w))[:, None]
    return lambda b: (b.values(v) ** 2 * b.values(w))[:, None]


def _angle_harmonic(a: str, v: str, w: float) -> Callable[[Block], np.ndarray]:
    return lambda b: b.values(a)[:, None] * np.column_stack(
        [np.sin(w * b.values(v)), np.cos(w * b.values(v))])


def _on_output(blocks: list[Block], h: int, f: Callable[[Block], np.ndarray]) -> Raw:
    """Columns ``f`` (N × m per block) added to output ``h``: their raw regressor."""
    return lambda i: blocks[i].hooks[:, :, h][:, :, None] * f(blocks[i])[:, None, :]


def _in_space(groups: list[tuple[Variable, set[str]]], space: Space, never: set[str]
              ) -> list[Variable]:
    """The distinct variables of a space (any name equal to one of its names), never a
    derived one or an excluded column."""
    wanted = set(space.variables)
    out = []
    for var, names in groups:
        if var.kind == "derived" or names & never:
            continue
        if names & wanted:
            out.append(var)
    return out


def _unused(problem: Problem, groups: list[tuple[Variable, set[str]]], space: Space
            ) -> tuple[str, ...]:
    """The declared variables of ``space`` that are computed from another sensor's
    outputs: no term uses them (:func:`_in_space`)."""
    own = {f"{space.instance}.{o}" for o in problem.instances[space.instance].model.outputs}
    derived = {n for var, names in groups if var.kind == "derived" for n in names}
    return tuple(n for n in space.variables if n in derived and n not in own)


def output_entries(problem: Problem, blocks: list[Block], fit: int
                   ) -> tuple[list[Entry], dict[str, Space]]:
    """Every (output × shape) candidate of every instance's space, with its regressor."""
    hp = problem.diagnostic
    never = excluded(problem)
    groups = distinct_groups(blocks[fit].variables)
    found = {name: replace(sp, unused=_unused(problem, groups, sp)) if sp.declared else sp
             for name, sp in spaces(problem).items()}
    out: list[Entry] = []
    for h, output in enumerate(hp.hooks):
        if all(not np.any(b.hooks[:, :, h]) for b in blocks):
            continue
        instance = output.split(".", 1)[0]
        if instance not in found:
            continue
        space = found[instance]
        variables = _in_space(groups, space, never)
        shapes = _shapes(variables, blocks[fit], space)
        shapes += _gains(problem, output, groups, variables, blocks[fit], space)
        shapes += _couplings(problem, output, blocks[fit], space)
        shapes += _own_powers(problem, output, variables, blocks[fit], space)
        out += _entries(blocks, fit, h, output, shapes, variables)
    return out, found


def _entries(blocks: list[Block], fit: int, h: int, output: str, shapes: list[_Shape],
             variables: list[Variable]) -> list[Entry]:
    """The candidates of ``shapes`` on output ``h``, with their regressors."""
    sigma = output_sigma(blocks[fit], h)
    out: list[Entry] = []
    for shape in shapes:
        phi = shape.phi
        basis = _with_scales(shape.basis, sigma, phi(blocks[fit]))

        def raw(i: int, phi: Callable = phi) -> np.ndarray:
            b = blocks[i]
            return b.hooks[:, :, h][:, :, None] * phi(b)[:, None, :]

        extra = None
        if shape.contains or shape.beyond is not None:
            parts = [_linear(n, 0.0 if v.kind == "drift" else centre_of(blocks[fit].values(n)))
                     for n in shape.contains
                     for v in variables if v.name == n]
            if shape.beyond is not None:
                parts.append(shape.beyond)

            def extra(i: int, parts: list = parts) -> np.ndarray:
                b = blocks[i]
                f = np.column_stack([p(b) for p in parts])
                return b.hooks[:, :, h][:, :, None] * f[:, None, :]

        lower = None if shape.lower is None else _on_output(blocks, h, shape.lower)
        out.append(Entry(Candidate(output, basis), raw, extra, lower))
    return out


def outside_entries(problem: Problem, blocks: list[Block], fit: int,
                    found: Mapping[str, Space]) -> list[Entry]:
    """The couplings no search space holds, tested as a family of their own: on each
    output of an instance whose variables are the default (not declared) and whose kinds
    allow a linear term, a term linear in a reading of another instance (a column it is
    bound to) that is not in the instance's space (crosstalk from a current channel into
    a voltage channel).  None where the problem has one instance."""
    hp = problem.diagnostic
    never = excluded(problem)
    groups = distinct_groups(blocks[fit].variables)
    out: list[Entry] = []
    for h, output in enumerate(hp.hooks):
        instance = output.split(".", 1)[0]
        space = found.get(instance)
        if space is None or space.declared or (space.kinds is not None
                                                and "linear" not in space.kinds):
            continue
        if all(not np.any(b.hooks[:, :, h]) for b in blocks):
            continue
        others = sorted({text for name, inst in problem.instances.items() if name != instance
                         for text in inst.bindings.values() if text in problem.column_specs}
                        - set(space.variables))
        mine = {id(v) for v in _in_space(groups, space, never)}
        outside = Space(instance, tuple(others), ("linear",), (), "outside")
        variables = [v for v in _in_space(groups, outside, never) if id(v) not in mine]
        out += _entries(blocks, fit, h, output, _shapes(variables, blocks[fit], outside),
                        variables)
    return out


def _with_scales(basis: Basis, sigma: float, phi: np.ndarray) -> Basis:
    """The basis with its coefficients' scales (terms of about ``sigma`` RMS)."""
    return replace(basis, scales=_scales(sigma, phi), term=sigma)


def fixed_entries(problem: Problem, blocks: list[Block], fit: int, free: np.ndarray,
                  gauge_fixes: set[str]) -> list[Entry]:
    """Each parameter the user fixed that no gauge needs fixed, as "this value is off"."""
    fixed = [n for n, f in zip(problem.parameter_names, free, strict=True) if not f]
    allowed = set(problem.candidates.fixed) if problem.candidates.where is not None \
        else set(fixed)
    out = []
    for k, name in enumerate(fixed):
        if name in gauge_fixes or name not in allowed:
            continue
        param = problem.parameters[problem.index[name]]
        x = blocks[fit].jac_fixed[:, :, k]
        if not np.any(x):
            continue
        scale = column_scale(blocks[fit], x)
        doc = f" ({param.doc})" if param.doc else ""
        basis = Basis("fixed", name, f"the fixed parameter {name}{doc} is off", ("delta",),
                      (), unit=param.unit, scales=(float(f"{scale:.3g}"),), term=scale,
                      centre=param.value, targets=(name,))
        out.append(Entry(Candidate("", basis), _derivative_raw(blocks, "jac_fixed", k)))
    return out


def _derivative_raw(blocks: list[Block], field: str, k: int) -> Raw:
    """The regressor of one derivative a block holds: column ``k`` of its ``field``
    (``jac_fixed``, ``jac_columns``)."""
    def raw(i: int) -> np.ndarray:
        jac: np.ndarray = getattr(blocks[i], field)
        return jac[:, :, k:k + 1]
    return raw


def constant_entries(problem: Problem, blocks: list[Block], fit: int) -> list[Entry]:
    """Each constant as "this value is off": a problem constant alone; a model's
    constant once for all the instances that share it (one pitch of one platen), and for
    each instance alone where several share it."""
    index = {c.key: k for k, c in enumerate(problem.diagnostic.constants)}
    groups: dict[tuple[str, str], list] = {}
    for c in problem.constants:
        if c.tested and c.key in index:
            groups.setdefault((str(c.model_file or ""), c.name), []).append(c)
    out = []
    for members in groups.values():
        sets = [members] + ([[c] for c in members] if len(members) > 1 else [])
        for chosen in sets:
            keys = [index[c.key] for c in chosen]
            x = blocks[fit].jac_constants[:, :, keys].sum(axis=2)
            if not np.any(x):
                continue
            first = chosen[0]
            doc = f"{first.doc} " if first.doc else ""
            whose = (f"{first.instance}'s " if len(chosen) == 1 and first.instance
                     else "the ")
            shared = (f" (shared by {', '.join(c.instance for c in chosen)})"
                      if len(chosen) > 1 else "")
            centre = centre_variable(first.doc)
            text = (f"{whose}{first.name}{shared}, the centre of its term in {centre}, is off"
                    if centre is not None else f"{whose}{doc}{first.name}{shared} is off")
            scale = column_scale(blocks[fit], x)
            basis = Basis("constant", first.name, text, ("delta",), (),
                          unit=first.unit, scales=(float(f"{scale:.3g}"),), term=scale,
                          centre=first.value * DISPLAY_UNITS[first.unit],
                          targets=tuple(c.key for c in chosen))
            out.append(Entry(Candidate("", basis), _constant_raw(blocks, keys)))
    return out


def _constant_raw(blocks: list[Block], keys: list[int]) -> Raw:
    def raw(i: int) -> np.ndarray:
        return blocks[i].jac_constants[:, :, keys].sum(axis=2)[:, :, None]
    return raw


def latency_entries(problem: Problem, blocks: list[Block], fit: int,
                    found: Mapping[str, Space]) -> list[Entry]:
    """Each instance reading data columns late by one delay, where some dataset's rows
    are time-ordered and its columns move smoothly."""
    time = next((c for c, s in problem.column_specs.items() if s.role == "time"), None)
    if time is None:
        return []
    hp = problem.diagnostic
    index = {c: k for k, c in enumerate(hp.columns)}
    out = []
    for name, inst in problem.instances.items():
        space = found.get(name)
        if space is not None and space.kinds is not None and "latency" not in space.kinds:
            continue
        cols = sorted({c for c in inst.bindings.values() if c in index and c != time})
        if not cols:
            continue
        noise = {c: r.sigma for c, r in problem.noise_columns().items()}
        found_rates = [_rates(b, time, cols, noise) for b in blocks]
        rates = [None if r is None else r[0] for r in found_rates]
        if all(r is None for r in rates):
            continue
        left = next(r[1] for r in (found_rates[fit], *found_rates) if r is not None)

        def raw(i: int, cols: list[str] = cols, rates: list = rates) -> np.ndarray:
            b = blocks[i]
            if rates[i] is None:
                return np.zeros((b.dataset.n, len(b.names), 1))
            x = sum(b.jac_columns[:, :, index[c]] * rates[i][:, j][:, None]
                    for j, c in enumerate(cols))
            return np.asarray(x)[:, :, None]

        x_fit = raw(fit)[:, :, 0]
        scale = column_scale(blocks[fit], x_fit) if np.any(x_fit) else 1e-3
        basis = Basis("latency", name, f"{name}'s readings ({', '.join(cols)}) lag by a "
                      "constant delay", ("tau",), (), unit="s",
                      scales=(float(f"{scale:.3g}"),), term=scale, targets=tuple(cols),
                      rate_noise=left)
        out.append(Entry(Candidate("", basis), raw))
    return out


#: A reading's zero is a sensor's own offset where the derivative by one of the sensor's
#: parameters, or by a constant of its model the search tests, has at least this cosine
#: with the derivative by the reading (both over the fitted rows): an offset it has, free
#: (its calibration is what absorbs the zero), fixed or a constant (the fixed parameter or
#: the constant that is off is the same candidate, named as the model names it: a
#: thermistor's lead resistance in series with the part is the zero of its resistance).
OWN_OFFSET = 0.999


def zero_entries(problem: Problem, blocks: list[Block], fit: int,
                 found: Mapping[str, Space], free: np.ndarray) -> list[Entry]:
    """Each data column the sensors read as "its zero is off" (see the module): one
    candidate per column, for every sensor that reads it, where the spaces of all of them
    allow the kind.  Not for a column a problem-level expression, constraint or comparison
    reads itself (the revision adds the offset where the sensors read the column, which
    would leave those reading it as it is), nor where a sensor that reads it has an offset
    of its own (:data:`OWN_OFFSET`; ``free``: the fit's free parameters)."""
    hp = problem.diagnostic
    index = {c: k for k, c in enumerate(hp.columns)}
    specs = problem.column_specs
    never = excluded(problem) | direct_columns(problem)
    reads = {name: list(dict.fromkeys(n.name for text in inst.bindings.values()
                                      for n in expr.names(expr.parse(text))))
             for name, inst in problem.instances.items()}    # in the bindings' order
    readers: dict[str, list[str]] = {}
    for name, names in reads.items():
        for col in names:
            if col in specs and col in index:
                readers.setdefault(col, []).append(name)
    derivatives = _derivatives(problem, blocks[fit], free)
    out = []
    for col, insts in readers.items():
        spec = specs[col]
        if col in never or spec.role in ("time", *NEVER) or spec.rate_of:
            continue
        if any((sp := found.get(i)) is not None and sp.kinds is not None
               and "zero" not in sp.kinds for i in insts):
            continue
        k = index[col]
        x_fit = blocks[fit].jac_columns[:, :, k]
        # the sensors' own parameters and constants, and the problem's parameters their
        # inputs read (``dp + zero_dp``: a zero kept)
        own = [d for name, d in derivatives if name.split(".", 1)[0] in insts
               or any(name in reads[i] for i in insts)]
        if not np.any(x_fit) or _own_offset(own, x_fit):
            continue
        scale = column_scale(blocks[fit], x_fit)
        basis = Basis("zero", col, f"the zero of {col} (read by {', '.join(insts)}) is off",
                      ("zero",), (), unit=spec.unit, scales=(float(f"{scale:.3g}"),),
                      term=scale, targets=tuple(insts))
        out.append(Entry(Candidate("", basis), _derivative_raw(blocks, "jac_columns", k)))
    return out


def _derivatives(problem: Problem, block: Block, free: np.ndarray
                 ) -> list[tuple[str, np.ndarray]]:
    """Every parameter's (free or fixed) and tested instance constant's derivative of the
    residuals on ``block`` (N × n_q), by name (``th2.r_lead`` for a constant)."""
    names = problem.parameter_names
    out = [(n, block.jac[:, :, j]) for j, n in
           enumerate(n for n, f in zip(names, free, strict=True) if f)]
    out += [(n, block.jac_fixed[:, :, j]) for j, n in
            enumerate(n for n, f in zip(names, free, strict=True) if not f)]
    index = {c.key: k for k, c in enumerate(problem.diagnostic.constants)}
    out += [(f"{c.instance}.{c.name}", block.jac_constants[:, :, index[c.key]])
            for c in problem.constants
            if c.tested and c.instance is not None and c.key in index
            and index[c.key] < block.jac_constants.shape[2]]
    return out


def _own_offset(own: list[np.ndarray], x: np.ndarray) -> bool:
    """Whether one of the derivatives ``own`` moves the residuals as the zero of the
    reading does (``x``, N × n_q): :data:`OWN_OFFSET`."""
    flat = x.ravel()
    norm = float(np.linalg.norm(flat))
    for col in own:
        other = col.ravel()
        size = float(np.linalg.norm(other))
        if size > 0 and abs(float(flat @ other)) >= OWN_OFFSET * norm * size:
            return True
    return False


def direct_columns(problem: Problem) -> set[str]:
    """The data columns a problem-level expression, constraint, comparison, implicit
    definition or bound constant reads by name (not through a sensor's inputs)."""
    system = problem.spec.system
    nodes = []
    for group in (system.expressions, system.constraints, system.comparisons,
                  system.implicit):
        for item in group.values():
            nodes += [v.node for v in vars(item).values() if isinstance(v, ExprSpec)]
    for inst in system.instances.values():
        nodes += [v.node for v in inst.constants.values()]
    return {n.name for node in nodes for n in expr.names(node)} & set(problem.column_specs)


def _rates(block: Block, time: str, cols: list[str], noise: Mapping[str, float]
           ) -> tuple[np.ndarray, tuple[float, ...]] | None:
    """The columns' time derivatives (internal units per second) on a dataset whose rows
    are time-ordered and whose columns move smoothly, with the noise their declared
    noise leaves in each (root mean square; 0 where none is declared); None elsewhere.
    As the derived column the revision declares computes them: smoothed where a column's
    declared noise (``noise``, internal units) would leave its rate noisy."""
    ds = block.dataset
    if time not in ds.columns or ds.n < 5:
        return None
    t = np.asarray(ds.columns[time], dtype=float) * DISPLAY_UNITS[_unit(block, time)]
    if np.any(np.diff(t) <= 0):
        return None
    out = []
    left: list[float] = []
    moving = False
    for c in cols:
        v = block.values(c) if c in block.regressors or any(
            x.name == c for x in block.variables) else np.asarray(ds.columns[c], dtype=float)
        var = float(np.var(v))
        if var <= 0:
            out.append(np.zeros_like(v))
            left.append(0.0)
            continue
        ratio = float(np.mean(np.diff(v) ** 2)) / (2 * var)
        if ratio > SMOOTH:
            return None
        moving = True
        found, noisy = rate_and_noise(v, t, noise.get(c))
        out.append(found)
        left.append(noisy)
    return (np.column_stack(out), tuple(left)) if moving else None


def _unit(block: Block, col: str) -> str:
    return next((v.unit for v in block.variables if v.name == col), "")
