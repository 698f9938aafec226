"""cuDSS (NVIDIA's sparse direct solver on CUDA) through nvmath-python: the ``cudss`` backend.

``nvmath.sparse.advanced.DirectSolver`` (nvmath-python 1.0, the optional extra
``torchfit[cuda]``) on torch CSR tensors on the GPU. What one sparsity pattern keeps
(:class:`CudssPlan`, made on first use and kept as long as the pattern lives):

* the CSR structure as int32 tensors on the device (cuDSS takes int32 indices);
* *slots*: a ``DirectSolver`` each, with its own value buffer and right-hand-side buffer,
  planned once (``plan()``: reordering and symbolic factorisation, the expensive step).
  A numeric factorisation copies the new CSR values
  into a free slot's buffer **in place** and calls ``factorize()`` again: the slot's plan
  is reused (passing a new tensor through ``reset_operands`` would force a new plan).
  A factor holds its slot until it is garbage collected, when the slot (and its plan)
  goes back to the pattern for the next factorisation. A linear problem therefore plans
  once or twice (the factor cache keeps two), a non-linear one once per frame whose
  factor is alive at the same time: after the first Newton iteration every
  factorisation of that pattern is numeric only.

Solves (:meth:`CudssFactor.solve`) take ``(n,)`` or ``(n, k)`` right-hand sides on the
device. The RHS buffer of a slot has ``rhs_block`` columns (column-major, as cuDSS
wants; nvmath checks that the RHS shape never changes, so it is fixed per slot): ``k``
columns are solved ``rhs_block`` at a time, the last block zero-padded. One call is one
counted solve (``rhs_columns += k``), as for the CPU backends.

Matrix types: a symmetric matrix is factorised as SPD (Cholesky, cuDSS's fastest). A
non-positive pivot (cuDSS's ``info > 0``) means it is not positive definite: a Newton
tangent far from equilibrium may be indefinite, as on the CPU, where PARDISO factorises
symmetric matrices as indefinite, so the matrix is then factorised as symmetric
indefinite (``LDL^T`` with pivoting, a plan of its own; counted once); with
``CudssBackend(indefinite=False)`` it is a :class:`SingularMatrixError` saying that the
matrix is not positive definite instead. Nonsymmetric matrices
get cuDSS's general LU (solves of ``A x = b``; a transposed solve is refused: no model
of torchfit has a nonsymmetric tangent). Running out of GPU memory (planning is the
largest allocation) is a :class:`GpuMemoryError` naming the matrix size and what to lower.
cuDSS plans much faster with its multithreading layer: nvmath-python loads it from
``CUDSS_THREADING_LIB`` (``.../nvidia/cu13/lib/libcudss_mtlayer_gomp.so.0``) when set.

``tests/linalg/test_cudss.py`` runs it where CUDA and nvmath are present; its error
paths are tested everywhere. Its history and costs: ``docs/notes/gpu.md``.
"""
from __future__ import annotations

import dataclasses
import threading
import weakref
from typing import Any

import torch
from torch import Tensor

from ..counters import count_factorization, count_solve
from ..errors import SingularMatrixError
from ..pattern import SparsePattern

#: how the optional dependency is installed (named by every "not installed" error)
CUDA_EXTRA = "pip install 'torchfit[cuda]'"
#: cuDSS matrix types used: Cholesky, symmetric indefinite LDL^T, general LU
MATRIX_KINDS = ("spd", "symmetric", "general")


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


class _Slot:
    """One ``DirectSolver``: a value buffer, a column-major RHS buffer, planned once."""

    def __init__(self, plan: "CudssPlan") -> None:
        advanced = load_nvmath()
        self.matrix = torch.sparse_csr_tensor(
            plan.crow, plan.col, torch.zeros(plan.nnz, dtype=plan.dtype, device=plan.device),
            size=(plan.n, plan.n), check_invariants=False)
        self.values = self.matrix.values()      # the matrix's own buffer: updated in place
        # column-major (n, block): the transpose of a contiguous (block, n)
        self.rhs = torch.zeros(plan.rhs_block, plan.n, dtype=plan.dtype, device=plan.device).T
        kind = {"spd": advanced.DirectSolverMatrixType.SPD,
                "symmetric": advanced.DirectSolverMatrixType.SYMMETRIC,
                "general": advanced.DirectSolverMatrixType.GENERAL}[plan.kind]
        options = advanced.DirectSolverOptions(sparse_system_type=kind)
        self.solver = advanced.DirectSolver(self.matrix, self.rhs, options=options)
        self.solver.plan()

    def free(self) -> None:
        self.solver.free()


class CudssPlan:
    """Everything one (pattern, matrix type, device, dtype) keeps for cuDSS.

    Attributes:
        analyses: ``plan()`` calls made for this pattern so far (one per slot ever made).
        slots_in_use: slots held by live factors.
    """

    def __init__(self, pattern: SparsePattern, kind: str, device: torch.device,
                 dtype: torch.dtype, rhs_block: int) -> None:
        n = pattern.shape[0]
        if pattern.shape[0] != pattern.shape[1]:
            raise ValueError(f"cuDSS needs a square matrix, got {pattern.shape}")
        if pattern.nnz >= 2 ** 31:
            raise ValueError(f"matrix with {pattern.nnz} stored entries is too large for "
                             "cuDSS's 32-bit indices")
        self.n, self.nnz = n, pattern.nnz
        if kind not in MATRIX_KINDS:
            raise ValueError(f"unknown cuDSS matrix kind {kind!r}; one of {MATRIX_KINDS}")
        self.kind = kind
        self.symmetric = kind != "general"
        self.device, self.dtype = device, dtype
        self.rhs_block = int(rhs_block)
        self.crow = pattern.crow_indices.to(device=device, dtype=torch.int32)
        self.col = pattern.col_indices.to(device=device, dtype=torch.int32)
        self._free: list[_Slot] = []
        self._lock = threading.Lock()
        self.analyses = 0
        self.slots_in_use = 0

    def size(self) -> str:
        return f"a {self.n:,} x {self.n:,} sparse matrix with {self.nnz:,} stored entries"

    def acquire(self) -> _Slot:
        """A free slot (its plan made), planning a new one if all are held."""
        with self._lock:
            if self._free:
                self.slots_in_use += 1
                return self._free.pop()
        try:
            slot = _Slot(self)
        except Exception as err:  # noqa: BLE001 - nvmath/cuDSS raise their own types
            if _is_out_of_memory(err):
                raise gpu_memory_error("cuDSS planning (reordering, symbolic factorisation)",
                                       self.size(), err) from None
            raise
        with self._lock:
            self.analyses += 1
            self.slots_in_use += 1
        return slot

    def release(self, slot: _Slot) -> None:
        with self._lock:
            self.slots_in_use -= 1
            self._free.append(slot)


#: pattern -> {(symmetric, device, dtype): plan}; the plans live as long as the pattern
_PLANS: "weakref.WeakKeyDictionary[SparsePattern, dict[tuple, CudssPlan]]" = \
    weakref.WeakKeyDictionary()


class CudssFactor:
    """A numeric cuDSS factorisation held in a slot of a :class:`CudssPlan`.

    ``solve(rhs)`` for ``rhs`` ``(n,)`` or ``(n, k)`` on the factor's device returns ``x``
    of the same shape (one counted solve, ``k`` columns). ``transpose=True`` is the same
    solve for a symmetric matrix and refused for a nonsymmetric one.
    """

    def __init__(self, plan: CudssPlan, slot: _Slot, info: dict[str, Any]) -> None:
        self._plan = plan
        self._slot = slot
        self.info = info
        self._finalizer = weakref.finalize(self, plan.release, slot)
        self._finalizer.atexit = False

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
        block = plan.rhs_block
        buffer = self._slot.rhs
        try:
            for start in range(0, k, block):
                stop = min(start + block, k)
                buffer.zero_()
                buffer[:, : stop - start] = columns[:, start:stop]
                x = self._slot.solver.solve()
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
    """cuDSS on CUDA (``torchfit[cuda]``): analysis once per pattern slot, numeric
    factorisation in place per matrix, batched solves with the stored factor.

    Args:
        rhs_block: right-hand sides solved per cuDSS call (the RHS buffer's columns).
        indefinite: a symmetric matrix that is not positive definite is factorised as
            symmetric indefinite (the default, as PARDISO on the CPU); ``False``: it is a
            :class:`SingularMatrixError` naming it.

    Raises :class:`CudssUnavailableError` (an ``ImportError`` naming
    ``pip install 'torchfit[cuda]'``) when CUDA, nvmath-python or cuDSS is missing.
    """

    rhs_block: int = 8
    indefinite: bool = True
    name: str = "cudss"

    def __post_init__(self) -> None:
        load_nvmath()
        if self.rhs_block < 1:
            raise ValueError(f"rhs_block must be >= 1, got {self.rhs_block}")

    def plan(self, pattern: SparsePattern, kind: str, device: torch.device,
             dtype: torch.dtype) -> CudssPlan:
        """The plan of ``pattern`` for this matrix kind (``'spd'``, ``'symmetric'``,
        ``'general'``), device and dtype (made once, kept with the pattern)."""
        plans = _PLANS.get(pattern)
        if plans is None:
            plans = _PLANS[pattern] = {}
        key = (kind, device, dtype, self.rhs_block)
        if key not in plans:
            plans[key] = CudssPlan(pattern, kind, device, dtype, self.rhs_block)
        return plans[key]

    def factorize(self, pattern: SparsePattern, values: Tensor, symmetric: bool) -> CudssFactor:
        if values.device.type != "cuda":
            raise ValueError(f"the cudss backend runs on CUDA, but the tensors are on "
                             f"{values.device}: use backend='scipy' or 'pardiso' on the CPU")
        if values.dtype not in (torch.float32, torch.float64):
            raise ValueError(f"the cudss backend takes float32 or float64 values, got {values.dtype}")
        if not bool(torch.isfinite(values).all()):
            raise SingularMatrixError("system matrix has NaN or infinite entries")
        kind = "spd" if symmetric else "general"
        factor = self._factorize(self.plan(pattern, kind, values.device, values.dtype), values)
        if factor is None and symmetric and self.indefinite:
            kind = "symmetric"
            factor = self._factorize(self.plan(pattern, kind, values.device, values.dtype),
                                     values)
        if factor is None:
            what = {"spd": "not positive definite", "symmetric": "singular",
                    "general": "singular"}[kind]
            raise SingularMatrixError(
                f"cuDSS factorisation failed (zero or negative pivot): the matrix is {what}; "
                "check that every connected part of the model has a Dirichlet (fixed) node "
                "and that all stiffnesses are positive")
        count_factorization()
        return factor

    @staticmethod
    def _factorize(plan: CudssPlan, values: Tensor) -> CudssFactor | None:
        """Numeric factorisation in a free slot of ``plan``; ``None`` when cuDSS reports a
        zero or (Cholesky) non-positive pivot."""
        slot = plan.acquire()
        try:
            slot.values.copy_(values.detach())       # in place: the plan stays valid
            info = int(slot.solver.factorize().info)
        except Exception as err:  # noqa: BLE001 - nvmath/cuDSS raise their own types
            plan.release(slot)
            if _is_out_of_memory(err):
                raise gpu_memory_error("the cuDSS factorisation", plan.size(), err) from None
            raise
        if info != 0:
            plan.release(slot)
            return None
        return CudssFactor(plan, slot, {"info": info, "kind": plan.kind})


__all__ = ["CUDA_EXTRA", "CudssBackend", "CudssFactor", "CudssPlan", "CudssUnavailableError",
           "GpuMemoryError", "MATRIX_KINDS", "cudss_available", "gpu_memory_error", "load_nvmath"]
