"""The whitened design of a diagnosis: residual rows, the nuisance (what the current
parameters and the comparisons' arbitrary offsets can already absorb) and candidate
regressors, weighted per observation.

Where every residual's readings declare their noise, each observation's rows are
whitened by the inverse square root of their propagated covariance (the weights of the
adjustment with condition equations: residuals of different noise and observations at
different poses combined as the theory says); elsewhere by one covariance per dataset,
estimated from what the current parameters cannot explain (not from the raw residuals:
comparisons also carry the estimate's own error, which a refit removes).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from symcal.analysis.discovery import Candidate, Design, bic_change, refit, rms
from symcal.analysis.row_noise import EXACT
from symcal.base.linalg import range_basis, whitening
from symcal.base.units import DISPLAY_UNITS
from symcal.problem.symbolic import Problem
from symcal.revise.blocks import Block

#: Each residual's ``"DATASET/NAME"`` → (now, predicted), display units.
Sizes = dict[str, tuple[float, float]]

Raw = Callable[[int], np.ndarray]   # block index -> unwhitened regressor (N, n_q, m)


def sqrt_rows(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row, ``C^-½`` and ``C^½`` of a covariance (m × n × n); an exact direction
    (a residual whose readings are all exact) gets weight zero."""
    w, v = np.linalg.eigh(c)
    top = np.max(w, axis=1, keepdims=True)
    keep = w > EXACT * np.maximum(top, 1e-300)
    root = np.sqrt(np.where(keep, w, 0.0))
    inv = np.where(keep, 1.0 / np.where(keep, root, 1.0), 0.0)
    return (np.einsum("mab,mb,mcb->mac", v, inv, v),
            np.einsum("mab,mb,mcb->mac", v, root, v))


def whiten(x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Whitened rows of a regressor (N, n_q, m) by per-row ``t`` (N, rank, n_q) →
    (N·rank, m)."""
    return np.einsum("nab,nbm->nam", t, x).reshape(-1, x.shape[2])


def _centred(b: Block) -> np.ndarray:
    resid = b.after.copy()
    for k, off in enumerate(b.offsets):
        if off:
            resid[:, k] -= resid[:, k].mean()
    return resid


def _whiteners(b: Block, noise: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Per row of ``b``: the whitening (N × rank × n_q) and unwhitening (N × n_q × rank)."""
    n, nq = b.after.shape
    if b.cov is not None and noise is None:
        return sqrt_rows(b.cov)
    cov = np.cov(_centred(b) if noise is None else noise, rowvar=False, bias=True)
    t, t_inv = whitening(np.asarray(cov).reshape(nq, nq))
    return (np.broadcast_to(t, (n, *t.shape)), np.broadcast_to(t_inv, (n, *t_inv.shape)))


def design(blocks: list[Block], problem: Problem, free: np.ndarray
           ) -> tuple[Design, list[np.ndarray]]:
    """The whitened design of ``blocks`` and each block's per-row whitening."""
    first, _ = _design(blocks, problem, free, None)
    if all(b.cov is not None for b in blocks):
        return first, [_whiteners(b, None)[0] for b in blocks]
    return _design(blocks, problem, free, _projected(first, blocks))


def _projected(design: Design, blocks: list[Block]) -> list[np.ndarray | None]:
    """Per block, the residuals (N × n_q, unwhitened) left after the nuisance is fitted,
    for the blocks whitened by an estimated covariance (None for a propagated one)."""
    q = range_basis(design.nuisance)
    r = design.r - q @ (q.T @ design.r)
    out: list[np.ndarray | None] = []
    for b, (_, rows, unwhiten, _, _) in zip(blocks, design.blocks, strict=True):
        rank = unwhiten.shape[2]
        out.append(None if b.cov is not None else
                   np.einsum("nqr,nr->nq", unwhiten, r[rows].reshape(-1, rank)))
    return out


def _design(blocks: list[Block], problem: Problem, free: np.ndarray,
            residuals: list[np.ndarray | None] | None) -> tuple[Design, list[np.ndarray]]:
    rows, nuis_rows, block_info, whiteners = [], [], [], []
    n_params = int(free.sum())
    n_offsets = sum(sum(b.offsets) for b in blocks)
    offset_index = 0
    start = 0
    for i, b in enumerate(blocks):
        resid = _centred(b)
        t, t_inv = _whiteners(b, None if residuals is None else residuals[i])
        whiteners.append(t)
        n, nq = resid.shape
        rank = t.shape[1]
        rows.append(np.einsum("nab,nb->na", t, resid).reshape(-1))
        nuis = np.zeros((n, nq, n_params + n_offsets))
        nuis[:, :, :n_params] = b.jac
        for k, off in enumerate(b.offsets):
            if off:
                nuis[:, k, n_params + offset_index] = 1.0
                offset_index += 1
        nuis_rows.append(whiten(nuis, t))
        scales = tuple(DISPLAY_UNITS[u] for u in b.units)
        block_info.append((b.dataset.name, slice(start, start + n * rank), t_inv,
                           tuple(b.names), scales))
        start += n * rank
    free_names = [n for n, f in zip(problem.parameter_names, free, strict=True) if f]
    offsets = [f"offset of {name} on {b.dataset.name}" for b in blocks
               for name, off in zip(b.names, b.offsets, strict=True) if off]
    out = Design(np.concatenate(rows), np.vstack(nuis_rows), tuple(free_names + offsets),
                 tuple(block_info))
    return out, whiteners


def predict(cand: Candidate, own: Design, x_own: np.ndarray, blocks: list[Block],
            free: np.ndarray, raw: Raw) -> None:
    """What solving the calibration again with ``cand`` would give on every dataset: a
    Gauss-Newton refit of the current parameters and the candidate's coefficients on the
    calibration's constraints, applied to every residual; fills ``reduction`` (RMS now →
    predicted, display units; the standard deviation where a comparison's mean is an
    arbitrary zero) and the coefficients of the term to add (regressors are the
    change a term of coefficient 1 makes) with standard errors, and the BIC's predicted
    change (:func:`~symcal.analysis.discovery.bic_change`)."""
    coef_x, cov, (sizes, scatter) = predicted_spreads(own, x_own, blocks, free, raw)
    cand.bic_change = bic_change(own, x_own)
    # the fit explains the residual as X·δ; the term to add to the model is -δ
    cand.coefficient = tuple(-float(v) for v in coef_x)
    cand.coefficient_se = tuple(float(np.sqrt(max(cov[k, k], 0.0)))
                                for k in range(len(coef_x)))
    cand.reduction, cand.scatter = sizes, scatter


def predicted_spreads(own: Design, x_own: np.ndarray, blocks: list[Block],
                      free: np.ndarray, raw: Raw
                      ) -> tuple[np.ndarray, np.ndarray, tuple[Sizes, Sizes]]:
    """The Gauss-Newton refit of :func:`predict` for the regressors ``x_own`` (whitened,
    the calibration's constraints) and ``raw`` (every block's): their coefficients, the
    coefficients' covariance, and every residual's RMS now and predicted (the mean
    removed first where it is an arbitrary zero) and the same of its standard deviation:
    the sizes ``symcal improve`` compares after the solve
    (:meth:`~symcal.analysis.fit.Spread.size`)."""
    coef_n, coef_x, cov, _ = refit(own, x_own)
    n_params = int(free.sum())
    sizes: Sizes = {}
    scatter: Sizes = {}
    for i, b in enumerate(blocks):
        change = b.jac @ coef_n[:n_params] + raw(i) @ coef_x
        predicted = b.after - change
        for k, name in enumerate(b.names):
            now, new = b.after[:, k], predicted[:, k]
            if b.offsets[k]:
                now, new = now - now.mean(), new - new.mean()
            scale, key = DISPLAY_UNITS[b.units[k]], f"{b.dataset.name}/{name}"
            sizes[key] = (rms(now) / scale, rms(new) / scale)
            scatter[key] = (float(np.std(now)) / scale, float(np.std(new)) / scale)
    return coef_x, cov, (sizes, scatter)
