"""Closing the implicit definitions a build left open (``x = F(x)``): at their final
fixed-point iterate (the problem in use, the diagnostic view) or at their starts (the
explicit twin), with the checks of contraction and convergence."""

from __future__ import annotations

import casadi as ca

from symcal.base.errors import SpecError, Where
from symcal.problem.names import OpenDefinition
from symcal.problem.symbolic import ImplicitOutput


def unroll(fmap: ca.SX, x: ca.SX, start: ca.SX, steps: int) -> tuple[ca.SX, ca.SX]:
    """The final iterate of ``x ← fmap(x)`` from ``start`` and the change of its last step."""
    iterates = [start]
    for _ in range(steps):
        iterates.append(ca.substitute(fmap, x, iterates[-1]))
    last = iterates[-1] - iterates[-2] if steps else ca.SX.zeros(start.shape)
    return iterates[-1], last


def close_unrolled(model: list[OpenDefinition], top: list[OpenDefinition]
                   ) -> tuple[list[ca.SX], list[ca.SX], list[ImplicitOutput]]:
    """Every placeholder at its final fixed-point iterate: the placeholders, their values
    (free of placeholders) and the implicit checks.

    ``model`` are the instances' definitions in the order they were opened, ``top`` the
    problem's (solved together, after the model level)."""
    # model level: innermost (latest opened) first, each in terms of the ones opened
    # before it; then forward, so that every value is free of model placeholders
    finals: dict[int, tuple[ca.SX, ca.SX, ca.SX]] = {}
    for k in range(len(model) - 1, -1, -1):
        d = model[k]
        later = [model[j].symbol for j in finals]
        later_values = [finals[j][0] for j in finals]
        fmap = ca.substitute(d.fmap, ca.vertcat(*later), ca.vertcat(*later_values)) \
            if later else d.fmap
        start = ca.substitute(d.start, ca.vertcat(*later), ca.vertcat(*later_values)) \
            if later else d.start
        final, last = unroll(fmap, d.symbol, start, d.steps)
        deriv = ca.substitute(ca.jacobian(fmap, d.symbol), d.symbol, final)
        finals[k] = (final, deriv, last)
    values: list[ca.SX] = []
    outs: list[tuple[ca.SX, ca.SX]] = []
    for k in range(len(model)):
        final, deriv, last = finals[k]
        if k:
            earlier = ca.vertcat(*(m.symbol for m in model[:k]))
            final, deriv, last = ca.substitute([final, deriv, last], [earlier],
                                               [ca.vertcat(*values)])
        values.append(final)
        outs.append((deriv, last))
    symbols = [d.symbol for d in model]
    checks_pending = [(d.key, d.steps, deriv, last) for d, (deriv, last) in zip(model, outs,
                                                                               strict=True)]
    if top:
        x = ca.vertcat(*(d.symbol for d in top))
        fmap = ca.vertcat(*(d.fmap for d in top))
        if model:
            fmap = ca.substitute([fmap], symbols, values)[0]
        for d in top:
            if not ca.depends_on(fmap, d.symbol):
                raise SpecError(d.where, f"'{d.key}' is declared implicit but no implicit "
                                         "definition depends on it")
        steps = max(d.steps for d in top)
        final, last = unroll(fmap, x, ca.vertcat(*(d.start for d in top)), steps)
        norm = ca.mmax(ca.sum2(ca.fabs(ca.jacobian(fmap, x))))  # ‖∂F/∂x‖∞
        top_values = [final[k] for k in range(len(top))]
        top_symbols = [d.symbol for d in top]
        values = ca.substitute(values, top_symbols, top_values) if values else []
        closed = []
        for key, count, dv, ls in checks_pending:
            dv, ls = ca.substitute([dv, ls], top_symbols, top_values)
            closed.append((key, count, dv, ls))
        checks_pending = closed
        checks_pending.insert(0, (", ".join(d.key for d in top), steps,
                                  ca.substitute(norm, x, final), ca.mmax(ca.fabs(last))))
        symbols += top_symbols
        values += top_values
    checks = [ImplicitOutput(k, s, dv, ls) for k, s, dv, ls in checks_pending]
    return symbols, values, checks

def close_at_starts(model: list[OpenDefinition], top: list[OpenDefinition]
                    ) -> tuple[list[ca.SX], list[ca.SX], list[ImplicitOutput]]:
    """Every placeholder at its start: the explicit model (zero fixed-point steps)."""
    symbols = [d.symbol for d in (*model, *top)]
    values = resolve_starts(symbols, [d.start for d in (*model, *top)])
    zero = ca.SX(0)
    checks = [ImplicitOutput(d.key, 0, zero, zero) for d in model]
    if top:
        checks.insert(0, ImplicitOutput(", ".join(d.key for d in top), 0, zero, zero))
    return symbols, values, checks


def resolve_starts(symbols: list[ca.SX], starts: list[ca.SX]) -> list[ca.SX]:
    """Every placeholder at its start, starts that name other placeholders included."""
    values = list(starts)
    for _ in range(len(symbols) + 1):
        if not any(ca.depends_on(v, s) for v in values for s in symbols):
            return values
        values = ca.substitute(values, symbols, values)
    raise SpecError(Where("implicit"), "the starts of implicit definitions refer to each "
                                       "other in a cycle")
