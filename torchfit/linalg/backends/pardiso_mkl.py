"""MKL PARDISO through ``ctypes``: the library, host-side structures and handles.

This module is the binding only (numpy in, numpy out, no torch, no counters); the
:class:`~torchfit.linalg.backends.pardiso.PardisoBackend` builds the ``Factor`` interface on it.
PARDISO comes with the optional extra ``torchfit[pardiso]`` (``pypardiso`` and the
``mkl`` wheels: x86-64 only, about 700 MB). The shared library is found the way
pypardiso finds it (``PYPARDISO_MKL_RT``, ``ctypes.util.find_library``, the
environment's ``lib``); the calls are made here, with settings of our own (why not
pypardiso's own solver: ``docs/notes/pardiso.md``).

PARDISO's phases: 11 symbolic analysis (fill-reducing METIS ordering, symbolic
factorisation), 22 numeric factorisation, 33 solve (forward/backward substitution),
0 release the factor ``mnum``, -1 release everything of a handle. One handle (the
64-pointer ``pt``) keeps one analysis and up to ``maxfct`` numeric factorisations of
matrices with that structure (selected by ``mnum``): :class:`PardisoHandle` uses this
to share the analysis among every factor of one sparsity pattern.

Settings (``iparm``, zero-based indices, everything set explicitly with ``iparm[0] = 1``):
METIS ordering (``[1] = 2``), pivot perturbation ``1e-13 ||A||`` (``[9] = 13``) for every
matrix type, so that a perturbed pivot marks a numerically singular matrix rather than
a small pivot of a regular one; scaling and weighted matching for nonsymmetric matrices
(``[10] = [12] = 1``, MKL's default there; they read the values in phase 11), none for
symmetric ones (their analysis is purely structural); Bunch-Kaufman pivoting for
symmetric indefinite (``[20] = 1``); zero-based CSR indices (``[34] = 1``); no iterative
refinement (``[7] = 0``: MKL then refines only after perturbed pivots, which
:class:`~torchfit.linalg.backends.pardiso.PardisoBackend` reports as singular).
"""
from __future__ import annotations

import ctypes
import threading
import weakref
from typing import Any

import numpy as np

from ..threads import apply_requested_threads

#: how the optional dependency is installed (named by every "not installed" error)
PARDISO_EXTRA = "pip install 'torchfit[pardiso]'"

#: PARDISO matrix types used here
REAL_SPD = 2
REAL_SYMMETRIC_INDEFINITE = -2
REAL_NONSYMMETRIC = 11

#: PARDISO's error codes (MKL reference, ``pardiso``)
ERROR_TEXT = {
    -1: "input inconsistent",
    -2: "not enough memory",
    -3: "reordering problem",
    -4: "zero pivot, numerical factorization or iterative refinement problem",
    -5: "unclassified (internal) error",
    -6: "reordering failed",
    -7: "diagonal matrix is singular",
    -8: "32-bit integer overflow problem",
    -9: "not enough memory for out-of-core",
    -10: "error opening out-of-core files",
    -11: "read/write error with out-of-core files",
    -12: "pardiso_64 called from a 32-bit library",
    -13: "interrupted",
    -15: "reordering failed (nonsymmetric matrix)",
}
#: error codes that mean "the matrix is singular"
SINGULAR_CODES = (-4, -7)


class PardisoUnavailableError(ImportError):
    """MKL PARDISO cannot be used here (pypardiso or the MKL library is missing)."""


class PardisoError(RuntimeError):
    """A PARDISO call returned an error code."""

    def __init__(self, code: int, phase: int) -> None:
        self.code = int(code)
        self.phase = int(phase)
        super().__init__(f"PARDISO phase {phase} failed with error {code} "
                         f"({ERROR_TEXT.get(code, 'unknown error')})")


def _unavailable(reason: str) -> PardisoUnavailableError:
    return PardisoUnavailableError(
        f"the 'pardiso' backend needs MKL PARDISO ({reason}): {PARDISO_EXTRA} "
        "(MKL wheels, x86-64 only, about 700 MB), or use backend='scipy'")


class PardisoLibrary:
    """The ``pardiso`` entry point of ``mkl_rt`` with its argument types."""

    def __init__(self, cdll: ctypes.CDLL) -> None:
        self.cdll = cdll
        self.path = getattr(cdll, "_name", "mkl_rt")
        int_p = ctypes.POINTER(ctypes.c_int32)
        function = cdll["pardiso"]      # a function object of our own (not pypardiso's)
        function.argtypes = [ctypes.POINTER(ctypes.c_int64),   # pt
                             int_p, int_p, int_p, int_p, int_p,  # maxfct mnum mtype phase n
                             ctypes.c_void_p,                    # a
                             int_p, int_p, int_p,                # ia ja perm
                             int_p, int_p, int_p,                # nrhs iparm msglvl
                             ctypes.c_void_p, ctypes.c_void_p,   # b x
                             int_p]                              # error
        function.restype = None
        self._function = function
        try:
            self._max_threads = cdll["mkl_get_max_threads"]
            self._max_threads.argtypes = []
            self._max_threads.restype = ctypes.c_int
        except (AttributeError, KeyError):  # pragma: no cover - every mkl_rt has it
            self._max_threads = None

    def max_threads(self) -> int:
        """MKL's current thread limit (``mkl_get_max_threads``; 0 when unknown)."""
        return int(self._max_threads()) if self._max_threads is not None else 0

    def call(self, pt: np.ndarray, maxfct: int, mnum: int, mtype: int, phase: int, n: int,
             a: np.ndarray, ia: np.ndarray, ja: np.ndarray, perm: np.ndarray, nrhs: int,
             iparm: np.ndarray, b: np.ndarray | None = None,
             x: np.ndarray | None = None) -> int:
        """One ``pardiso(...)`` call; returns PARDISO's error code (0: success)."""
        int_p = ctypes.POINTER(ctypes.c_int32)
        error = ctypes.c_int32(0)

        def ref(value: int) -> Any:
            return ctypes.byref(ctypes.c_int32(int(value)))

        self._function(pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)), ref(maxfct),
                       ref(mnum), ref(mtype), ref(phase), ref(n), a.ctypes.data,
                       ia.ctypes.data_as(int_p), ja.ctypes.data_as(int_p),
                       perm.ctypes.data_as(int_p), ref(nrhs), iparm.ctypes.data_as(int_p),
                       ref(0), None if b is None else b.ctypes.data,
                       None if x is None else x.ctypes.data, ctypes.byref(error))
        return int(error.value)


_LIBRARY: PardisoLibrary | None = None
_LIBRARY_ERROR: PardisoUnavailableError | None = None
_LOAD_LOCK = threading.Lock()


def load_pardiso() -> PardisoLibrary:
    """The MKL library (loaded once per process), or :class:`PardisoUnavailableError`.

    Loading applies the thread count of :func:`torchfit.linalg.set_threads`, if one was
    set, to MKL (threadpoolctl only limits the libraries already loaded).
    """
    global _LIBRARY, _LIBRARY_ERROR
    with _LOAD_LOCK:
        if _LIBRARY is not None:
            return _LIBRARY
        if _LIBRARY_ERROR is not None:
            raise _LIBRARY_ERROR
        try:
            import pypardiso  # noqa: F401  (type: ignore[import-not-found])
        except ImportError as err:
            _LIBRARY_ERROR = _unavailable(f"pypardiso is not installed: {err}")
            raise _LIBRARY_ERROR from None
        try:
            # pypardiso's constructor finds mkl_rt (and raises ImportError without it)
            cdll = pypardiso.PyPardisoSolver().libmkl
            library = PardisoLibrary(cdll)
        except (ImportError, OSError, AttributeError) as err:
            _LIBRARY_ERROR = _unavailable(f"the MKL runtime could not be loaded: {err}")
            raise _LIBRARY_ERROR from None
        _LIBRARY = library
    apply_requested_threads()
    return library


def pardiso_available() -> bool:
    """Whether :func:`load_pardiso` succeeds in this process."""
    try:
        load_pardiso()
    except PardisoUnavailableError:
        return False
    return True


def default_iparm(mtype: int) -> np.ndarray:
    """The ``iparm`` array of this module's settings (see the module docstring)."""
    iparm = np.zeros(64, dtype=np.int32)
    iparm[0] = 1            # no solver defaults: every value below is ours
    iparm[1] = 2            # METIS nested-dissection ordering
    iparm[7] = 0            # iterative refinement: only after perturbed pivots
    iparm[9] = 13           # perturb pivots below 1e-13 ||A||
    nonsymmetric = mtype == REAL_NONSYMMETRIC
    iparm[10] = 1 if nonsymmetric else 0   # scaling
    iparm[12] = 1 if nonsymmetric else 0   # weighted matching
    iparm[17] = -1          # report the number of nonzeros of the factor
    iparm[20] = 1           # Bunch-Kaufman pivoting (symmetric indefinite)
    iparm[26] = 0           # no matrix checker (the structure is built here)
    iparm[27] = 0           # double precision
    iparm[34] = 1           # zero-based ia/ja
    return iparm


class PardisoStructure:
    """The CSR structure PARDISO gets for one sparsity pattern (built once, host side).

    Symmetric matrix types take the upper triangle only; an entry stored only below the
    diagonal is moved to its mirror position (the matrix is symmetric). Every diagonal
    entry is present (PARDISO requires it; missing ones are explicit zeros), so that a
    structurally empty row is reported as a zero pivot instead of crashing MKL.

    Args:
        rows, cols: ``(nnz,)`` row and column of every stored value of the pattern
            (its CSR order).
        n: the matrix size.
        symmetric: upper triangle (symmetric types) or all entries.

    Attributes:
        ia: ``(n + 1,)`` int32 zero-based row pointer; ``ja``: int32 column indices.
        nnz: stored entries of the PARDISO matrix.
        perm: ``(n,)`` int32 scratch array (PARDISO's ``perm`` argument).
    """

    def __init__(self, rows: np.ndarray, cols: np.ndarray, n: int, symmetric: bool) -> None:
        rows = np.asarray(rows, dtype=np.int64)
        cols = np.asarray(cols, dtype=np.int64)
        if symmetric:
            rows, cols = np.minimum(rows, cols), np.maximum(rows, cols)
        diagonal = np.arange(n, dtype=np.int64)
        keys = np.concatenate([rows * n + cols, diagonal * n + diagonal])
        sources = np.concatenate([np.arange(rows.size, dtype=np.int64),
                                  -np.ones(n, dtype=np.int64)])
        # first occurrence of every position: a stored slot wins over an inserted zero
        unique, first = np.unique(keys, return_index=True)
        source = sources[first]
        row_of = unique // n
        if unique.size >= 2 ** 31:
            raise ValueError(f"matrix with {unique.size} entries is too large for 32-bit "
                             "PARDISO indices")
        crow = np.zeros(n + 1, dtype=np.int64)
        np.add.at(crow, row_of + 1, 1)
        np.cumsum(crow, out=crow)
        self.n = int(n)
        self.symmetric = bool(symmetric)
        self.nnz = int(unique.size)
        self.ia = crow.astype(np.int32)
        self.ja = (unique % n).astype(np.int32)
        self.perm = np.zeros(max(self.n, 1), dtype=np.int32)
        stored = source >= 0
        self._positions = np.nonzero(stored)[0]
        self._slots = source[stored]

    def gather(self, values: np.ndarray) -> np.ndarray:
        """PARDISO's value array (float64, ``(nnz,)``) from the pattern's CSR values."""
        a = np.zeros(self.nnz, dtype=np.float64)
        a[self._positions] = values[self._slots]
        return a


class _HandleState:
    """What the release of a handle needs (kept apart so that a finalizer can hold it)."""

    def __init__(self, library: PardisoLibrary, structure: PardisoStructure, mtype: int,
                 capacity: int) -> None:
        self.library = library
        self.structure = structure
        self.mtype = mtype
        self.capacity = capacity
        self.pt = np.zeros(64, dtype=np.int64)
        self.iparm = default_iparm(mtype)
        self.lock = threading.RLock()
        self.closed = False

    def call(self, phase: int, mnum: int = 1, a: np.ndarray | None = None, nrhs: int = 0,
             b: np.ndarray | None = None, x: np.ndarray | None = None,
             iparm: np.ndarray | None = None) -> int:
        s = self.structure
        values = a if a is not None else np.zeros(1)
        return self.library.call(self.pt, self.capacity, mnum, self.mtype, phase, s.n, values,
                                 s.ia, s.ja, s.perm, nrhs,
                                 self.iparm if iparm is None else iparm, b, x)

    def release_all(self) -> None:
        with self.lock:
            if not self.closed:
                self.closed = True
                self.call(-1)


class PardisoHandle:
    """One PARDISO handle: the analysis (phase 11) of one structure and up to
    ``capacity`` numeric factorisations with it (``maxfct = capacity``, one ``mnum`` slot
    per factor). A larger ``capacity`` costs nothing until a slot is factorised (measured:
    phase 11 and memory are the same for ``maxfct`` 1 and 1024).

    Args:
        library: :func:`load_pardiso`.
        structure: the host structure.
        mtype: PARDISO matrix type.
        capacity: factor slots.
        values: ``(nnz,)`` PARDISO values read by the analysis (scaling and matching of
            nonsymmetric matrices; symmetric analyses only read the structure).

    The handle's memory is released (phase -1) when the handle is garbage collected
    (factors keep their handle alive); a slot's factor memory (phase 0) when its slot is
    released.

    ``threads`` is MKL's thread limit at the analysis. A numeric factorisation under a
    lower limit than the analysis had crashes MKL (a segmentation fault, measured with
    MKL 2025 on the arm: analysis with 2 threads, factorisation with 1), so
    :class:`~torchfit.linalg.backends.pardiso.PardisoPlan` factorises only into handles analysed
    under the current limit. Solves with existing factors are safe under any limit.
    """

    def __init__(self, library: PardisoLibrary, structure: PardisoStructure, mtype: int,
                 capacity: int, values: np.ndarray) -> None:
        if capacity < 1:
            raise ValueError(f"a PARDISO handle needs at least one factor slot, got {capacity}")
        self._state = _HandleState(library, structure, mtype, int(capacity))
        self._free = list(range(int(capacity), 0, -1))    # pop() hands out 1, 2, ...
        self._finalizer = weakref.finalize(self, self._state.release_all)
        self._finalizer.atexit = False     # the OS takes the memory at exit; no MKL call then
        self.threads = library.max_threads()
        with self._state.lock:
            error = self._state.call(11, a=values)
        if error:
            self._finalizer()
            raise PardisoError(error, 11)

    @property
    def mtype(self) -> int:
        return self._state.mtype

    @property
    def capacity(self) -> int:
        return self._state.capacity

    @property
    def free_slots(self) -> int:
        return len(self._free)

    def acquire(self) -> int | None:
        """A free slot number (``mnum``), or ``None`` when every slot holds a factor."""
        with self._state.lock:
            return self._free.pop() if self._free else None

    def factorize(self, mnum: int, a: np.ndarray) -> dict[str, int]:
        """Numeric factorisation (phase 22) of ``a`` into slot ``mnum``.

        Returns PARDISO's report: ``error`` (0 on success), ``perturbed_pivots``,
        ``positive``/``negative`` eigenvalues (symmetric indefinite), ``factor_nnz`` and
        ``pivot_row`` (where a Cholesky found a non-positive pivot).
        """
        state = self._state
        with state.lock:
            iparm = state.iparm.copy()
            error = state.call(22, mnum, a, iparm=iparm)
        return {"error": error, "perturbed_pivots": int(iparm[13]),
                "positive": int(iparm[21]), "negative": int(iparm[22]),
                "factor_nnz": int(iparm[17]), "pivot_row": int(iparm[29])}

    def solve(self, mnum: int, a: np.ndarray, b: np.ndarray, transpose: bool = False) -> np.ndarray:
        """Phase 33 with the factor in slot ``mnum``: ``x`` with ``A x = b`` (``A^T x = b``).

        ``b`` is ``(n,)`` or ``(n, k)`` (any layout; PARDISO reads columns); returns
        ``x`` of the same shape, C-contiguous.
        """
        state = self._state
        columns = np.asfortranarray(b, dtype=np.float64)
        nrhs = 1 if columns.ndim == 1 else columns.shape[1]
        x = np.zeros_like(columns, order="F")
        if nrhs == 0:
            return np.ascontiguousarray(x)
        with state.lock:
            iparm = state.iparm.copy()
            iparm[11] = 2 if transpose else 0
            error = state.call(33, mnum, a, nrhs, columns, x, iparm=iparm)
        if error:
            raise PardisoError(error, 33)
        return np.ascontiguousarray(x)

    def release(self, mnum: int) -> None:
        """Free the factor memory of slot ``mnum`` (phase 0) and make the slot free."""
        state = self._state
        with state.lock:
            if state.closed:
                return
            state.call(0, mnum)
            self._free.append(mnum)

    def close(self) -> None:
        """Release everything now (phase -1); the handle is unusable afterwards."""
        self._finalizer()


__all__ = ["ERROR_TEXT", "PARDISO_EXTRA", "PardisoError", "PardisoHandle", "PardisoLibrary",
           "PardisoStructure", "PardisoUnavailableError", "REAL_NONSYMMETRIC", "REAL_SPD",
           "REAL_SYMMETRIC_INDEFINITE", "SINGULAR_CODES", "default_iparm", "load_pardiso",
           "pardiso_available"]
