"""cuDSS (NVIDIA's sparse direct solver on CUDA) through nvmath-python: the ``cudss`` backend.

``nvmath.sparse.advanced.DirectSolver`` (nvmath-python 1.0, the optional extra
``torchfit[cuda]``) on torch CSR tensors on the GPU.

**One analysis per pattern.** Every frame and every Newton step of a body share one
sparsity pattern, and the analysis (``plan()``: reordering and symbolic factorisation) is
the expensive step of cuDSS (seconds at a million dofs). A pattern keeps one
:class:`CudssPlan` per matrix kind: the CSR structure as int32 tensors on the device
(cuDSS takes int32 indices) and ``resident`` *slots* (default 1), each a ``DirectSolver``
with its own value buffer and right-hand-side buffer, planned once when it is made. A
numeric factorisation copies a matrix's values into a slot's buffer **in place** and calls
``factorize()`` again: the plan stays valid (a new tensor through ``reset_operands`` would
force a new one). A slot holds the numeric factor of one matrix at a time, so a
:class:`CudssFactor` is the matrix's values (a copy, ``nnz`` numbers on the device) plus
the slot it was last factorised in: it is factorised **when first solved** (so Newton's
round of "factorise every frame, then solve every frame" factorises each frame once), and
factorised again, in the least recently used slot, when it is solved after other factors
took the slots. So ``F`` frames cost one analysis and the factor memory of ``resident``
matrices, for one extra numeric factorisation per frame and pass when a pass over the
frames (the adjoint, the Jacobian) follows another; every numeric factorisation,
first or again, is counted (``count_factorization``), every analysis too
(``count_analysis``). ``CudssBackend(resident=R)`` keeps ``R`` factors at once for ``R``
analyses.

**The device of the calling thread.** nvmath runs its calls through ``cuda.core``, which
needs the device made current in the *calling* thread (``Device(i).set_current()``).
Autograd runs a CUDA backward on a thread of its own, and a torchrun worker uses its own
device, so every call into nvmath (``DirectSolver``, ``plan``, ``factorize``, ``solve``,
``free``, also from a garbage collector's finaliser) is preceded by making the factor's
device current in the thread making it (:meth:`CudssRuntime.make_current`).

**The seam.** Everything the backend uses of nvmath and CUDA is a :class:`CudssRuntime`:
``advanced`` (the ``nvmath.sparse.advanced`` module: ``DirectSolver``,
``DirectSolverOptions``, ``DirectSolverMatrixType``), ``device_type`` (where its tensors
live) and ``make_current``. :class:`NvmathRuntime` is the real one (nvmath-python and
``cuda.core``); tests pass a stand-in to ``CudssBackend(runtime=...)`` that runs on the
CPU and refuses a call from a thread where no device was made current.

Solves (:meth:`CudssFactor.solve`) take ``(n,)`` or ``(n, k)`` right-hand sides on the
device. The RHS buffer of a slot has ``rhs_block`` columns (column-major, as cuDSS wants;
nvmath refuses an RHS of another shape than the planned one, so it is fixed per plan):
``k`` columns are solved ``rhs_block`` at a time, the last block zero-padded. By default
``rhs_block`` is chosen per pattern so that one block of right-hand sides holds about
:data:`RHS_BLOCK_BYTES` (between 1 and :data:`MAX_RHS_BLOCK` columns): the arm's 192
Jacobian columns of a frame in 3 or 4 cuDSS calls, a few columns per call for a
million-dof body. One call of ``solve`` is one counted solve (``rhs_columns += k``), as
for the CPU backends.

Matrix types: a symmetric matrix is factorised as SPD (Cholesky, cuDSS's fastest). A
non-positive pivot (cuDSS's ``info > 0``) means it is not positive definite: a Newton
tangent far from equilibrium may be indefinite, as on the CPU, where PARDISO factorises
symmetric matrices as indefinite, so the matrix is then factorised as symmetric
indefinite (``LDL^T`` with pivoting, a plan of its own, counted once; the factor stays
indefinite when factorised again); with ``CudssBackend(indefinite=False)`` it is a
:class:`SingularMatrixError` saying that the matrix is not positive definite instead.
Nonsymmetric matrices get cuDSS's general LU (solves of ``A x = b``; a transposed solve is
refused: no model of torchfit has a nonsymmetric tangent). Running out of GPU memory
(planning is the largest allocation) is a :class:`GpuMemoryError` naming the matrix size
and what to lower. cuDSS plans much faster with its multithreading layer: nvmath-python
loads it from ``CUDSS_THREADING_LIB`` (``.../nvidia/cu13/lib/libcudss_mtlayer_gomp.so.0``)
when set.

``tests/linalg/backends/test_cudss.py`` runs it where CUDA and nvmath are present and, with
a stand-in runtime (``tests/helpers/fake_nvmath.py``), everywhere. Its history and costs:
``docs/notes/gpu.md``; how to run it: ``docs/guide/gpu.md``.
"""
from __future__ import annotations

import dataclasses
import threading
import weakref
from typing import Any, Protocol

import torch
from torch import Tensor

from ..counters import count_analysis, count_factorization, count_solve
from ..errors import SingularMatrixError
from ..pattern import SparsePattern, csr_matrix

#: how the optional dependency is installed (named by every "not installed" error)
CUDA_EXTRA = "pip install 'torchfit[cuda]'"
#: cuDSS matrix types used: Cholesky, symmetric indefinite LDL^T, general LU
MATRIX_KINDS = ("spd", "symmetric", "general")
#: about this many bytes of right-hand sides per cuDSS solve call when ``rhs_block`` is
#: chosen per pattern (``CudssBackend(rhs_block=None)``, the default)
RHS_BLOCK_BYTES = 64 * 2 ** 20
#: the most right-hand-side columns per cuDSS solve call when chosen per pattern
MAX_RHS_BLOCK = 64


class CudssUnavailableError(ImportError):
    """cuDSS cannot be used here (no CUDA, or nvmath-python / the cuDSS library missing)."""


class GpuMemoryError(MemoryError):
    """The GPU ran out of memory; the message names the problem size and what to lower."""


def gpu_memory_error(what: str, size: str, err: BaseException) -> GpuMemoryError:
    """One-line :class:`GpuMemoryError` for ``what`` (an operation) on ``size``."""
    first_line = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    return GpuMemoryError(
        f"out of GPU memory during {what} ({size}): lower the problem size (mesh "
        "resolution, frames solved at once) or use problem.backend=cg, which needs no "
        f"factor; CUDA said: {first_line}")


def _is_out_of_memory(err: BaseException) -> bool:
    if isinstance(err, torch.cuda.OutOfMemoryError):
        return True
    text = str(err).upper()
    return "OUT OF MEMORY" in text or "ALLOC_FAILED" in text or "OUT_OF_MEMORY" in text


_NVMATH: Any = None
_NVMATH_ERROR: CudssUnavailableError | None = None
_LOCK = threading.Lock()


def _unavailable(reason: str) -> CudssUnavailableError:
    return CudssUnavailableError(
        f"the 'cudss' backend needs CUDA and nvmath-python with cuDSS ({reason}): "
        f"{CUDA_EXTRA}, or use backend='cg'")


def load_nvmath() -> Any:
    """``nvmath.sparse.advanced`` (imported once per process), or
    :class:`CudssUnavailableError` (one line naming the extra)."""
    global _NVMATH, _NVMATH_ERROR
    with _LOCK:
        if _NVMATH is not None:
            return _NVMATH
        if _NVMATH_ERROR is not None:
            raise _NVMATH_ERROR
        if not torch.cuda.is_available():
            _NVMATH_ERROR = _unavailable("torch sees no CUDA device here")
            raise _NVMATH_ERROR
        try:
            import nvmath.sparse.advanced as advanced  # type: ignore[import-not-found]
            from nvmath.bindings import cudss  # noqa: F401  (loads libcudss)  # type: ignore[import-not-found]
        except (ImportError, OSError, RuntimeError) as err:
            _NVMATH_ERROR = _unavailable(f"{type(err).__name__}: {err}".splitlines()[0])
            raise _NVMATH_ERROR from None
        _NVMATH = advanced
        return advanced


def cudss_available() -> bool:
    """Whether :func:`load_nvmath` succeeds in this process (never raises)."""
    try:
        load_nvmath()
    except CudssUnavailableError:
        return False
    return True


class CudssRuntime(Protocol):
    """What :class:`CudssBackend` uses of nvmath-python and CUDA (its seam).

    Attributes:
        advanced: the ``nvmath.sparse.advanced`` module (or a stand-in with the same
            ``DirectSolver``, ``DirectSolverOptions`` and ``DirectSolverMatrixType``).
        device_type: the device type of the tensors it factorises (``'cuda'``).
    """

    advanced: Any
    device_type: str

    def make_current(self, device: torch.device) -> None:
        """Make ``device`` the current device of the calling thread for nvmath's calls."""


def _device_class() -> Any:
    """``cuda.core``'s ``Device`` (``cuda.core`` >= 0.4, else ``cuda.core.experimental``)."""
    try:
        from cuda.core import Device  # type: ignore[import-not-found]
    except ImportError:
        try:
            from cuda.core.experimental import Device  # type: ignore[import-not-found]
        except ImportError as err:
            raise _unavailable(f"cuda.core is missing: {err}".splitlines()[0]) from None
    return Device


class NvmathRuntime:
    """The real :class:`CudssRuntime`: nvmath-python and ``cuda.core``.

    Args:
        advanced: ``nvmath.sparse.advanced`` (default: :func:`load_nvmath`).
        device_class: ``cuda.core``'s ``Device`` (default: imported on first use).
    """

    device_type = "cuda"

    def __init__(self, advanced: Any = None, device_class: Any = None) -> None:
        self.advanced = load_nvmath() if advanced is None else advanced
        self._device_class = device_class

    def make_current(self, device: torch.device) -> None:
        """``Device(index).set_current()`` in the calling thread: cuda.core keeps the current
        device per thread, and autograd's device thread or a torchrun worker starts with
        none (nvmath then fails with "Device 0 is not yet initialized")."""
        if self._device_class is None:
            self._device_class = _device_class()
        index = device.index if device.index is not None else torch.cuda.current_device()
        self._device_class(int(index)).set_current()


def default_runtime() -> NvmathRuntime:
    """nvmath-python's runtime (:class:`CudssUnavailableError` where it cannot run)."""
    return NvmathRuntime()


def rhs_block_for(n: int, itemsize: int) -> int:
    """Right-hand-side columns per cuDSS solve call for ``n`` unknowns of ``itemsize``
    bytes: about :data:`RHS_BLOCK_BYTES` of columns, between 1 and :data:`MAX_RHS_BLOCK`."""
    return int(max(1, min(MAX_RHS_BLOCK, RHS_BLOCK_BYTES // max(1, n * itemsize))))


class _Slot:
    """One ``DirectSolver``: a value buffer, a column-major RHS buffer, planned once; it
    holds the numeric factor of one :class:`CudssFactor` at a time (``holder``)."""

    def __init__(self, plan: "CudssPlan") -> None:
        advanced = plan.runtime.advanced
        self.matrix = csr_matrix(plan.crow, plan.col, torch.zeros(
            plan.nnz, dtype=plan.dtype, device=plan.device), (plan.n, plan.n))
        self.values = self.matrix.values()      # the matrix's own buffer: updated in place
        # column-major (n, block): the transpose of a contiguous (block, n)
        self.rhs = torch.zeros(plan.rhs_block, plan.n, dtype=plan.dtype, device=plan.device).T
        kind = {"spd": advanced.DirectSolverMatrixType.SPD,
                "symmetric": advanced.DirectSolverMatrixType.SYMMETRIC,
                "general": advanced.DirectSolverMatrixType.GENERAL}[plan.kind]
        options = advanced.DirectSolverOptions(sparse_system_type=kind)
        plan.runtime.make_current(plan.device)
        self.solver = advanced.DirectSolver(self.matrix, self.rhs, options=options)
        plan.runtime.make_current(plan.device)
        self.solver.plan()
        self.holder: "weakref.ref[CudssFactor] | None" = None
        self.used = 0            # the plan's clock at the last use (least recently used)


def _free_slots(runtime: CudssRuntime, device: torch.device, slots: list[_Slot]) -> None:
    """Release the ``DirectSolver`` of every slot (a plan's finaliser: any thread)."""
    for slot in slots:
        runtime.make_current(device)
        slot.solver.free()
    slots.clear()


class CudssPlan:
    """One pattern's analysis for one matrix kind (``'spd'``, ``'symmetric'``,
    ``'general'``) on one device and dtype: the int32 CSR structure and up to
    ``resident`` slots (each planned once).

    Attributes:
        analyses: ``plan()`` calls made for this pattern and kind (one per slot made).
        factorizations: numeric factorisations made in its slots, first or again.
        refactorizations: of those, the ones of a factor that had been factorised before
            and lost its slot to another.
        rejected: numeric factorisations cuDSS refused (a zero or, for ``'spd'``, a
            non-positive pivot: the matrix then goes to the ``'symmetric'`` plan).
    """

    def __init__(self, pattern: SparsePattern, kind: str, device: torch.device,
                 dtype: torch.dtype, rhs_block: int, resident: int,
                 runtime: CudssRuntime) -> None:
        n = pattern.shape[0]
        if pattern.shape[0] != pattern.shape[1]:
            raise ValueError(f"cuDSS needs a square matrix, got {pattern.shape}")
        if pattern.nnz >= 2 ** 31:
            raise ValueError(f"matrix with {pattern.nnz} stored entries is too large for "
                             "cuDSS's 32-bit indices")
        if kind not in MATRIX_KINDS:
            raise ValueError(f"unknown cuDSS matrix kind {kind!r}; one of {MATRIX_KINDS}")
        self.n, self.nnz = n, pattern.nnz
        self.kind = kind
        self.symmetric = kind != "general"
        self.device, self.dtype = device, dtype
        self.rhs_block = int(rhs_block)
        self.resident = int(resident)
        self.runtime = runtime
        self.crow = pattern.crow_indices.to(device=device, dtype=torch.int32)
        self.col = pattern.col_indices.to(device=device, dtype=torch.int32)
        self.slots: list[_Slot] = []
        # a slot's solver is freed (on whatever thread collects the plan) with the plan
        weakref.finalize(self, _free_slots, runtime, device, self.slots).atexit = False
        # held while a slot is chosen, factorised and solved with: another thread (autograd's)
        # must not take the slot in between
        self.lock = threading.RLock()
        self.clock = 0
        self.analyses = 0
        self.factorizations = 0
        self.refactorizations = 0
        self.rejected = 0

    def size(self) -> str:
        return f"a {self.n:,} x {self.n:,} sparse matrix with {self.nnz:,} stored entries"

    def slot_of(self, factor: "CudssFactor") -> _Slot | None:
        """``factor``'s numeric factorisation: the slot holding it, factorising it (again)
        in the least recently used slot if none does; ``None`` when cuDSS reports a zero
        or (Cholesky) non-positive pivot. Call with :attr:`lock` held."""
        self.clock += 1
        for slot in self.slots:
            if slot.holder is not None and slot.holder() is factor:
                slot.used = self.clock
                return slot
        slot = self._free_slot()
        slot.holder = None
        try:
            slot.values.copy_(factor.values)       # in place: the plan stays valid
            self.runtime.make_current(self.device)
            info = int(slot.solver.factorize().info)
        except Exception as err:  # noqa: BLE001 - nvmath/cuDSS raise their own types
            if _is_out_of_memory(err):
                raise gpu_memory_error("the cuDSS factorisation", self.size(), err) from None
            raise
        if info != 0:
            self.rejected += 1
            return None
        self.factorizations += 1
        if factor.factorized:
            self.refactorizations += 1
        count_factorization()
        slot.holder = weakref.ref(factor)
        slot.used = self.clock
        return slot

    def _free_slot(self) -> _Slot:
        """An empty slot, a new one (planned now) while fewer than ``resident`` exist, else
        the least recently used."""
        for slot in self.slots:
            if slot.holder is None or slot.holder() is None:
                return slot
        if len(self.slots) < self.resident:
            try:
                slot = _Slot(self)
            except Exception as err:  # noqa: BLE001 - nvmath/cuDSS raise their own types
                if _is_out_of_memory(err):
                    raise gpu_memory_error("cuDSS planning (reordering, symbolic "
                                           "factorisation)", self.size(), err) from None
                raise
            self.analyses += 1
            count_analysis()
            self.slots.append(slot)
            return slot
        return min(self.slots, key=lambda s: s.used)


#: pattern -> {(kind, device, dtype, rhs_block, resident, id of nvmath): plan}; the plans
#: live as long as the pattern (every equilibrium makes a backend of its own)
_PLANS: "weakref.WeakKeyDictionary[SparsePattern, dict[tuple, CudssPlan]]" = \
    weakref.WeakKeyDictionary()


class CudssFactor:
    """A matrix to solve with cuDSS: its CSR values (a copy on the device) and the kind it
    is factorised as; the numeric factorisation is made in a slot of its pattern's plan at
    the first solve and again whenever another factor took the slot.

    ``solve(rhs)`` for ``rhs`` ``(n,)`` or ``(n, k)`` on the factor's device returns ``x``
    of the same shape (one counted solve, ``k`` columns). ``transpose=True`` is the same
    solve for a symmetric matrix and refused for a nonsymmetric one.
    """

    def __init__(self, backend: "CudssBackend", pattern: SparsePattern, values: Tensor,
                 kind: str) -> None:
        self._backend = backend
        self._pattern = pattern
        self.values = values
        self.kind = kind
        self.factorized = False
        self._plan = backend.plan(pattern, kind, values.device, values.dtype)

    @property
    def info(self) -> dict[str, Any]:
        """The kind it is factorised as and whether it has been yet."""
        return {"kind": self.kind, "factorized": self.factorized}

    @property
    def plan(self) -> CudssPlan:
        return self._plan

    def _slot(self) -> _Slot:
        """The slot holding this factor's numeric factorisation (made now if needed), the
        plan's lock held by the caller; the SPD attempt falls back to ``LDL^T``."""
        slot = self._plan.slot_of(self)
        if slot is None and self.kind == "spd" and self._backend.indefinite:
            self.kind = "symmetric"
            self._plan = self._backend.plan(self._pattern, self.kind, self.values.device,
                                            self.values.dtype)
            with self._plan.lock:
                slot = self._plan.slot_of(self)
        if slot is None:
            what = {"spd": "not positive definite", "symmetric": "singular",
                    "general": "singular"}[self.kind]
            raise SingularMatrixError(
                f"cuDSS factorisation failed (zero or negative pivot): the matrix is {what}; "
                "check that every connected part of the model has a Dirichlet (fixed) node "
                "and that all stiffnesses are positive")
        self.factorized = True
        return slot

    def solve(self, rhs: Tensor, transpose: bool = False) -> Tensor:
        plan = self._plan
        if rhs.device != plan.device:
            raise ValueError(f"the cudss factor lives on {plan.device}; the right-hand side "
                             f"is on {rhs.device}")
        if transpose and not plan.symmetric:
            raise NotImplementedError("the cudss backend solves A x = b only for a "
                                      "nonsymmetric matrix (no transposed solve); use a "
                                      "symmetric model or backend='cg'")
        if rhs.shape[0] != plan.n or rhs.dim() > 2:
            raise ValueError(f"rhs must be ({plan.n},) or ({plan.n}, k), got {tuple(rhs.shape)}")
        columns = rhs.detach().reshape(plan.n, -1).to(plan.dtype)
        k = columns.shape[1]
        count_solve(k)
        out = torch.empty_like(columns)
        with plan.lock:
            slot = self._slot()
            plan = self._plan                      # the indefinite one after a fallback
            block = plan.rhs_block
            buffer = slot.rhs
            try:
                for start in range(0, k, block):
                    stop = min(start + block, k)
                    buffer.zero_()
                    buffer[:, : stop - start] = columns[:, start:stop]
                    plan.runtime.make_current(plan.device)
                    x = slot.solver.solve()
                    out[:, start:stop] = torch.as_tensor(x, device=plan.device)[:, : stop - start]
            except Exception as err:  # noqa: BLE001
                if _is_out_of_memory(err):
                    raise gpu_memory_error("a cuDSS solve", plan.size(), err) from None
                raise
        if not bool(torch.isfinite(out).all()):
            raise SingularMatrixError("the cuDSS solve produced NaN or infinite values: the "
                                      "matrix is singular or not positive definite")
        return out.reshape(rhs.shape).to(rhs.dtype)


@dataclasses.dataclass
class CudssBackend:
    """cuDSS on CUDA (``torchfit[cuda]``): one analysis per pattern and matrix kind, the
    numeric factorisation in place at a factor's first solve (and again when it lost its
    slot), solves in blocks of right-hand sides.

    Args:
        rhs_block: right-hand sides solved per cuDSS call (the RHS buffer's columns);
            ``None``: :func:`rhs_block_for` the pattern (about :data:`RHS_BLOCK_BYTES`).
        indefinite: a symmetric matrix that is not positive definite is factorised as
            symmetric indefinite (the default, as PARDISO on the CPU); ``False``: it is a
            :class:`SingularMatrixError` naming it.
        resident: numeric factors a pattern keeps at once (each slot an analysis of its
            own); 1 makes one analysis serve every frame and Newton step.
        runtime: nvmath-python and CUDA (:class:`CudssRuntime`); default
            :class:`NvmathRuntime`, a stand-in in tests.

    Raises :class:`CudssUnavailableError` (an ``ImportError`` naming
    ``pip install 'torchfit[cuda]'``) when CUDA, nvmath-python or cuDSS is missing.
    """

    rhs_block: int | None = None
    indefinite: bool = True
    resident: int = 1
    runtime: Any = dataclasses.field(default=None, repr=False, compare=False)
    name: str = "cudss"

    def __post_init__(self) -> None:
        if self.runtime is None:
            self.runtime = default_runtime()
        if self.rhs_block is not None and self.rhs_block < 1:
            raise ValueError(f"rhs_block must be >= 1, got {self.rhs_block}")
        if self.resident < 1:
            raise ValueError(f"resident must be >= 1, got {self.resident}")

    def plan(self, pattern: SparsePattern, kind: str, device: torch.device,
             dtype: torch.dtype) -> CudssPlan:
        """The plan of ``pattern`` for this matrix kind (``'spd'``, ``'symmetric'``,
        ``'general'``), device and dtype (made once, kept with the pattern, shared by every
        backend with the same settings and nvmath)."""
        itemsize = torch.empty(0, dtype=dtype).element_size()
        block = self.rhs_block or rhs_block_for(pattern.shape[0], itemsize)
        # the plan keeps its runtime: the id of its nvmath stays that nvmath's
        key = (kind, device, dtype, block, self.resident, id(self.runtime.advanced))
        with _LOCK:
            plans = _PLANS.get(pattern)
            if plans is None:
                plans = _PLANS[pattern] = {}
            if key not in plans:
                plans[key] = CudssPlan(pattern, kind, device, dtype, block, self.resident,
                                       self.runtime)
            return plans[key]

    def factorize(self, pattern: SparsePattern, values: Tensor, symmetric: bool) -> CudssFactor:
        """A :class:`CudssFactor` of ``values`` ``(nnz,)``: checked and copied now, the
        numeric factorisation made (and counted) at its first solve."""
        device_type = self.runtime.device_type
        if values.device.type != device_type:
            raise ValueError(f"the cudss backend runs on {device_type.upper()}, but the "
                             f"tensors are on {values.device}: use backend='scipy' or "
                             "'pardiso' on the CPU")
        if values.dtype not in (torch.float32, torch.float64):
            raise ValueError(f"the cudss backend takes float32 or float64 values, got {values.dtype}")
        if values.shape != (pattern.nnz,):
            raise ValueError(f"values must have shape ({pattern.nnz},), got {tuple(values.shape)}")
        if not bool(torch.isfinite(values).all()):
            raise SingularMatrixError("system matrix has NaN or infinite entries")
        return CudssFactor(self, pattern, values.detach().clone(),
                           "spd" if symmetric else "general")


__all__ = ["CUDA_EXTRA", "CudssBackend", "CudssFactor", "CudssPlan", "CudssRuntime",
           "CudssUnavailableError", "GpuMemoryError", "MATRIX_KINDS", "MAX_RHS_BLOCK",
           "NvmathRuntime", "RHS_BLOCK_BYTES", "cudss_available", "default_runtime",
           "gpu_memory_error", "load_nvmath", "rhs_block_for"]
