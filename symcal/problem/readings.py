"""Where each declared noise applies: to a data column, or to an instance input bound to an
expression.

An input bound to a bare column (``p: p1``) reads that column: its declared noise is the
column's, so every use of the column (in other expressions too) carries the same noise.
So does an input bound to a column corrected for its latency or its zero, the column plus
terms in its rate, parameters and constants (``psi_x: psi_x + tau*psi_x_rate``,
``psi_x_rate`` declared ``rate_of: psi_x``; ``Vth: Vth + zero_Vth``): the rate's own noise
is not propagated.
An input bound to an expression (``q: py_raw - l_o*theta_raw``) carries its own noise,
independent of its columns'.  Most specific first, a reading's noise is declared by

1. the problem's ``noise:`` section (naming the column, or an input bound to it);
2. the column's own ``noise`` (in ``columns:`` or the column preset);
3. the instance's ``noise: {input: ...}``;
4. the model input's ``noise``.

A column of ``role: time`` declared nowhere is exact (a clock's error is negligible
beside the sensors'): a drift term in time does not leave its readings undeclared.

Two different values at the same level for one column (two instances of different models
bound to it, say) are refused, naming both.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from symcal.base.errors import SpecError, Where
from symcal.language import expr
from symcal.language.noise import NoiseSpec, check_noise_unit
from symcal.language.problem_file import SystemSpec


@dataclass(frozen=True)
class Declared:
    """A noise and where it applies: ``unit`` is the reading's unit (a plain number is in
    the unit of the place that declares it, ``declared_in``); ``origin`` says in words
    who declared it."""

    spec: NoiseSpec
    unit: str
    declared_in: str
    origin: str

    @property
    def sigma(self) -> float:
        """The standard deviation in internal units."""
        return self.spec.sigma(self.declared_in)

    @property
    def where(self) -> Where:
        """Where the noise is written."""
        return self.spec.where


@dataclass(frozen=True)
class NoisePlan:
    """The declared noise of a problem's readings: by column, and by instance input
    (``s1.q``) for inputs bound to an expression."""

    columns: Mapping[str, Declared]
    inputs: Mapping[str, Declared]


def bare_column(system: SystemSpec, binding: expr.Node) -> str | None:
    """The column an input binding reads: a column named alone, or a column plus terms in
    its rate and in parameters or constants (a latency or a zero correction); None for any
    other expression."""
    if isinstance(binding, expr.Name) and binding.name in system.columns:
        return binding.name
    terms = _summands(binding)
    bare = [t.name for t in terms if isinstance(t, expr.Name) and t.name in system.columns]
    if len(terms) < 2 or not bare:
        return None
    column = bare[0]
    rates = {k for k, c in system.columns.items() if c.rate_of == column}
    exact = rates | set(system.parameters) | set(system.constants)
    rest = [t for t in terms if not (isinstance(t, expr.Name) and t.name == column)]
    names = {n.name for t in rest for n in expr.names(t)}
    if len(rest) == len(terms) - 1 and names <= exact:
        return column
    return None


def _summands(node: expr.Node) -> list[expr.Node]:
    """The terms of a sum written with ``+`` (the node itself for anything else)."""
    if isinstance(node, expr.Binary) and node.op == "+":
        return _summands(node.left) + _summands(node.right)
    return [node]


def plan_noise(system: SystemSpec) -> NoisePlan:
    """Where each declared noise of ``system`` applies (the module's rules).

    Raises
    ------
    SpecError
        Two different noises for one column at the same level, or a noise whose unit
        measures something else than its column.
    """
    levels: list[dict[str, list[Declared]]] = [{}, {}, {}, {}]
    inputs: dict[str, Declared] = {}
    for name, col in system.columns.items():
        if name in system.noise:
            spec = system.noise[name]
            levels[0].setdefault(name, []).append(
                Declared(spec, col.unit, col.unit, f"the problem's noise: '{name}'"))
        if col.noise is not None:
            levels[1].setdefault(name, []).append(
                Declared(col.noise, col.unit, col.unit, f"column '{name}'"))
    for iname, inst in system.instances.items():
        for key, inp in inst.model.inputs.items():
            full = f"{iname}.{key}"
            found: list[tuple[int, NoiseSpec, str]] = []
            if full in system.noise:
                found.append((0, system.noise[full], f"the problem's noise: '{full}'"))
            if key in inst.noise:
                found.append((2, inst.noise[key], f"instance '{iname}' noise '{key}'"))
            if inp.noise is not None:
                found.append((3, inp.noise, f"model '{inst.model.name}' input '{key}'"))
            if not found:
                continue
            column = bare_column(system, inst.bindings[key].node)
            if column is None:      # the most specific declaration, on the input itself
                _, spec, origin = min(found, key=lambda f: f[0])
                inputs[full] = Declared(spec, inp.unit, inp.unit, origin)
                continue
            unit = system.columns[column].unit
            for rank, spec, origin in found:
                levels[rank].setdefault(column, []).append(
                    Declared(spec, unit, inp.unit or unit, origin))
    columns: dict[str, Declared] = {}
    for level in levels:
        for column, declared in level.items():
            if column in columns:
                continue
            first = declared[0]
            for other in declared[1:]:
                if abs(other.sigma - first.sigma) > 1e-12 * max(first.sigma, other.sigma):
                    raise SpecError(other.where, f"column '{column}' has two noises: "
                                                 f"'{other.spec.text}' ({other.origin}) and "
                                                 f"'{first.spec.text}' ({first.origin}, "
                                                 f"{first.where}); declare its noise once, "
                                                 f"e.g. 'noise: {{{column}: ...}}' in the "
                                                 "problem")
            check_noise_unit(first.spec, first.unit, f"column '{column}'")
            columns[column] = first
    for name, col in system.columns.items():     # a clock is exact unless declared noisy
        if col.role == "time" and name not in columns:
            columns[name] = Declared(NoiseSpec(0.0, "", "0", col.where), col.unit, col.unit,
                                     f"column '{name}' (role: time: exact unless its noise "
                                     "is declared)")
    return NoisePlan(columns, inputs)
