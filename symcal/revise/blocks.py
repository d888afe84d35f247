"""Every residual of a result on one dataset, with what a diagnosis needs to test effects:
its sensitivities (to each sensor output through the hooks, to the free and the fixed
parameters, to the data columns), the variables an effect may depend on, those variables
at the adjusted readings (:mod:`symcal.analysis.adjustment`), and the residuals'
propagated covariance per observation.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import casadi as ca
import numpy as np

from symcal.analysis.adjustment import Adjustment, adjust, adjusted_values
from symcal.analysis.residuals import Variable
from symcal.base.numeric import mapped
from symcal.base.units import ANGLE_UNITS, DISPLAY_UNITS
from symcal.data.dataset import Dataset
from symcal.problem.symbolic import Problem


@dataclass
class Block:
    """One dataset's residuals (``before`` at the start, ``after`` at the estimate, N ×
    n_q, internal units) and their derivatives: by the hooks (``hooks``, N × n_q × n_h),
    the free parameters (``jac``), the fixed ones (``jac_fixed``) and the data columns
    the problem reads (``jac_columns``, N × n_q × n_u, by each column in internal units).
    ``variables`` hold the raw values (what the report shows), ``regressors`` the same
    variables at the adjusted readings where the noise is declared (what candidate terms
    are evaluated on); ``cov`` is the residuals' propagated covariance per observation
    (None where a residual's readings do not all declare their noise)."""

    dataset: Dataset
    names: list[str]
    kinds: list[str]
    units: list[str]
    offsets: list[bool]
    before: np.ndarray
    after: np.ndarray
    hooks: np.ndarray
    jac: np.ndarray
    jac_fixed: np.ndarray
    jac_columns: np.ndarray
    variables: list[Variable]
    jac_constants: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 0)))
    regressors: dict[str, np.ndarray] = field(default_factory=dict)
    cov: np.ndarray | None = None

    def values(self, name: str) -> np.ndarray:
        """A variable's values as candidate terms see them (adjusted where possible)."""
        if name in self.regressors:
            return self.regressors[name]
        return next(v.values for v in self.variables if v.name == name)

    def subset(self, cols: list[int]) -> Block:
        """The block restricted to the residuals ``cols`` (e.g. the fit's constraints)."""
        return replace(self, names=[self.names[k] for k in cols],
                       kinds=[self.kinds[k] for k in cols], units=[self.units[k] for k in cols],
                       offsets=[self.offsets[k] for k in cols], before=self.before[:, cols],
                       after=self.after[:, cols], hooks=self.hooks[:, cols, :],
                       jac=self.jac[:, cols, :], jac_fixed=self.jac_fixed[:, cols, :],
                       jac_columns=self.jac_columns[:, cols, :],
                       jac_constants=self.jac_constants[:, cols, :],
                       cov=None if self.cov is None else self.cov[:, cols][:, :, cols])


def _residuals(problem: Problem, hp: Problem, ds: Dataset
               ) -> tuple[list[str], list[str], list[str], list[bool], list[ca.SX],
                          list[ca.SX], list[bool]]:
    """The residuals examined on ``ds``: names, kinds, units, whether their zero is
    arbitrary, their SX in the diagnostic and in the noisy view, whether their readings
    declare their noise."""
    names, kinds, units, offsets, exprs, noisy, declared = [], [], [], [], [], [], []
    nv = problem.noisy
    twins = {c.name: c for c in nv.comparisons}
    for c, n in zip(hp.constraints, nv.constraints, strict=True):
        names.append(c.name)
        kinds.append("constraint")
        units.append(c.unit)
        offsets.append(False)
        exprs.append(c.sx)
        noisy.append(n.sx)
        declared.append(not problem.undeclared(problem.constraint(c.name).sx))
    for comp in hp.comparisons:
        if comp.datasets is not None and ds.name not in comp.datasets:
            continue
        if any(col not in ds.columns for col in hp.columns_of(comp.reference)):
            continue
        names.append(comp.name)
        kinds.append("comparison")
        units.append(comp.unit)
        offsets.append(comp.remove_mean)
        exprs.append(comp.estimate - comp.reference)
        twin = twins[comp.name]
        noisy.append(twin.estimate - twin.reference)
        declared.append(not problem.undeclared(comp.estimate - comp.reference))
    return names, kinds, units, offsets, exprs, noisy, declared


def evaluate(problem: Problem, ds: Dataset, theta0: np.ndarray, theta: np.ndarray,
             free: np.ndarray) -> Block:
    """Every residual of ``problem`` on ``ds`` with its derivatives and variables."""
    hp = problem.diagnostic
    names, kinds, units, offsets, exprs, noisy, declared = _residuals(problem, hp, ds)
    hooks = ca.vertcat(*hp.hooks.values())
    deltas = ca.vertcat(*(c.symbol for c in hp.constants)) if hp.constants else ca.SX(0, 1)
    u_ext = ca.vertcat(hp.u, hooks, deltas)
    e = ca.vertcat(*exprs)
    theta_free = hp.theta[np.flatnonzero(free).tolist()]
    theta_fixed = hp.theta[np.flatnonzero(~free).tolist()]
    var_specs = variable_specs(hp)
    outs = [e, ca.jacobian(e, hooks).T, ca.jacobian(e, theta_free).T,
            ca.jacobian(e, theta_fixed).T,
            # by each column in internal units: ∂e/∂u divided by the column's size
            (ca.jacobian(e, hp.u) @ ca.diag(1.0 / _sizes(hp))).T if hp.columns
            else ca.SX(0, e.shape[0]),
            ca.vertcat(*(sx for _, sx, _, _, _ in var_specs)),
            ca.jacobian(e, deltas).T]
    fn = mapped(hp.theta, u_ext, outs, "diag")
    # the hooks and the constants' offsets δ are at zero: the problem as it is
    u = np.vstack([ds.matrix(hp.columns), np.zeros((hooks.shape[0] + deltas.shape[0], ds.n))])
    after, dh, dj, dfix, dcol, values, dcon = fn(theta, u)
    before = fn(theta0, u)[0]
    adjustment = adjust(problem, noisy, offsets, ds, theta, all(declared))
    if adjustment is not None:
        # the derivatives where the adjustment linearises: at the adjusted readings (a
        # candidate's regressor is evaluated there too; at the raw readings the
        # parameters' columns would carry the noise the adjusted regressors lack)
        _, dh, dj, dfix, dcol, _, dcon = fn(theta, _adjusted_columns(hp, u, adjustment))
    n, nq = after.shape
    variables = [Variable(name, values[:, k], unit, period, kind, role(hp, name))
                 for k, (name, _, unit, period, kind) in enumerate(var_specs)]
    variables += unused_columns(hp, ds)
    block = Block(ds, names, kinds, units, offsets, before, after,
                  dh.reshape(n, nq, hooks.shape[0]),     # vec() of (n_h × n_q) is
                  dj.reshape(n, nq, int(free.sum())),    # column-major
                  dfix.reshape(n, nq, int((~free).sum())),
                  dcol.reshape(n, nq, len(hp.columns)), variables,
                  dcon.reshape(n, nq, deltas.shape[0]))
    if adjustment is not None:
        _adjusted(problem, block, var_specs, adjustment, theta)
    return block


def _adjusted_columns(hp: Problem, u: np.ndarray, adjustment: Adjustment) -> np.ndarray:
    """The diagnostic view's inputs (columns in their declared units, then the hooks) with
    every column reading moved to its adjusted value; readings of inputs bound to
    expressions cannot be moved here (their corrections reach the regressors only)."""
    out = u.copy()
    index = {c: k for k, c in enumerate(hp.columns)}
    for j, name in enumerate(adjustment.readings):
        if name in index:
            out[index[name]] += adjustment.corrections[:, j] / DISPLAY_UNITS[_unit(hp, name)]
    return out


def _sizes(hp: Problem) -> ca.DM:
    return ca.DM([DISPLAY_UNITS[_unit(hp, c)] for c in hp.columns])


def _unit(hp: Problem, col: str) -> str:
    spec = hp.column_specs.get(col)
    return spec.unit if spec is not None else ""


def _adjusted(problem: Problem, block: Block, var_specs: list, adjustment: Adjustment,
              theta: np.ndarray) -> None:
    """Fill the block's regressors (its variables at the adjusted readings) and, where
    every residual declares its noise, its propagated covariance."""
    nv = problem.noisy
    signals = {q.name: q.sx for q in nv.signals}
    expressions = {q.name: q.sx for q in nv.expressions}
    columns = {c: k for k, c in enumerate(nv.columns)}
    noise = {r.name: r.symbol for r in nv.readings if r.name in adjustment.readings}
    hp_outputs = set(problem.diagnostic.hooks)
    named: list[tuple[str, ca.SX]] = []
    for name, _, _, _, kind in var_specs:
        if kind == "derived" and name not in hp_outputs:
            continue        # a sensor's own output is one (its gain's candidates use it)
        if name in columns:
            sx = nv.u[columns[name]] * DISPLAY_UNITS[_unit(nv, name)]
            named.append((name, sx + noise[name] if name in noise else sx))
        elif name in signals:
            named.append((name, signals[name]))
        elif name in expressions:
            named.append((name, expressions[name]))
    block.regressors = adjusted_values(problem, named, block.dataset, theta, adjustment)
    if adjustment.complete:
        block.cov = adjustment.cov


def variable_specs(hp: Problem) -> list[tuple[str, ca.SX, str, float | None, str]]:
    """(name, SX, unit, period, kind) of every variable: columns (but the references),
    sensor inputs and outputs, and named expressions.

    Variables computed from sensor outputs have kind ``"derived"``: the residuals are
    examined along them, but no candidate term uses them (a sensor input would then
    depend on sensor outputs, a cycle in the model).
    """
    refs = references(hp)
    hooks = ca.vertcat(*hp.hooks.values())
    out: list[tuple[str, ca.SX, str, float | None, str]] = []
    for k, col in enumerate(hp.columns):
        if col not in refs:
            spec = hp.column_specs.get(col)
            unit = spec.unit if spec is not None else ""
            factor = DISPLAY_UNITS[unit]    # a column in its declared unit → internal units
            out.append((col, hp.u[k] * factor if factor != 1.0 else hp.u[k], unit, None,
                        column_kind(hp, col)))
    for sig in hp.signals:
        derived = ca.depends_on(sig.sx, hooks)
        period = sig.period
        inst, _, name = sig.name.partition(".")
        if inst in hp.instances:
            model = hp.instances[inst].model
            point = model.evaluation_point(name)
            if point is not None and point in model.implicit:
                period = None   # harmonics where the model evaluates its error, not here
            if name in {model.evaluation_point(i) for i in model.inputs}:
                derived = False  # its own evaluation point: a term there stays inside

        out.append((sig.name, sig.sx, sig.unit, period, "derived" if derived else "signal"))
    for q in hp.expressions:
        kind = "angle" if q.unit in ANGLE_UNITS else "expression"
        out.append((q.name, q.sx, q.unit, None,
                    "derived" if ca.depends_on(q.sx, hooks) else kind))
    return out


def references(hp: Problem) -> set[str]:
    """Columns of reference sensors: never a variable a model may use."""
    return {col for comp in hp.comparisons for col in hp.columns_of(comp.reference)}


def unused_columns(hp: Problem, ds: Dataset) -> list[Variable]:
    """Data columns the problem does not use yet (but the references): the residuals are
    examined along them (e.g. a drift in time)."""
    refs = references(hp)
    out = []
    for col, spec in hp.column_specs.items():
        if col in ds.columns and col not in hp.columns and col not in refs:
            factor = DISPLAY_UNITS[spec.unit]   # declared unit → internal units
            values = np.asarray(ds.columns[col])
            out.append(Variable(col, values * factor if factor != 1.0 else values, spec.unit,
                                None, column_kind(hp, col), spec.role))
    return out


def role(hp: Problem, name: str) -> str:
    """A column's declared role ("" for anything else)."""
    spec = hp.column_specs.get(name)
    return spec.role if spec is not None else ""


def column_kind(hp: Problem, col: str) -> str:
    """``drift`` for the column declared as time (``role: time``), else ``column``."""
    spec = hp.column_specs.get(col)
    return "drift" if spec is not None and spec.role == "time" else "column"


def distinct(variables: list[Variable]) -> list[Variable]:
    """Drop variables equal to another (e.g. an input bound to a column), keeping the one
    that declares a period, else the first."""
    return [v for v, _ in distinct_groups(variables)]


def distinct_groups(variables: list[Variable]) -> list[tuple[Variable, set[str]]]:
    """The distinct variables (constant or non-finite ones dropped), each with the names
    of every variable equal to it (an input and the column it is bound to), keeping the
    one that declares a period, else the first."""
    kept: list[tuple[Variable, set[str]]] = []
    for var in variables:
        if np.ptp(var.values) <= 0 or not np.all(np.isfinite(var.values)):
            continue
        tol = 1e-12 * (1 + float(np.abs(var.values).max()))
        same = next((i for i, (k, _) in enumerate(kept)
                     if np.allclose(var.values, k.values, rtol=0, atol=tol)), None)
        if same is None:
            kept.append((var, {var.name}))
            continue
        names = kept[same][1] | {var.name}
        kept[same] = (var if var.period and not kept[same][0].period else kept[same][0],
                      names)
    return kept
