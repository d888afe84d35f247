"""Compiled one-observation functions, built once and cached on disk by their content.

CasADi's virtual machine interprets a function's instructions; the same function as C
code, compiled, evaluates about 3× faster here (17.5 → 6.2 ms per chunk of 8192
observations of the §3.2 Jacobian), so a pass over a large log is worth a compile
(≈ 0.4 s).  The C code is CasADi's own code generation of the function; the compiled
library is cached under the user's cache folder (``$XDG_CACHE_HOME/symcal/functions``,
by default ``~/.cache/symcal/functions``) in a file named by the SHA-256 of everything
that determines it (format, CasADi version, compiler, flags, and the function's CasADi
serialisation), so another run of the same problem, or a Dask worker on the same
machine, loads it instead of compiling.

Safety of the cache: the library is written through :func:`symcal.base.files.atomic_write_bytes`
(temporary file and rename: a concurrent writer or a crash never leaves half a file),
next to the SHA-256 of its bytes; an entry is loaded only when its bytes have that
digest, and anything else (missing, corrupted, unloadable) is rebuilt, never trusted.

``SYMCAL_JIT``: ``auto`` (default, when a C compiler is found: ``$CC``, ``cc`` or
``gcc``), ``on`` (compile for every pass), ``off`` (never).  ``auto`` builds the twin
when it pays (:func:`select`): at once for a pass over at least :data:`JIT_MIN`
observations (a large solve: the compile is repaid within the pass), and in a background
thread once a function's passes in this process have evaluated :data:`JIT_MIN`
observations in all (a loop of repeated solves of one structure: ``improve``, ``design``, a
benchmark, a fleet's worker), while the passes go on interpreted until the twin is
loaded; a twin already in the cache is used from the first pass.  The compile of the
bundled problems' functions takes 0.07 to 0.13 s and saves about 1.4 µs per observation
of the §3.2 Jacobian, so :data:`JIT_MIN` observations repay it (a rent-or-buy rule: at
most twice the cost of knowing the future).  When compiling fails the interpreted
function is used, as without a compiler; the results are the same bit for bit (the
compiled code performs the same IEEE operations in the same order, contraction into fused
multiply-adds disabled), so when a pass switches makes no difference to any result.

A function of a linearisation, ``(g, vec(Jᵀ))``, has a second loop (:data:`BLOCK_ENTRY`,
:meth:`CompiledMapped.fill_block`) that writes its observations straight into the
column-major block ``[J | g]`` a QR pass factors, :data:`TILE` observations at a time (a
tile evaluated, then laid out while it is in the cache): the same block as the evaluated
rows copied, without that transposing copy (about 1 ms of a 13 ms chunk of the §3.2 pass).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
import threading
import time
import weakref
from pathlib import Path

import casadi as ca
import numpy as np

from symcal.base.errors import SymcalError
from symcal.base.files import atomic_write_bytes, atomic_write_text
from symcal.base.forks import ForkLock, in_forked_child
from symcal.base.numeric import Mapped, from_serialized

#: ``auto`` compiles for a pass over at least this many observations, and in the
#: background once a function's passes have evaluated this many in all.
JIT_MIN = 131_072
#: Version of the cache's layout and key (4: the block loop).
FORMAT = 4
#: Compiler flags: no fused multiply-add contraction, so results keep IEEE operations.
FLAGS = ("-O1", "-fPIC", "-shared", "-ffp-contract=off")

_LOCK = ForkLock()
_LOADED: dict[str, ctypes.CDLL] = {}
_FAILED: set[str] = set()


def mode() -> str:
    """``SYMCAL_JIT``: ``auto``, ``on`` or ``off``."""
    value = os.environ.get("SYMCAL_JIT", "auto").strip().lower() or "auto"
    if value not in ("auto", "on", "off"):
        raise SymcalError(f"SYMCAL_JIT must be auto, on or off, not '{value}'")
    return value


def compiler() -> str | None:
    """The C compiler: ``$CC`` if set, else ``cc`` or ``gcc`` on the path, else None."""
    cc = os.environ.get("CC")
    if cc:
        return shutil.which(cc)
    return shutil.which("cc") or shutil.which("gcc")


def cache_dir() -> Path:
    """Where compiled functions are kept: ``$XDG_CACHE_HOME/symcal/functions`` (an absolute
    ``XDG_CACHE_HOME`` only, as the XDG specification says), else
    ``~/.cache/symcal/functions``."""
    base = os.environ.get("XDG_CACHE_HOME", "")
    root = Path(base) if base and os.path.isabs(base) else Path.home() / ".cache"
    return root / "symcal" / "functions"


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


#: Name of the loop over observations appended to the generated code.
ENTRY = "symcal_map"
#: Name of the loop writing a linearisation's observations into a column-major block.
BLOCK_ENTRY = "symcal_block"
#: Observations the block loop evaluates before laying them out (a tile that stays in
#: the cache while it is transposed).
TILE = 64


def _source(fn: ca.Function) -> str:
    """CasADi's C code of ``fn`` and a loop calling it on ``n`` observations: θ shared,
    observation i's inputs at ``u + i·n_u``, its outputs at ``out_k + i·nnz_k``."""
    cg = ca.CodeGenerator(f"{fn.name()}.c", {"with_header": False})
    cg.add(fn)
    nu = fn.nnz_in(1)
    strides = [fn.nnz_out(k) for k in range(fn.n_out())]
    calls = "\n".join(f"    res[{k}] = out[{k}] + i * {s};" for k, s in enumerate(strides))
    return str(cg.dump()) + f"""
int {ENTRY}(casadi_int n, const casadi_real* theta, const casadi_real* u,
            casadi_real** out, casadi_real* w, casadi_int* iw) {{
  const casadi_real* arg[{max(fn.sz_arg(), 2)}];
  casadi_real* res[{max(fn.sz_res(), len(strides))}];
  casadi_int i;
  arg[0] = theta;
  for (i = 0; i < n; ++i) {{
    arg[1] = u + i * {nu};
{calls}
    if ({fn.name()}(arg, res, iw, w, 0)) return 1;
  }}
  return 0;
}}
""" + _block_source(fn)


def _block_source(fn: ca.Function) -> str:
    """For a function ``(θ, u) → (g, vec(Jᵀ))`` (``n_g`` residuals, ``vec(Jᵀ)`` holding
    ``J[a, p]`` at ``a·n_p + p``), a loop :data:`BLOCK_ENTRY` writing ``n`` observations
    straight into a column-major block ``[J | g]`` of leading dimension ``ld``:
    observation i's residual a on row ``i·n_g + a`` (what a QR pass factors, without the
    transposing copy); empty for any other function."""
    if fn.n_out() != 2 or fn.nnz_out(0) == 0 or fn.nnz_out(1) % fn.nnz_out(0):
        return ""
    ng = fn.nnz_out(0)
    n_p = fn.nnz_out(1) // ng
    return f"""
int {BLOCK_ENTRY}(casadi_int n, const casadi_real* theta, const casadi_real* u,
                  casadi_real* block, casadi_int ld, casadi_real** tmp, casadi_real* w,
                  casadi_int* iw) {{
  const casadi_real* arg[{max(fn.sz_arg(), 2)}];
  casadi_real* res[{max(fn.sz_res(), 2)}];
  casadi_int i, j, t, a, p;
  arg[0] = theta;
  for (i = 0; i < n; i += {TILE}) {{
    t = n - i < {TILE} ? n - i : {TILE};
    for (j = 0; j < t; ++j) {{
      arg[1] = u + (i + j) * {fn.nnz_in(1)};
      res[0] = tmp[0] + j * {ng};
      res[1] = tmp[1] + j * {ng * n_p};
      if ({fn.name()}(arg, res, iw, w, 0)) return 1;
    }}
    for (p = 0; p < {n_p}; ++p) {{
      casadi_real* col = block + p * ld + i * {ng};
      for (j = 0; j < t; ++j)
        for (a = 0; a < {ng}; ++a) col[j * {ng} + a] = tmp[1][j * {ng * n_p} + a * {n_p} + p];
    }}
    for (j = 0; j < t * {ng}; ++j) block[{n_p} * ld + i * {ng} + j] = tmp[0][j];
  }}
  return 0;
}}
"""


def _load(path: Path) -> ctypes.CDLL:
    """The library at ``path`` with its loop's signature declared."""
    lib = ctypes.CDLL(str(path))
    entry = getattr(lib, ENTRY)
    entry.restype = ctypes.c_int
    entry.argtypes = [ctypes.c_longlong, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
                      ctypes.c_void_p, ctypes.c_void_p]
    block = getattr(lib, BLOCK_ENTRY, None)
    if block is not None:
        block.restype = ctypes.c_int
        block.argtypes = [ctypes.c_longlong, ctypes.c_void_p, ctypes.c_void_p,
                          ctypes.c_void_p, ctypes.c_longlong, ctypes.c_void_p,
                          ctypes.c_void_p, ctypes.c_void_p]
    return lib


def _trusted(path: Path) -> bool:
    """Whether the cached library at ``path`` has the digest recorded beside it."""
    sidecar = path.with_suffix(".sha256")
    try:
        return sidecar.read_text(encoding="ascii").strip() == _digest(path.read_bytes())
    except (OSError, UnicodeError):
        return False


def _build(source: str, name: str, cc: str, target: Path) -> None:
    """Compile ``source`` and store the library at ``target`` with its digest."""
    with tempfile.TemporaryDirectory(prefix="symcal-jit-") as tmp:
        c_file, so_file = Path(tmp) / f"{name}.c", Path(tmp) / f"{name}.so"
        c_file.write_text(source, encoding="utf-8")
        subprocess.run([cc, *FLAGS, str(c_file), "-o", str(so_file), "-lm"], check=True,
                       capture_output=True, timeout=300)
        data = so_file.read_bytes()
    atomic_write_bytes(target, data)
    atomic_write_text(target.with_suffix(".sha256"), _digest(data) + "\n")


#: A build whose claim is older than this (s) was abandoned (its process was killed): the
#: claim is taken over.  As long as the compiler's own time limit.
BUILD_WAIT = 300.0


def _claim(lock: Path) -> bool:
    """Claim the build of a cache entry (create ``lock`` exclusively); False when another
    process holds a claim younger than :data:`BUILD_WAIT`."""
    lock.parent.mkdir(parents=True, exist_ok=True)
    for _ in range(2):
        try:
            os.close(os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644))
            return True
        except FileExistsError:
            try:
                if time.time() - lock.stat().st_mtime <= BUILD_WAIT:
                    return False
                lock.unlink()                         # abandoned: take it over
            except FileNotFoundError:
                continue                              # released meanwhile: claim again
    return False


def _build_once(fn: ca.Function, cc: str, target: Path) -> None:
    """Build the entry ``target``, once across processes: the process that claims it
    compiles; another one waits for its entry (its passes go on interpreted meanwhile,
    when it builds in the background) and compiles itself only if none appears.  A fleet
    of worker processes on one machine compiles each function once, not once per
    worker."""
    lock = target.with_suffix(".building")
    if _claim(lock):
        try:
            _build(_source(fn), fn.name(), cc, target)
        finally:
            lock.unlink(missing_ok=True)
        return
    deadline = time.monotonic() + BUILD_WAIT
    while lock.exists() and not _trusted(target) and time.monotonic() < deadline:
        time.sleep(0.05)
    if not _trusted(target):                          # the other build failed
        _build(_source(fn), fn.name(), cc, target)


def _key(serialized: bytes, cc: str) -> str:
    """The cache key: everything that determines the compiled library."""
    head = "\0".join([str(FORMAT), str(ca.CasadiMeta.version()), cc, *FLAGS]).encode()
    return _digest(head + b"\0" + serialized)


def compiled(fn: ca.Function, serialized: bytes, build: bool = True) -> ctypes.CDLL | None:
    """The compiled library of ``fn`` (its loop :data:`ENTRY`), loaded from the disk cache
    or, when ``build``, compiled now; None when there is no compiler, ``fn``'s name is not
    a C identifier, compiling fails, or it is not cached and ``build`` is False.

    ``serialized`` is ``fn``'s CasADi serialisation: the cache is keyed by it (with the
    format, CasADi version, compiler and flags), so a problem built again from the same
    YAML finds its functions.  No lock is held while compiling: other threads go on (two
    threads compiling the same function write the same entry, atomically).
    """
    cc = compiler()
    if cc is None or not fn.name().isidentifier():
        return None
    key = _key(serialized, cc)
    with _LOCK:
        if key in _LOADED:
            return _LOADED[key]
        if key in _FAILED:
            return None
    target = cache_dir() / f"{key}.so"
    try:
        if not _trusted(target):
            if not build:
                return None
            _build_once(fn, cc, target)
        try:
            loaded = _load(target)
        except (OSError, AttributeError):   # trusted bytes that do not load: rebuild
            _build(_source(fn), fn.name(), cc, target)
            loaded = _load(target)
    except (OSError, AttributeError, subprocess.SubprocessError):
        with _LOCK:
            _FAILED.add(key)
        return None
    with _LOCK:
        return _LOADED.setdefault(key, loaded)


class _Work:
    """One thread's buffers for the compiled loop."""

    def __init__(self, fn: ca.Function, size: int) -> None:
        self.size = size
        self.u = np.empty((size, fn.nnz_in(1)))
        self.outs = [np.empty((size, fn.nnz_out(k))) for k in range(fn.n_out())]
        self.pointers = (ctypes.c_void_p * len(self.outs))(
            *(o.ctypes.data for o in self.outs))
        self.w = np.empty(max(int(fn.sz_w()), 1))
        self.iw = np.empty(max(int(fn.sz_iw()), 1), dtype=np.int64)


class CompiledMapped(Mapped):
    """A :class:`~symcal.base.numeric.Mapped` evaluated by compiled code, called through
    ctypes (which releases the GIL: threads evaluate chunks on different cores); pickles
    as its interpreted source, which the receiving process compiles or loads from its
    cache."""

    def __init__(self, source: Mapped, lib: ctypes.CDLL) -> None:
        super().__init__(source.fn)
        self.source = source
        self.lib = lib
        self._entry = getattr(lib, ENTRY)
        self._block = getattr(lib, BLOCK_ENTRY, None)
        self._serialized = source.serialized()

    def evaluate(self, theta: np.ndarray, u: np.ndarray) -> list[np.ndarray]:
        """As :meth:`Mapped.evaluate`: views of this thread's buffers."""
        n = u.shape[1]
        work, th = self._inputs(theta, u)
        self._check(self._entry(n, th.ctypes.data, work.u.ctypes.data, work.pointers,
                                work.w.ctypes.data, work.iw.ctypes.data))
        return [out[:n] for out in work.outs]

    def _inputs(self, theta: np.ndarray, u: np.ndarray) -> tuple[_Work, np.ndarray]:
        """This thread's buffers with the observations ``u`` in, and θ contiguous."""
        n = u.shape[1]
        work: _Work | None = getattr(self._local, "work", None)
        if work is None or work.size < n:
            work = _Work(self.fn, max(n, 1))
            self._local.work = work
        work.u[:n] = u.T
        return work, np.ascontiguousarray(theta, dtype=float)

    def _check(self, status: int) -> None:
        if status:  # pragma: no cover - generated SX code does not fail
            raise ArithmeticError(f"compiled {self.fn.name()} failed (status {status})")

    @property
    def fills_blocks(self) -> bool:
        """Whether :meth:`fill_block` is available (a function ``(g, vec(Jᵀ))``)."""
        return self._block is not None

    def fill_block(self, theta: np.ndarray, u: np.ndarray, block: np.ndarray) -> None:
        """Write the ``n`` observations ``u`` (``n_u × n``) into ``block``, a column-major
        ``(n·n_g) × (n_p + 1)`` float array: ``[J | g]`` with observation i's residual a
        on row ``i·n_g + a`` (the values :meth:`evaluate` gives, copied, the same bits)."""
        n = u.shape[1]
        ng = self.fn.nnz_out(0)
        if (self._block is None or block.dtype != np.float64 or not block.flags.f_contiguous
                or not block.flags.writeable
                or block.shape != (n * ng, self.fn.nnz_out(1) // ng + 1)
                or np.size(theta) != self.fn.nnz_in(0)):
            raise ValueError("fill_block needs a (g, vec(J')) function, its parameters and a "
                             "writable column-major block of its shape")
        work, th = self._inputs(theta, u)
        self._check(self._block(n, th.ctypes.data, work.u.ctypes.data, block.ctypes.data,
                                block.shape[0], work.pointers, work.w.ctypes.data,
                                work.iw.ctypes.data))

    def __reduce__(self) -> tuple[object, tuple[bytes]]:
        return fast_from_serialized, (self.source.serialized(),)


_TWINS: dict[int, Mapped] = {}


def _known(mapped: Mapped) -> Mapped | None:
    """The twin of ``mapped`` this process already has, if any."""
    twin = _TWINS.get(id(mapped))
    return twin if twin is not None and getattr(twin, "source", None) is mapped else None


def fast(mapped: Mapped, build: bool = True) -> Mapped:
    """The compiled twin of ``mapped`` (one per process), or ``mapped`` itself when it is
    not compiled: no compiler, compiling failed, or not in the cache and not ``build``."""
    if isinstance(mapped, CompiledMapped):
        return mapped
    twin = _known(mapped)
    if twin is not None:
        return twin
    lib = compiled(mapped.fn, mapped.serialized(), build)
    if lib is None:
        return mapped
    twin = CompiledMapped(mapped, lib)
    _TWINS[id(mapped)] = twin
    return twin


def fast_from_serialized(data: bytes) -> Mapped:
    """:func:`fast` of the process's :class:`~symcal.base.numeric.Mapped` of ``data``."""
    return fast(from_serialized(data))


#: Observations each function's passes evaluated interpreted in this process.
_TALLY: weakref.WeakKeyDictionary[Mapped, int] = weakref.WeakKeyDictionary()
#: Functions whose twin is being (or was) built in the background.
_PENDING: weakref.WeakSet[Mapped] = weakref.WeakSet()
_TALLY_LOCK = ForkLock()


def _forget_builds() -> None:
    """A forked child starts its own tallies: its parent's builds in the background run
    in threads the child lacks, and would never end there."""
    _TALLY.clear()
    _PENDING.clear()


in_forked_child(_forget_builds)


def select(mapped: Mapped, observations: int) -> Mapped:
    """The function a pass over ``observations`` observations evaluates: ``mapped`` or its
    compiled twin, built when it pays (see the module; ``SYMCAL_JIT``).

    Parameters
    ----------
    mapped
        The interpreted one-observation function of the pass.
    observations
        How many observations the pass evaluates.

    Returns
    -------
    Mapped
        The twin when this process has it, the cache holds it, ``SYMCAL_JIT=on``, or the
        pass is large (compiled now); else ``mapped``, and a background build starts
        once the function's passes have evaluated :data:`JIT_MIN` observations in all.
    """
    m = mode()
    if m == "off" or isinstance(mapped, CompiledMapped):
        return mapped
    twin = _known(mapped)
    if twin is not None:
        return twin
    if m == "on" or observations >= JIT_MIN:
        return fast(mapped, build=True)
    with _TALLY_LOCK:
        before = _TALLY.get(mapped, 0)
        total = before + observations
        _TALLY[mapped] = total
        start = total >= JIT_MIN and mapped not in _PENDING
        if start:
            _PENDING.add(mapped)
    if before == 0:             # the first pass in this process: look in the cache
        found = fast(mapped, build=False)
        if found is not mapped:
            return found
    if start:
        threading.Thread(target=fast, args=(mapped, True), name="symcal-jit",
                         daemon=False).start()
    return mapped


def building() -> list[threading.Thread]:
    """The background builds still running (join them to wait for their twins)."""
    return [t for t in threading.enumerate() if t.name == "symcal-jit" and t.is_alive()]
