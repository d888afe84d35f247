"""The search space of candidate effects, in the problem's names: each instance's
``candidates:`` (its own, else its model's) resolved to the names the problem uses
(``s1.p``, columns as named, problem expressions, ``s3.p``), checked (no column that is
never an effect, no name computed from the instance's own outputs), and the constants
and fixed parameters the problem's ``candidates:`` lets the search test.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import casadi as ca

from symcal.base.errors import SpecError, Where
from symcal.language.candidates import CandidatesSpec, select
from symcal.language.problem_file import NOT_EFFECTS, InstanceSpec, SystemSpec
from symcal.problem.symbolic import CandidateSpace, ProblemCandidates


def _own_names(inst: InstanceSpec) -> set[str]:
    model = inst.model
    return {n for n in (*model.inputs, *model.outputs, *model.expressions)
            if not n.startswith("base.")}


def declared_space(inst: InstanceSpec) -> tuple[CandidatesSpec, str] | None:
    """The instance's ``candidates:`` and where it is declared (``"instance"`` over
    ``"model"``), or None."""
    if inst.candidates is not None:
        return inst.candidates, "instance"
    if inst.model.candidates is not None:
        return inst.model.candidates, "model"
    return None


def resolved_variables(inst: InstanceSpec) -> list[tuple[str, Where, bool]]:
    """``(problem name, where, own)`` of each variable the instance's space names; own:
    a name of its own model (an input, output or expression), written ``inst.name``."""
    found = declared_space(inst)
    if found is None or found[0].variables is None:
        return []
    own = _own_names(inst)
    return [(f"{inst.name}.{n}" if n in own else n, at, n in own)
            for n, at in found[0].variables]


def expressions_needed(system: SystemSpec) -> dict[str, list[str]]:
    """Instance → the model expressions its own or another instance's space names that
    are not signals of the problem yet (inputs, outputs and evaluation points are): the
    compiler adds them as signals, so that the search can evaluate them."""
    out: dict[str, list[str]] = {}
    for inst in system.instances.values():
        for name, _, _ in resolved_variables(inst):
            owner, _, local = name.partition(".")
            other = system.instances.get(owner)
            if other is None or local not in other.model.expressions:
                continue
            model = other.model
            points = {model.evaluation_point(i) for i in model.inputs}
            if local not in points and local not in out.setdefault(owner, []):
                out[owner].append(local)
    return out


def instance_space(inst: InstanceSpec) -> CandidateSpace | None:
    """The instance's declared search space in the problem's names (None: not
    declared)."""
    found = declared_space(inst)
    if found is None:
        return None
    spec, declared_in = found
    variables = (None if spec.variables is None
                 else tuple(n for n, _, _ in resolved_variables(inst)))
    return CandidateSpace(variables, spec.kinds, spec.harmonics, spec.where, declared_in)


def check_spaces(system: SystemSpec, references: set[str],
                 sx_of: Callable[[str], ca.SX | None],
                 hooks: Mapping[str, ca.SX]) -> None:
    """Refuse a space that names a column that is never an effect (a label, index or
    reference column, or a comparison's reference) or, in an instance's entry, a name
    computed from that instance's own outputs (a term would feed back into itself).

    Parameters
    ----------
    system
        The problem's system.
    references
        The columns the comparisons use as their reference.
    sx_of
        A name's SX with the hooks open (None for a column).
    hooks
        Instance output (``s1.p_hat``) → its hook symbol.
    """
    for inst in system.instances.values():
        mine = [h for k, h in hooks.items() if k.split(".", 1)[0] == inst.name]
        for name, at, own in resolved_variables(inst):
            column = system.columns.get(name)
            if column is not None and (column.role in NOT_EFFECTS or name in references):
                why = (f"a {column.role} column (role: {column.role})"
                       if column.role in NOT_EFFECTS else "the reference of a comparison")
                raise SpecError(at, f"'{name}' is {why}: it is never an effect on a sensor")
            if own or column is not None or not mine:
                continue
            sx = sx_of(name)
            if sx is not None and any(ca.depends_on(sx, h) for h in mine):
                raise SpecError(at, f"'{name}' is computed from the outputs of '{inst.name}' "
                                    f"itself: a term in it would feed back into itself")


def problem_candidates(system: SystemSpec, constants: list[str],
                       fixed: list[str]) -> ProblemCandidates:
    """The constants (keys) and fixed parameters (names) the search may test."""
    spec = system.candidates
    if spec is None:
        return ProblemCandidates(tuple(constants), tuple(fixed), None)
    return ProblemCandidates(select(spec.constants, constants, "constant"),
                             select(spec.fixed, fixed, "fixed parameter"), spec.where)
