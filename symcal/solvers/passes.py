"""The chunk passes over the data: one task per piece, reduced in the order of the pieces.

A piece is a block of observations (``n_u × m``, a chunk of an in-memory dataset) or a
shard of a partitioned dataset (:class:`symcal.data.shards.Shard`, read by whoever runs the
task).  :class:`Pass` is the task: it evaluates a :class:`~symcal.base.numeric.Mapped`
function chunk by chunk and reduces the piece to something small; :func:`run_pass` maps
it with an executor (:mod:`symcal.solvers.executor`) and reduces the pieces' results in
their order, so that every executor gives the same result, bit for bit, on the same
pieces.  The kinds:

* ``cost``: Σ g²;
* ``terms``: Σ g_k² per constraint k;
* ``normal``: ``(Σ g², Jᵀg, JᵀJ)``;
* ``r``: the R factor of ``[J | g]`` (a TSQR: one blocked QR per chunk, combined in
  order);
* ``rt``: ``r`` and ``terms`` of the same evaluation (the same bits as each);
* ``gram``: ``(gᵀg, observations)``, g as an ``m × n_g`` matrix;
* ``residuals``: g itself, ``m × n_g`` (in-memory data only: its size grows with N).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Literal, Protocol

import numpy as np

from symcal.base import stops
from symcal.base.numeric import Mapped, chunks
from symcal.solvers.executor import Executor, blas_limit, blas_loaded

Kind = Literal["cost", "terms", "normal", "r", "rt", "gram", "residuals"]


class Piece(Protocol):
    """A shard of a partitioned dataset: read by the task that processes it."""

    def read(self, columns: tuple[str, ...]) -> np.ndarray:
        """The columns of the shard, ``len(columns) × rows``."""
        ...


#: Block size of LAPACK's compact-WY QR (``dgeqrt``): its panel updates are matrix-matrix
#: products, 1.4x faster than ``dgeqrf`` on the 24576 x 50 blocks of a chunk and 2.7x
#: faster than numpy's QR on the 3000 x 50 block of a dual solve at N = 1e3 (best of 8,
#: 16, 32, 50 measured here; the R factors agree to 1e-16 of their size).
QR_BLOCK = 16
#: Without numpy's own LAPACKE (see :func:`_lapacke_geqrt`): pieces of at least this
#: many rows go to SciPy's LAPACK, which releases the GIL (numpy's QR holds it: two
#: threads no faster than one), smaller ones to numpy, so that a small solve never pays
#: SciPy's 0.12 s import.
LAPACK_ROWS = 4_096
_LAPACK_SEEN = False
_GEQRT: list[Any] = []


def _lapacke_geqrt() -> Any:
    """``LAPACKE_dgeqrt`` of the OpenBLAS numpy itself loaded (its wheels bundle one with
    64-bit integers, ``scipy_LAPACKE_dgeqrt64_``), called through ctypes, which releases
    the GIL; None when numpy's LAPACK has no such entry (another build of numpy)."""
    if _GEQRT:
        return _GEQRT[0]
    import ctypes

    found = None
    try:
        from threadpoolctl import threadpool_info

        libs = [d["filepath"] for d in threadpool_info()
                if d.get("internal_api") == "openblas" and "numpy" in d["filepath"]]
        for path in libs:
            lib = ctypes.CDLL(path)
            entry = getattr(lib, "scipy_LAPACKE_dgeqrt64_", None)
            if entry is not None:
                entry.restype = ctypes.c_int64
                i64 = ctypes.c_int64
                entry.argtypes = [ctypes.c_int, i64, i64, i64, ctypes.c_void_p, i64,
                                  ctypes.c_void_p, i64]
                found = entry
                break
    except (OSError, ImportError, AttributeError):  # pragma: no cover - other builds
        found = None
    _GEQRT.append(found)
    return found


def _numpy_r(a: np.ndarray) -> np.ndarray:
    """The R factor by numpy's QR (LAPACK's ``geqrf``, the GIL held)."""
    r: np.ndarray = np.linalg.qr(np.asarray(a, dtype=float), mode="r")  # type: ignore[assignment]
    return r


def _qr_r(a: np.ndarray, overwrite: bool = False) -> np.ndarray:
    """The R factor of ``a`` (``min(rows, cols) × cols``) by LAPACK's blocked ``geqrt``:
    numpy's own LAPACKE at every size when it has one, else SciPy's for a tall piece and
    numpy's ``geqrf`` for a small one (the choice depends on the installation and the
    size alone, so the result never depends on what was imported before).  ``overwrite``:
    ``a`` may be overwritten (no copy where it is already a column-major float array)."""
    geqrt = _lapacke_geqrt()
    if geqrt is not None:
        if overwrite and a.dtype == np.float64 and a.flags.f_contiguous and a.flags.writeable:
            f = a
        else:
            f = np.array(a, dtype=float, order="F")    # a copy: LAPACK overwrites it
        m, n = f.shape
        k = min(m, n)
        if k == 0:
            return np.zeros((0, n))
        nb = min(QR_BLOCK, k)
        t = np.empty((nb, k), order="F")
        info = geqrt(102, m, n, nb, f.ctypes.data, m, t.ctypes.data, nb)  # column-major
        if info == -5:      # LAPACKE refuses NaN or inf: numpy's QR carries them into R,
            return _numpy_r(a)   # which the solver reads as a point to step back from
        if info != 0:  # pragma: no cover - LAPACK reports an illegal argument only
            raise ArithmeticError(f"LAPACKE dgeqrt failed (info {info})")
        return np.triu(f[:k])
    if a.shape[0] < LAPACK_ROWS:
        return _numpy_r(a)
    global _LAPACK_SEEN
    from scipy.linalg import lapack

    if not _LAPACK_SEEN:
        _LAPACK_SEEN = True
        blas_loaded()
    f = np.asfortranarray(a, dtype=float) if overwrite else np.array(a, dtype=float,
                                                                     order="F")
    k = min(f.shape)
    qr, _, info = lapack.dgeqrt(min(QR_BLOCK, k), f, overwrite_a=True)
    if info != 0:  # pragma: no cover - LAPACK reports an illegal argument only
        raise ArithmeticError(f"LAPACK dgeqrt failed (info {info})")
    return np.triu(qr[:k])


@dataclass(frozen=True, eq=False)
class Pass:
    """One pass's task: evaluate ``fn`` on a piece and reduce it (picklable for Dask).

    Attributes
    ----------
    kind
        What the piece is reduced to (see the module's docstring).
    fn
        ``fn(θ, u) -> (g,)`` or ``(g, vec(Jᵀ))`` per observation.
    theta
        The parameters.
    shape
        ``(n_g, n_free)``.
    columns
        The problem's columns, in the order of ``u`` (to read a shard).
    transform
        Optional ``k × n_g`` matrix applied to each observation's g and J (``r``); each
        observation then gives ``k`` rows, which may be fewer than ``n_g`` (the square
        root of a singular covariance).
    """

    kind: Kind
    fn: Mapped
    theta: np.ndarray
    shape: tuple[int, int]
    columns: tuple[str, ...]
    transform: np.ndarray | None = None

    def __call__(self, piece: np.ndarray | tuple[np.ndarray, np.ndarray] | Piece) -> Any:
        """The piece's reduction: a block ``u``, a block with per-row factors
        ``(u, w)`` (``w`` is ``m × n_g``, or ``m × n_g × n_g``: a matrix applied to each
        row's g and J), or a shard to read."""
        w: np.ndarray | None = None
        if isinstance(piece, tuple):
            u, w = piece
        else:
            u = piece if isinstance(piece, np.ndarray) else piece.read(self.columns)
        out: Any = None
        # a NaN or infinite cost is an answer (the solver steps back), not a warning; set
        # here, in the thread that evaluates (numpy's error state is per thread)
        with np.errstate(over="ignore", invalid="ignore"):
            for part in chunks(u.shape[1]):
                value = self._chunk(u[:, part], None if w is None else w[part])
                out = value if out is None else reduce_two(self.kind, out, value)
        return out

    def _chunk(self, u: np.ndarray, w: np.ndarray | None) -> Any:
        if self.kind in ("r", "rt") and w is None and self.transform is None and getattr(
                self.fn, "fills_blocks", False):
            return self._reduced(u)
        outs = self.fn.evaluate(self.theta, u)
        if w is None:
            g = outs[0]
        elif w.ndim == 3:
            g = np.einsum("mab,mb->ma", w, outs[0])
        else:
            g = outs[0] * w
        m = g.shape[0]
        if self.kind == "cost":
            return float(np.sum(g * g))
        if self.kind == "terms":
            return np.sum(g * g, axis=0)
        if self.kind == "gram":
            return g.T @ g, m
        if self.kind == "residuals":
            return g.copy()
        ng, n = self.shape
        jac = outs[1].reshape(m, ng, n)
        if w is not None:
            jac = jac * w[:, :, None] if w.ndim == 2 else np.einsum("mab,mbn->man", w, jac)
        if self.kind == "normal":
            jac2, res = jac.reshape(m * ng, n), g.reshape(m * ng)
            return float(res @ res), jac2.T @ res, jac2.T @ jac2
        if self.transform is not None:    # k rows per observation, maybe fewer than n_g
            g = g @ self.transform.T
            jac = np.einsum("ab,mbn->man", self.transform, jac)
            ng = self.transform.shape[0]
        block = np.empty((m * ng, n + 1), order="F")     # column-major for LAPACK
        block[:, :n] = jac.reshape(m * ng, n)
        block[:, n] = g.reshape(m * ng)
        return self._factored(block, m, ng)

    def _reduced(self, u: np.ndarray) -> Any:
        """:meth:`_chunk` of an ``r`` or ``rt`` pass by a compiled function that writes
        the block itself (:meth:`~symcal.base.jit.CompiledMapped.fill_block`): the same
        block, without the copy that lays the evaluated rows out column-major."""
        ng, n = self.shape
        m = u.shape[1]
        block = np.empty((m * ng, n + 1), order="F")
        self.fn.fill_block(self.theta, u, block)    # type: ignore[attr-defined]
        return self._factored(block, m, ng)

    def _factored(self, block: np.ndarray, m: int, ng: int) -> Any:
        """An ``r`` or ``rt`` chunk's result from its column-major block ``[J | g]``
        (``m`` observations of ``ng`` rows), factored in place."""
        g = block[:, -1]
        # each constraint's Σ g², as "terms" sums them (rows of one observation in order)
        terms = np.sum((g * g).reshape(m, ng), axis=0) if self.kind == "rt" else None
        if not np.isfinite(g).all():
            block[:, -1] = np.nan   # a residual inf or NaN: R's last column says so
        r = _qr_r(block, overwrite=True)
        return (r, m * ng) if terms is None else (r, m * ng, terms)


def reduce_two(kind: Kind, a: Any, b: Any) -> Any:
    """The reduction of two consecutive pieces' results (``a`` first)."""
    if kind == "cost":
        return a + b
    if kind == "terms":
        return a + b
    if kind == "gram":
        return a[0] + b[0], a[1] + b[1]
    if kind == "residuals":
        return np.concatenate([a, b], axis=0)
    if kind == "normal":
        return a[0] + b[0], a[1] + b[1], a[2] + b[2]
    n1 = a[0].shape[1]
    if kind == "rt":
        return _qr_r(np.vstack([a[0], b[0]]))[:n1], a[1] + b[1], a[2] + b[2]
    return _qr_r(np.vstack([a[0], b[0]]))[:n1], a[1] + b[1]


def run_pass(task: Pass, pieces: Iterable[np.ndarray | Piece], executor: Executor) -> Any:
    """Map ``task`` over ``pieces`` with ``executor``; reduce the results in order.

    ``residuals`` results are concatenated once at the end (not pairwise).  BLAS is held
    to its threads for symcal (:func:`~symcal.solvers.executor.blas_limit`) meanwhile.
    A stop the user asked for that other code swallowed is raised first
    (:func:`symcal.base.stops.check`).
    """
    stops.check()
    with blas_limit():
        if task.kind == "residuals":
            parts = list(executor.map(task, pieces))
            ng = task.shape[0]
            return np.concatenate(parts, axis=0) if parts else np.empty((0, ng))
        out: Any = None
        for value in executor.map(task, pieces):
            out = value if out is None else reduce_two(task.kind, out, value)
        return out
