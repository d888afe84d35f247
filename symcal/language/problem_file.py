"""Calibration problem files (``problems/*.yaml``) → validated, frozen :class:`ProblemSpec`."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import SpecError, Where, excerpt
from symcal.base.files import LINK_LOOP, input_refusal, resolve
from symcal.base.options import METHODS, SolveOptions
from symcal.language import expr
from symcal.language.candidates import (
    CandidatesSpec,
    ProblemCandidatesSpec,
    parse_candidates,
    parse_problem_candidates,
)
from symcal.language.common import (
    ConstantSpec,
    ExprSpec,
    ParameterSpec,
    check_unique,
    display_unit,
    parse_constant,
    parse_expr,
    parse_parameter,
    section,
)
from symcal.language.courier import PRESETS
from symcal.language.dimensions import same_dimension
from symcal.language.fields import (
    MAX_SAMPLES,
    check_keys,
    child_where,
    expect_bool,
    expect_choice,
    expect_int,
    expect_list,
    expect_map,
    expect_name,
    expect_number,
    expect_str,
    expect_symbol,
)
from symcal.language.loss import LossSpec, parse_loss
from symcal.language.model_file import (
    ImplicitSpec,
    ModelSpec,
    expression_nodes,
    load_model,
    parse_implicit,
)
from symcal.language.noise import NoiseSpec, parse_noise
from symcal.language.overlay import extends_chain, load_with_extends, merge_problem
from symcal.language.solver import parse_solver
from symcal.language.yamlio import MAX_BYTES, YMap, display_path

PROBLEM_KEYS = ["doc", "extends", "constants", "parameters", "columns", "expressions",
                "comparisons", "stages", "weighting", "implicit", "solver", "noise",
                "candidates"]
#: ``auto`` (not written): ``propagated`` where every reading of the constraints declares
#: its noise and no constraint has a robust loss, else ``equal``.
WEIGHTINGS = ("equal", "estimated", "propagated")
#: What a column may be declared as (``role:``): the time of an observation, a raw
#: position reading along which residuals are plotted, a category (a pose or window
#: index), a sample counter, an external reference reading, or a measured state of the
#: system or its environment any sensor may depend on (an ambient temperature).
ROLES = ("time", "axis", "label", "index", "reference", "state")
#: Roles of columns that are never an effect on a sensor (nor is any column a comparison
#: uses as its reference).
NOT_EFFECTS = ("label", "index", "reference")


#: A dataset's roles: the data a problem is fitted on, and data held out to check it.
FIT, CHECK = "fit", "check"
DATASET_ROLES = (FIT, CHECK)
#: The one place the name is written: a dataset of this name is the one fitted unless a
#: dataset declares ``role: fit``.
DEFAULT_FIT = "calibration"


@dataclass(frozen=True)
class ColumnSpec:
    """A data column the problem may refer to by name; ``role`` is "" or one of
    :data:`ROLES`; ``noise`` is the declared standard deviation of its readings (None: not
    declared); ``rate_of`` names the column whose time derivative this one is, computed
    when a dataset is loaded (:mod:`symcal.data.derived`; "": read from the data)."""

    name: str
    unit: str
    doc: str
    where: Where
    role: str = ""
    noise: NoiseSpec | None = None
    rate_of: str = ""


@dataclass(frozen=True)
class InstanceSpec:
    """A sensor instance: a model with its inputs bound, parameter overrides and the
    noise of its inputs where it overrides the model's (``noise: {p: 1 um}``)."""

    name: str
    model: ModelSpec
    bindings: dict[str, ExprSpec]
    overrides: dict[str, tuple[YMap, Where]]
    doc: str
    where: Where
    noise: dict[str, NoiseSpec] = field(default_factory=dict)
    #: Model constants bound to a problem expression (``constants: {rho: rho}``): the
    #: instance uses the expression's value instead of the model's.
    constants: dict[str, ExprSpec] = field(default_factory=dict)
    #: The instance's own search space (``candidates:``), over its model's; None: its
    #: model's (which may be None too).
    candidates: CandidatesSpec | None = None


@dataclass(frozen=True)
class QuantitySpec:
    """A named expression, constraint or comparison side, with display unit and weight;
    a constraint may carry a robust ``loss``."""

    name: str
    expr: ExprSpec
    unit: str
    sigma: float
    doc: str
    where: Where
    loss: LossSpec | None = None
    #: True when ``sigma`` is written (in the constraint's unit), False for the default 1
    #: (one internal unit: the constraint unweighted).
    sigma_given: bool = False


@dataclass(frozen=True)
class ComparisonSpec:
    """An estimate compared against an independent reference sensor."""

    name: str
    estimate: ExprSpec
    reference: ExprSpec
    unit: str
    datasets: tuple[str, ...] | None
    remove_mean: bool
    doc: str
    where: Where


@dataclass(frozen=True)
class DatasetSpec:
    """Where a named dataset comes from (a CSV/NPZ file or a simulated scenario run) and
    its role: ``fit`` (the data the problem is solved on: one per problem) or ``check``
    (held out: evaluated at the estimate, never fitted)."""

    name: str
    path: Path | None
    scenario: Path | None
    run: str | None
    seed: int
    n: int | None
    doc: str
    where: Where
    role: str = "check"

    @property
    def source(self) -> str:
        """Human-readable origin of the data."""
        if self.path is not None:
            return display_path(self.path)
        assert self.scenario is not None  # a dataset has a path or a scenario
        return f"simulated {display_path(self.scenario)} run '{self.run}' seed {self.seed}"


@dataclass(frozen=True)
class StageSpec:
    """One step of a staged calibration: which constraints, which parameters free."""

    name: str
    constraints: tuple[str, ...]
    free: tuple[tuple[str, Where], ...]
    method: str
    doc: str
    where: Where


@dataclass(frozen=True)
class SystemSpec:
    """What is measured: the sensors, their redundancy and the reference comparisons."""

    constants: dict[str, ConstantSpec]
    parameters: dict[str, ParameterSpec]
    columns: dict[str, ColumnSpec]
    instances: dict[str, InstanceSpec]
    expressions: dict[str, QuantitySpec]
    constraints: dict[str, QuantitySpec]
    comparisons: dict[str, ComparisonSpec]
    implicit: dict[str, ImplicitSpec] = field(default_factory=dict)
    #: The problem's ``noise:`` section: a column or an instance input (``s1.p``) → its
    #: noise, over every other declaration of it.
    noise: dict[str, NoiseSpec] = field(default_factory=dict)
    #: The problem's ``candidates:`` section (which constants and fixed parameters the
    #: search may test); None: not written.
    candidates: ProblemCandidatesSpec | None = None


@dataclass(frozen=True)
class StudySpec:
    """On what data, in which steps: the datasets, the stages and the weighting."""

    datasets: dict[str, DatasetSpec]
    stages: tuple[StageSpec, ...]
    weighting: str


@dataclass(frozen=True)
class ProblemSpec:
    """A calibration problem as declared in YAML: the system, the study, the solve options."""

    name: str
    doc: str
    path: Path
    system: SystemSpec
    study: StudySpec
    options: SolveOptions
    where: Where
    sources: tuple[Path, ...] = ()


def _doc(entry: YMap, where: Where) -> str:
    return expect_str(entry["doc"], child_where(entry, where, "doc")) if "doc" in entry else ""


def _relative(base: Path, value: Any, where: Where) -> Path:
    text = expect_str(value, where)
    try:
        return resolve(base.parent / text)
    except OSError:
        raise SpecError(where, f"{display_path(base.parent / text)} is {LINK_LOOP}") from None


def _nearby(path: Path) -> str:
    """A did-you-mean among the YAML files beside where ``path`` was looked for."""
    try:
        names = sorted(p.name for p in path.parent.iterdir()
                       if p.suffix in (".yaml", ".yml") and p.is_file())
    except OSError:
        return ""
    hint = did_you_mean(path.name, names)
    found = next((n for n in names if hint == f" (did you mean '{n}'?)"), None)
    return "" if found is None else f" (did you mean '{display_path(path.with_name(found))}'?)"


class _ModelCache:
    def __init__(self) -> None:
        self.models: dict[Path, ModelSpec] = {}

    def get(self, path: Path, where: Where) -> ModelSpec:
        if path not in self.models:
            if not path.exists():
                raise SpecError(where, f"model file not found: {display_path(path)}"
                                       f"{_nearby(path)}")
            reason = input_refusal(path, MAX_BYTES)
            if reason is not None:
                raise SpecError(where, f"cannot read model file {display_path(path)}: it "
                                       f"{reason}")
            self.models[path] = load_model(path)
        return self.models[path]


def _parse_instance(
    name: str, value: Any, where: Where, base: Path, cache: _ModelCache
) -> InstanceSpec:
    expect_symbol(name, where, "an instance's name")
    entry = check_keys(value, where, required=["model", "inputs"],
                       optional=["parameters", "noise", "constants", "candidates", "doc"])
    model_at = child_where(entry, where, "model")
    model = cache.get(_relative(base, entry["model"], model_at), model_at)
    inputs_at = child_where(entry, where, "inputs")
    inputs = expect_map(entry["inputs"], inputs_at)
    bindings: dict[str, ExprSpec] = {}
    for key, text in inputs.items():
        at = child_where(inputs, inputs_at, key)
        if key not in model.inputs:
            raise SpecError(at, _not_in(key, "an input", model.name, list(model.inputs)))
        bindings[key] = parse_expr(text, at)
    for key in model.inputs:
        if key not in bindings:
            raise SpecError(inputs_at, f"input '{key}' of model '{model.name}' is not bound "
                                       f"(add '{key}: <column or expression>')")
    overrides: dict[str, tuple[YMap, Where]] = {
        key: (check_keys(val, at, optional=["value", "lower", "upper", "fixed", "scale"]), at)
        for key, val, at in _model_entries(entry, where, "parameters", model,
                                           list(model.parameters), "a parameter")}
    noise: dict[str, NoiseSpec] = {
        key: parse_noise(val, at, model.inputs[key].unit)
        for key, val, at in _model_entries(entry, where, "noise", model, list(model.inputs),
                                           "an input")}
    constants: dict[str, ExprSpec] = {
        key: parse_expr(val, at)
        for key, val, at in _model_entries(entry, where, "constants", model,
                                           list(model.constants), "a constant")}
    candidates = (parse_candidates(entry["candidates"], child_where(entry, where, "candidates"))
                  if "candidates" in entry else None)
    return InstanceSpec(name, model, bindings, overrides, _doc(entry, where), where, noise,
                        constants, candidates)


def _model_entries(entry: YMap, where: Where, part: str, model: ModelSpec,
                   names: list[str], what: str) -> Iterator[tuple[str, Any, Where]]:
    """The keys, values and places of an instance's map ``part`` (``parameters``,
    ``noise``, ...), each key refused unless it is one of the model's ``names`` (``what``:
    "a parameter", ...)."""
    part_at = child_where(entry, where, part)
    items = expect_map(entry.get(part), part_at)
    for key, val in items.items():
        at = child_where(items, part_at, key)
        if key not in names:
            raise SpecError(at, _not_in(key, what, model.name, names))
        yield key, val, at


def _not_in(key: str, what: str, model: str, names: list[str]) -> str:
    return (f"'{key}' is not {what} of model '{model}'{did_you_mean(key, names)}; "
            f"it has: {', '.join(names) or 'none'}")


def _parse_quantity(name: str, value: Any, where: Where, weighted: bool) -> QuantitySpec:
    expect_symbol(name, where)
    if not isinstance(value, dict):
        return QuantitySpec(name, parse_expr(value, where), "", 1.0, "", where)
    optional = ["unit", "doc"] + (["sigma", "loss"] if weighted else [])
    entry = check_keys(value, where, required=["expr"], optional=optional)
    sigma = 1.0
    if "sigma" in entry:
        at = child_where(entry, where, "sigma")
        sigma = expect_number(entry["sigma"], at)
        if sigma <= 0:
            raise SpecError(at, f"sigma must be positive, found {entry['sigma']}")
    unit = display_unit(entry.get("unit"), child_where(entry, where, "unit"))
    loss = (parse_loss(entry["loss"], child_where(entry, where, "loss"), unit)
            if "loss" in entry else None)
    return QuantitySpec(
        name, parse_expr(entry["expr"], child_where(entry, where, "expr")), unit, sigma,
        _doc(entry, where), where, loss, "sigma" in entry,
    )


def _parse_comparison(name: str, value: Any, where: Where) -> ComparisonSpec:
    expect_name(name, where)
    entry = check_keys(value, where, required=["estimate", "reference"],
                       optional=["unit", "datasets", "remove_mean", "doc"])
    datasets = None
    if "datasets" in entry:
        at = child_where(entry, where, "datasets")
        items = expect_list(entry["datasets"], at)
        datasets = tuple(expect_name(v, child_where(items, at, i), "a dataset name")
                         for i, v in enumerate(items))
    remove_mean = True
    if "remove_mean" in entry:
        remove_mean = expect_bool(entry["remove_mean"], child_where(entry, where, "remove_mean"))
    return ComparisonSpec(
        name,
        parse_expr(entry["estimate"], child_where(entry, where, "estimate")),
        parse_expr(entry["reference"], child_where(entry, where, "reference")),
        display_unit(entry.get("unit"), child_where(entry, where, "unit")),
        datasets, remove_mean, _doc(entry, where), where,
    )


def _parse_dataset(name: str, value: Any, where: Where, base: Path) -> DatasetSpec:
    expect_name(name, where, "a dataset's name")
    entry = check_keys(value, where,
                       optional=["path", "simulate", "run", "seed", "n", "role", "doc"])
    role = ""                                   # not declared: resolved with the others
    if "role" in entry:
        role = expect_choice(entry["role"], child_where(entry, where, "role"), DATASET_ROLES,
                             "role")
    has_path, has_sim = "path" in entry, "simulate" in entry
    if has_path == has_sim:
        raise SpecError(where, "a dataset needs exactly one of 'path' (a CSV or NPZ file) "
                               "or 'simulate' (a scenario file)")
    if has_path:
        for key in ("run", "seed", "n"):
            if key in entry:
                raise SpecError(child_where(entry, where, key),
                                f"'{key}' only applies to simulated datasets")
        path = _relative(base, entry["path"], child_where(entry, where, "path"))
        return DatasetSpec(name, path, None, None, 0, None, _doc(entry, where), where, role)
    scenario = _relative(base, entry["simulate"], child_where(entry, where, "simulate"))
    run = (expect_name(entry["run"], child_where(entry, where, "run"), "a run name")
           if "run" in entry else name)
    seed = (expect_int(entry["seed"], child_where(entry, where, "seed"), 0)
            if "seed" in entry else 0)
    n = (expect_int(entry["n"], child_where(entry, where, "n"), 1, MAX_SAMPLES)
         if "n" in entry else None)
    return DatasetSpec(name, None, scenario, run, seed, n, _doc(entry, where), where, role)


def _resolve_roles(datasets: dict[str, DatasetSpec]) -> dict[str, DatasetSpec]:
    """Datasets with their roles: a declared role as declared; without one, the dataset
    named :data:`DEFAULT_FIT` is fitted when no dataset declares ``role: fit``, and every
    other is held out."""
    declared_fit = any(d.role == FIT for d in datasets.values())

    def role(d: DatasetSpec) -> str:
        if d.role:
            return d.role
        return FIT if d.name == DEFAULT_FIT and not declared_fit else CHECK

    return {k: replace(d, role=role(d)) for k, d in datasets.items()}


def _parse_stage(index: int, value: Any, where: Where, constraints: dict) -> StageSpec:
    entry = check_keys(value, where, required=["name", "constraints", "free"],
                       optional=["method", "doc"])
    name = expect_name(entry["name"], child_where(entry, where, "name"), "a stage's name")
    at = child_where(entry, where, "constraints")
    items = expect_list(entry["constraints"], at)
    if not items:
        raise SpecError(at, "a stage needs at least one constraint")
    names = []
    for i, item in enumerate(items):
        item_at = child_where(items, at, i)
        if item not in constraints:
            raise SpecError(item_at, f"unknown constraint '{excerpt(item)}'"
                                     f"{did_you_mean(str(item), constraints)}; "
                                     f"constraints: {', '.join(constraints)}")
        names.append(item)
    at = child_where(entry, where, "free")
    items = expect_list(entry["free"], at)
    if not items:
        raise SpecError(at, "a stage needs at least one free parameter (a name or a pattern)")
    free = tuple((expect_str(v, child_where(items, at, i)), child_where(items, at, i))
                 for i, v in enumerate(items))
    method = "auto"
    if "method" in entry:
        method = expect_choice(entry["method"], child_where(entry, where, "method"), METHODS,
                               "method")
    return StageSpec(name, tuple(names), free, method, _doc(entry, where), where)


def _parse_stages(doc: YMap, where: Where, constraints: dict) -> tuple[StageSpec, ...]:
    if "stages" not in doc:
        return ()
    at = child_where(doc, where, "stages")
    items = expect_list(doc["stages"], at)
    stages = tuple(_parse_stage(i, v, child_where(items, at, i), constraints)
                   for i, v in enumerate(items))
    seen: set[str] = set()
    for stage in stages:
        if stage.name in seen:
            raise SpecError(stage.where, f"stage '{stage.name}' is defined twice")
        seen.add(stage.name)
    return stages


def _parse_column(name: str, value: Any, where: Where) -> ColumnSpec:
    expect_symbol(name, where, "a column's name")
    entry = check_keys(value, where, optional=["unit", "doc", "role", "noise", "rate_of"])
    role = (expect_choice(entry["role"], child_where(entry, where, "role"), ROLES, "role")
            if "role" in entry else "")
    unit = display_unit(entry.get("unit"), child_where(entry, where, "unit"))
    noise = (parse_noise(entry["noise"], child_where(entry, where, "noise"), unit)
             if "noise" in entry else None)
    rate_of = (expect_symbol(entry["rate_of"], child_where(entry, where, "rate_of"),
                             "a column's name") if "rate_of" in entry else "")
    return ColumnSpec(name, unit, _doc(entry, where), where, role, noise, rate_of)


def _parse_columns(doc: YMap, where: Where) -> dict[str, ColumnSpec]:
    """``columns:`` as a mapping of columns, or the name of a preset (``courier``)."""
    at = child_where(doc, where, "columns")
    value = doc.get("columns")
    if isinstance(value, str):
        if value not in PRESETS:
            raise SpecError(at, f"unknown column preset '{excerpt(value)}'"
                                f"{did_you_mean(value, PRESETS)}; presets: "
                                f"{', '.join(PRESETS)} (or a mapping of columns)")
        return {k: ColumnSpec(k, unit, text, at, role,
                              None if noise is None else parse_noise(noise, at, unit))
                for k, (unit, role, text, noise) in PRESETS[value].items()}
    mapping = expect_map(value, at)
    columns = {k: _parse_column(k, v, child_where(mapping, at, k)) for k, v in mapping.items()}
    return {k: _check_rate(c, columns) if c.rate_of else c for k, c in columns.items()}


def _check_rate(col: ColumnSpec, columns: dict[str, ColumnSpec]) -> ColumnSpec:
    """A derived column (``rate_of: SOURCE``): its source is a column read from the data,
    the problem declares one time column, and the unit is the source's per the time's
    (written, or that by default)."""
    from symcal.base.units import parse_unit, text_of

    at = col.where.child("rate_of")
    source = columns.get(col.rate_of)
    if source is None or source.name == col.name:
        others = [k for k in columns if k != col.name]
        raise SpecError(at, f"'{excerpt(col.rate_of)}' is not another column of the problem"
                            f"{did_you_mean(col.rate_of, others)}; 'rate_of' names the column "
                            f"whose time derivative '{col.name}' is")
    if source.rate_of:
        raise SpecError(at, f"'{source.name}' is itself a rate (rate_of: {source.rate_of}); "
                            "a rate is computed from a column read from the data")
    times = [c for c in columns.values() if c.role == "time"]
    if len(times) != 1:
        found = ("no column declares 'role: time'" if not times else
                 f"{len(times)} columns declare it ({', '.join(c.name for c in times)})")
        raise SpecError(at, f"the rate of '{source.name}' is computed against the problem's "
                            f"time column, and {found}: declare exactly one, e.g. "
                            "columns: {t: {unit: s, role: time}}")
    if times[0].name == source.name:
        raise SpecError(at, f"'{source.name}' is the time column: its rate is 1")
    rate = parse_unit(source.unit or "1") / parse_unit(times[0].unit or "1")
    if not col.unit:
        return replace(col, unit=text_of(rate) or "")
    if not same_dimension(parse_unit(col.unit), rate):
        raise SpecError(col.where.child("unit"),
                        f"'{col.name}' is the rate of '{source.name}' ({source.unit or 'no unit'}"
                        f" per {times[0].unit or 'unit of time'}), but its unit '{col.unit}' "
                        f"measures something else")
    return col


def _check_candidates(instances: dict[str, InstanceSpec], columns: dict[str, ColumnSpec],
                      expressions: dict[str, QuantitySpec]) -> None:
    """The variables of an instance's ``candidates:``: its model's own names, the
    problem's columns and expressions, and other instances' signals (``s3.p``)."""
    signals = [f"{i}.{n}" for i, inst in instances.items()
               for n in (*inst.model.inputs, *inst.model.outputs, *inst.model.expressions)
               if not n.startswith("base.")]
    for inst in instances.values():
        if inst.candidates is None:
            continue
        model = inst.model
        own = [n for n in (*model.inputs, *model.outputs, *model.expressions)
               if not n.startswith("base.")]
        for name, at in inst.candidates.variables or ():
            if name in own or name in columns or name in expressions or name in signals:
                continue
            known = [*own, *columns, *expressions, *signals]
            raise SpecError(at, f"'{excerpt(name)}' is not a name of instance '{inst.name}' "
                                f"(an input, output or expression of model '{model.name}'), "
                                f"a column, a problem expression or another instance's "
                                f"signal{did_you_mean(name, known)}")


#: Most expression nodes a problem may expand to: every expression of every instance's
#: model, every binding and the problem's own expressions, each use of a YAML alias counted.
MAX_EXPRESSION_NODES = 100_000


def _parse_noise_section(doc: YMap, where: Where, columns: dict[str, ColumnSpec],
                         instances: dict[str, InstanceSpec]) -> dict[str, NoiseSpec]:
    """The problem's ``noise:`` section: a column or an instance input (``s1.p``) → its
    noise, each name checked and each unit against its reading's."""
    mapping, at = section(doc, where, "noise")
    inputs = {f"{i}.{k}": inp.unit for i, inst in instances.items()
              for k, inp in inst.model.inputs.items()}
    out: dict[str, NoiseSpec] = {}
    for key, value in mapping.items():
        here = child_where(mapping, at, key)
        name = str(key)
        if name in columns:
            out[name] = parse_noise(value, here, columns[name].unit)
        elif name in inputs:
            out[name] = parse_noise(value, here, inputs[name])
        else:
            known = [*columns, *inputs]
            raise SpecError(here, f"'{excerpt(name)}' is neither a column nor an instance "
                                  f"input{did_you_mean(name, known)}; 'noise:' names the "
                                  "readings whose noise it declares (a column such as "
                                  "'x_ref', or an input such as 's1.p')")
    return out


def _check_size(name: str, where: Where, instances: dict[str, InstanceSpec],
                groups: list[list[ExprSpec]]) -> None:
    """Refuse a problem whose expressions, expanded, are too large to build in bounded time."""
    nodes = [n for inst in instances.values() for n in expression_nodes(inst.model)]
    nodes += [b.node for inst in instances.values() for b in inst.bindings.values()]
    nodes += [spec.node for group in groups for spec in group]
    total = expr.total_size(nodes)
    if total > MAX_EXPRESSION_NODES:
        raise SpecError(where, f"the expressions of problem '{name}' expand to {total} nodes, "
                               f"more than the limit of {MAX_EXPRESSION_NODES} (a model counts "
                               "once per instance, an alias once per use)")


def load_problem_spec(path: str | Path) -> ProblemSpec:
    """Load and validate a problem file and the model files it names.

    Parameters
    ----------
    path
        The problem's YAML file; relative paths inside it are relative to it.

    Returns
    -------
    ProblemSpec

    Raises
    ------
    SpecError
        Naming file, line and key path for any problem in the files.
    """
    path = Path(path).resolve() if Path(path).exists() else Path(path)
    doc, where = load_with_extends(path, "problem", merge_problem)
    check_keys(doc, where, required=["problem", "constraints", "datasets"],
               optional=["instances", *PROBLEM_KEYS])
    name = expect_name(doc["problem"], child_where(doc, where, "problem"), "the problem's name")
    cache = _ModelCache()

    def entries(key: str, parse: Any) -> dict[str, Any]:
        mapping, at = section(doc, where, key)
        return {k: parse(k, v, child_where(mapping, at, k)) for k, v in mapping.items()}

    constants = entries("constants", parse_constant)
    parameters = entries("parameters", parse_parameter)
    columns = _parse_columns(doc, where)
    instances = entries("instances", lambda k, v, at: _parse_instance(k, v, at, path, cache))
    noise = _parse_noise_section(doc, where, columns, instances)
    expressions = entries("expressions", lambda k, v, at: _parse_quantity(k, v, at, False))
    constraints = entries("constraints", lambda k, v, at: _parse_quantity(k, v, at, True))
    datasets = entries("datasets", lambda k, v, at: _parse_dataset(k, v, at, path))
    comparisons = entries("comparisons", _parse_comparison)
    for key, at in (("constraints", constraints), ("datasets", datasets)):
        if not at:
            raise SpecError(child_where(doc, where, key), f"'{key}' must not be empty")
    datasets = _resolve_roles(datasets)
    fit = [d for d in datasets.values() if d.role == FIT]
    if not fit:
        raise SpecError(child_where(doc, where, "datasets"),
                        f"a problem needs a dataset to fit (the data it is solved on): one "
                        f"named '{DEFAULT_FIT}', or one with 'role: {FIT}'")
    if len(fit) > 1:
        raise SpecError(fit[1].where, f"datasets '{fit[0].name}' and '{fit[1].name}' both "
                                      f"have role '{FIT}'; a problem is fitted on one dataset "
                                      f"(give the others 'role: {CHECK}')")
    for comp in comparisons.values():
        for ds in comp.datasets or ():
            if ds not in datasets:
                raise SpecError(comp.where.child("datasets"),
                                f"unknown dataset '{ds}'{did_you_mean(ds, datasets)}")
    check_unique({
        sect: [(k, v.where) for k, v in group.items()]
        for sect, group in (("columns", columns), ("constants", constants),
                            ("parameters", parameters), ("instances", instances),
                            ("expressions", expressions), ("constraints", constraints))
    })
    _check_size(name, where, instances, [
        [q.expr for q in expressions.values()], [q.expr for q in constraints.values()],
        [c.estimate for c in comparisons.values()], [c.reference for c in comparisons.values()],
    ])
    stages = _parse_stages(doc, where, constraints)
    weighting = "auto"
    if "weighting" in doc:
        weighting = expect_choice(doc["weighting"], child_where(doc, where, "weighting"),
                                  WEIGHTINGS, "weighting")
    robust = next((q for q in constraints.values() if q.loss is not None), None)
    if weighting in ("estimated", "propagated") and robust is not None and robust.loss \
            is not None:
        raise SpecError(robust.loss.where, f"constraint '{robust.name}' declares a robust "
                                           f"loss, which 'weighting: {weighting}' does not "
                                           "support: remove one of them")
    implicit = entries("implicit", parse_implicit)
    for key, item in implicit.items():
        if key not in expressions:
            raise SpecError(item.where, f"'{key}' is not an expression of the problem"
                                        f"{did_you_mean(key, expressions)}; only problem "
                                        "expressions can be declared implicit here")
    options = (parse_solver(doc["solver"], child_where(doc, where, "solver"))
               if "solver" in doc else SolveOptions())
    _check_candidates(instances, columns, expressions)
    candidates = (parse_problem_candidates(doc["candidates"],
                                           child_where(doc, where, "candidates"))
                  if "candidates" in doc else None)
    system = SystemSpec(constants, parameters, columns, instances, expressions, constraints,
                        comparisons, implicit, noise, candidates)
    return ProblemSpec(name, _doc(doc, where), path, system,
                       StudySpec(datasets, stages, weighting), options, where,
                       extends_chain(path, "problem"))
