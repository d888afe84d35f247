"""The symbolic problem: parameters θ, per-observation inputs u, named residuals, and the
views of one build (:attr:`Problem.explicit`, :attr:`Problem.diagnostic`,
:attr:`Problem.noisy`).

A :class:`Problem` is plain, frozen data: it holds its views as values, made by the
compiler (:mod:`symcal.problem.build`) by substitution from one build, and keeps no
pointer to the compiler.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import casadi as ca

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import Where
from symcal.base.options import SolveOptions
from symcal.language.loss import LossSpec
from symcal.language.model_file import ModelSpec
from symcal.language.problem_file import NOT_EFFECTS, ColumnSpec, DatasetSpec, ProblemSpec


@dataclass(frozen=True)
class Parameter:
    """One scalar parameter of the problem, named ``instance.name`` or ``name``."""

    name: str
    value: float
    unit: str
    lower: float
    upper: float
    fixed: bool
    scale: float
    doc: str
    where: Where


@dataclass(frozen=True, eq=False)
class Quantity:
    """A named symbolic quantity of one observation (constraint, expression or signal)."""

    name: str
    sx: ca.SX
    unit: str = ""
    sigma: float = 1.0
    doc: str = ""
    period: float | None = None
    loss: LossSpec | None = None


@dataclass(frozen=True, eq=False)
class Comparison:
    """An estimate of a quantity and its independent reference."""

    name: str
    estimate: ca.SX
    reference: ca.SX
    unit: str
    datasets: tuple[str, ...] | None
    remove_mean: bool
    doc: str


@dataclass(frozen=True, eq=False)
class ImplicitOutput:
    """A definition solved by fixed-point steps ``x = F(x)``, with what checks it.

    ``derivative`` is ∂F/∂x at the final iterate (the map contracts where |·| < 1);
    ``last_step`` is the change made by the last step (how far from converged).
    """

    name: str
    steps: int
    derivative: ca.SX
    last_step: ca.SX


@dataclass(frozen=True, eq=False)
class Reading:
    """A reading with a declared noise: a data column (``kind`` ``"column"``) or an
    instance input bound to an expression (``"input"``, named ``s1.q``).

    ``sigma`` is its standard deviation in internal units, ``unit`` the reading's unit,
    ``text`` the noise as declared (``0.5 um``), ``origin`` who declared it, in words.
    ``symbol`` is added to the reading in :attr:`Problem.noisy` (zero elsewhere).  The
    noise of an input bound to an expression adds to that of the columns it reads.
    """

    name: str
    kind: str
    sigma: float
    unit: str
    text: str
    origin: str
    symbol: ca.SX


@dataclass(frozen=True)
class Stage:
    """One step of a calibration: constraints used and parameters freed (by name)."""

    name: str
    constraints: tuple[str, ...]
    free: tuple[str, ...]
    method: str = "auto"
    doc: str = ""


@dataclass(frozen=True)
class CandidateSpace:
    """The search space of candidate effects declared for one instance (``candidates:``
    in its model file, or in its instance entry, which replaces the model's).

    ``variables`` are the problem's names (``s1.p``, columns as named, problem
    expressions, ``s3.p``), ``kinds`` a subset of
    :data:`~symcal.language.candidates.KINDS` (``()``: never add a term to this sensor),
    ``harmonics`` the harmonic orders; each None where the file does not say (the
    search's default applies).  ``where`` is where it is declared, ``declared_in``
    ``"model"`` or ``"instance"``.
    """

    variables: tuple[str, ...] | None
    kinds: tuple[str, ...] | None
    harmonics: tuple[int, ...] | None
    where: Where
    declared_in: str

    @property
    def none(self) -> bool:
        """Whether no term may be added to this sensor."""
        return self.kinds == ()

    @property
    def origin(self) -> str:
        """Where it is declared, for a report: ``"the space declared at
        models/x.yaml:12"``."""
        place = self.where.file if self.where.line is None else \
            f"{self.where.file}:{self.where.line}"
        return f"the space declared at {place}"


@dataclass(frozen=True)
class Instance:
    """A sensor instance of the problem: its model, its input bindings (as written), the
    model constants it binds to problem expressions (as written) and its declared search
    space of candidate effects (None: not declared, the search's default applies)."""

    name: str
    model: ModelSpec
    bindings: Mapping[str, str]
    doc: str
    constants: Mapping[str, str] = field(default_factory=dict)
    candidates: CandidateSpace | None = None


@dataclass(frozen=True, eq=False)
class ConstantInfo:
    """A constant of the problem (``l_s``) or of an instance's model (``s1.rho``), as a
    candidate: "this value is off".

    ``value`` and ``unit`` are as declared; ``symbol`` is added to its value (internal
    units) in :attr:`Problem.diagnostic` and is zero in every other view, so that the
    derivative of a residual by it is the residual's sensitivity to the constant.
    ``tested`` says whether the problem's ``candidates: {constants: ...}`` lets the
    search test it.  A model constant an instance binds to a problem expression
    (``constants: {rho: rho}``) is not a constant of that instance.
    """

    key: str
    name: str
    instance: str | None
    model_file: Path | None
    value: float
    unit: str
    doc: str
    where: Where
    symbol: ca.SX
    tested: bool = True


@dataclass(frozen=True)
class ProblemCandidates:
    """What the problem's ``candidates:`` section lets the search test: the keys of the
    constants (``Problem.constants``) and the names of the fixed parameters; every one of
    each when the section does not restrict it (``where`` None: not written)."""

    constants: tuple[str, ...] = ()
    fixed: tuple[str, ...] = ()
    where: Where | None = None


@dataclass(frozen=True)
class Study:
    """On what data and in which steps a problem is solved.

    ``weighting``: ``"equal"`` (the cost is Σ (g/σ)² as written), ``"estimated"`` (each
    stage with several constraints is solved again, weighted by the inverse of their
    covariance estimated from the residuals: feasible generalised least squares) or
    ``"propagated"`` (each observation's constraints weighted by the inverse of their
    covariance propagated from the readings' declared noise, at the estimate: the
    adjustment with condition equations).  A problem file that does not write one gets
    ``propagated`` where every reading of its constraints declares its noise and no
    constraint has a robust loss, else ``equal`` (``weighting_declared`` is False).
    """

    datasets: Mapping[str, DatasetSpec]
    stages: tuple[Stage, ...]
    weighting: str
    weighting_declared: bool = True


@dataclass(frozen=True, eq=False)
class Problem:
    """A calibration problem in symbolic form: the system, the study, the solve options.

    Attributes
    ----------
    parameters
        Every scalar parameter, in the order of ``theta``.
    theta
        SX column of parameter symbols.
    columns
        Names of the data columns the problem reads, in the order of ``u``.
    u
        SX column of per-observation input symbols.
    constraints
        Named residuals g(θ, u) that must vanish for consistent measurements.
    expressions
        The problem's named expressions.
    signals
        Every instance input and output (``s1.p``, ``s1.p_hat``).
    comparisons
        Estimates to compare with a reference sensor.
    study
        Datasets, stages and weighting (:class:`Study`).
    options
        The solve options the problem file declares (``solver:``).
    instances
        The sensor instances by name.
    column_specs
        Every column the problem declares (used or not), with unit, role and doc.
    implicit
        Definitions solved by fixed-point steps, with their convergence checks.
    hooks
        Instance output → its hook symbol (see :attr:`diagnostic`).
    constants
        Every constant of the problem and of each instance's model
        (:class:`ConstantInfo`); its symbol is open in :attr:`diagnostic`.
    candidates
        Which constants and fixed parameters the search may test
        (:class:`ProblemCandidates`).
    readings
        Every reading with a declared noise (:class:`Reading`); its symbol is open in
        :attr:`noisy`.
    spec
        The validated spec the problem was built from (for derived problems).
    views
        The other views of the same build (:class:`Views`); None on a view itself.
    """

    name: str
    doc: str
    path: Path
    parameters: tuple[Parameter, ...]
    theta: ca.SX
    columns: tuple[str, ...]
    u: ca.SX
    constraints: tuple[Quantity, ...]
    expressions: tuple[Quantity, ...]
    signals: tuple[Quantity, ...]
    comparisons: tuple[Comparison, ...]
    study: Study
    options: SolveOptions
    instances: Mapping[str, Instance]
    column_specs: Mapping[str, ColumnSpec]
    implicit: tuple[ImplicitOutput, ...]
    hooks: Mapping[str, ca.SX]
    spec: ProblemSpec = field(repr=False)
    views: Views | None = field(default=None, repr=False)
    readings: tuple[Reading, ...] = ()
    constants: tuple[ConstantInfo, ...] = ()
    candidates: ProblemCandidates = field(default_factory=ProblemCandidates)

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Names of all parameters, in the order of ``theta``."""
        return tuple(p.name for p in self.parameters)

    @cached_property
    def index(self) -> dict[str, int]:
        """Position of each parameter in θ, by name."""
        return {p.name: i for i, p in enumerate(self.parameters)}

    @property
    def free(self) -> tuple[bool, ...]:
        """Which parameters are free (not fixed)."""
        return tuple(not p.fixed for p in self.parameters)

    @property
    def datasets(self) -> Mapping[str, DatasetSpec]:
        """Where each named dataset comes from (``study.datasets``)."""
        return self.study.datasets

    @property
    def fit_dataset(self) -> str:
        """The name of the dataset the problem is fitted on (``role: fit``); every other
        dataset is held out to check the fit."""
        return next(d.name for d in self.study.datasets.values() if d.role == "fit")

    @property
    def stages(self) -> tuple[Stage, ...]:
        """The ordered steps of the calibration (``study.stages``)."""
        return self.study.stages

    @property
    def weighting(self) -> str:
        """``"equal"``, ``"estimated"`` or ``"propagated"`` (``study.weighting``)."""
        return self.study.weighting

    def column_role(self, name: str) -> str:
        """The declared role of column ``name`` (``"time"``, ``"axis"``, ``"label"``,
        ``"index"``, ``"reference"``, ``"state"``), or ``""`` (none declared, or not a
        column)."""
        spec = self.column_specs.get(name)
        return spec.role if spec is not None else ""

    @cached_property
    def never_effects(self) -> frozenset[str]:
        """The columns that are never an effect on a sensor: those declared ``label``,
        ``index`` or ``reference``, and every column a comparison uses as its
        reference."""
        out = {k for k, c in self.column_specs.items() if c.role in NOT_EFFECTS}
        for comp in self.comparisons:
            out.update(self.columns_of(comp.reference))
        return frozenset(out)

    def constraint(self, name: str) -> Quantity:
        """The constraint called ``name``."""
        return next(c for c in self.constraints if c.name == name)

    def columns_of(self, sx: ca.SX) -> list[str]:
        """Data columns an expression depends on, in ``u`` order."""
        used = {v.name() for v in ca.symvar(sx)}
        return [c for c in self.columns if c in used]

    def quantity(self, name: str) -> ca.SX:
        """The SX of a named constraint, expression, signal or comparison (estimate minus
        reference), looked up in that order: a comparison named like an expression is
        reached through the expression it compares.

        Raises
        ------
        KeyError
            With the names there are, for an unknown name.
        """
        for group in (self.constraints, self.expressions, self.signals):
            for q in group:
                if q.name == name:
                    return q.sx
        for comp in self.comparisons:
            if comp.name == name:
                return comp.estimate - comp.reference
        known = [q.name for g in (self.constraints, self.expressions, self.signals) for q in g]
        known += [c.name for c in self.comparisons]
        raise KeyError(f"problem '{self.name}' has no quantity '{name}'"
                       f"{did_you_mean(name, known)}")

    def source_files(self) -> tuple[Path, ...]:
        """Every file the problem was built from: the problem file, the files it extends,
        and its model files (through their ``extends`` too)."""
        own = self.spec.sources or (Path(self.path),)
        return (*own, *(f for f in self.model_files() if f not in own))

    def model_files(self) -> tuple[Path, ...]:
        """Every model file the problem's instances read, through ``extends`` too."""
        files: list[Path] = []
        for inst in self.instances.values():
            model: ModelSpec | None = inst.model
            while model is not None:
                if model.path not in files:
                    files.append(model.path)
                model = model.extends
        return tuple(files)

    @property
    def explicit(self) -> Problem | None:
        """With implicit definitions: the same problem with every one at its start (zero
        fixed-point steps: the explicit model), to start the solver from a closed form."""
        return self.views.explicit if self.views is not None else None

    @property
    def diagnostic(self) -> Problem:
        """The problem with the hooks left open: evaluate with the hooks as extra rows of
        u set to zero; the derivative of a residual by a hook is its derivative by that
        sensor output."""
        return self.views.diagnostic if self.views is not None else self

    @property
    def noisy(self) -> Problem:
        """The problem with every declared reading's noise symbol left open (hooks at
        zero): the derivative of a residual by a reading's symbol is its derivative by that
        reading's error, and the values are those with the symbols at zero (evaluated as
        extra rows of u set to zero, or substituted by zero in the expressions, as
        :class:`~symcal.analysis.row_noise.RowPropagation` does)."""
        return self.views.noisy if self.views is not None and self.views.noisy is not None \
            else self

    def noise_columns(self) -> dict[str, Reading]:
        """The declared readings that are data columns, by column."""
        return {r.name: r for r in self.readings if r.kind == "column"}

    def undeclared(self, sx: ca.SX) -> list[str]:
        """The columns ``sx`` reads whose noise no one declared, in ``u`` order."""
        declared = self.noise_columns()
        return [c for c in self.columns_of(sx) if c not in declared]

    def with_weighting(self, weighting: str) -> Problem:
        """The problem with another weighting of its constraints (no rebuild)."""
        if weighting == self.weighting:
            return self
        views = self.views
        if views is not None:
            views = Views(views.diagnostic.with_weighting(weighting),
                          views.explicit.with_weighting(weighting)
                          if views.explicit is not None else None,
                          views.noisy.with_weighting(weighting)
                          if views.noisy is not None else None)
        return replace(self, study=replace(self.study, weighting=weighting,
                                           weighting_declared=True), views=views)


@dataclass(frozen=True, eq=False)
class Views:
    """The other views of one build, derived by substitution.

    Attributes
    ----------
    diagnostic
        The hooks left open (:attr:`Problem.diagnostic`).
    explicit
        Every implicit definition at its start (:attr:`Problem.explicit`); None without
        implicit definitions.
    noisy
        The readings' noise symbols left open (:attr:`Problem.noisy`); None without a
        declared noise.
    """

    diagnostic: Problem
    explicit: Problem | None
    noisy: Problem | None = None
