"""A stand-in for nvmath-python's sparse direct solver and cuda.core's current device, on the
CPU: the :class:`~torchfit.linalg.backends.cudss.CudssRuntime` that
``CudssBackend(runtime=...)`` takes in tests where there is no GPU.

It behaves as nvmath does where the backend relies on it: ``DirectSolver(a, b, options=)``
(``a`` and ``b`` a matrix and a right-hand side, or sequences of them: an explicit batch)
keeps references to ``a`` and ``b`` (values changed in place are read by the next
``factorize()`` / ``solve()``), ``plan()`` analyses the pattern, ``factorize()`` returns an
object with ``info`` (> 0: a non-positive pivot of a Cholesky (SPD) factorisation, or a
zero pivot), ``solve()`` returns ``x`` shaped as ``b``. And as cuda.core does where the
backend once failed: every call from a thread where no device was made current raises
``CUDAError: Device 0 is not yet initialized, perhaps you forgot to call .set_current()
first?``. Every call is recorded (``FakeCuda.calls``: method, thread, device) so that tests
can count analyses and see which thread made each call.

The numerics are SuperLU's: SPD and symmetric matrices factorised without row pivoting
in symmetric mode (the diagonal of ``U`` is ``D`` of ``L D L^T``: its signs tell a
positive definite matrix), general ones with partial pivoting.
"""
from __future__ import annotations

import enum
import threading
import types
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch


class MatrixType(enum.IntEnum):
    GENERAL = 0
    SYMMETRIC = 1
    SPD = 3


@dataclass
class DirectSolverOptions:
    sparse_system_type: MatrixType = MatrixType.GENERAL


class NotCurrentError(RuntimeError):
    """What cuda.core raises for a call from a thread with no current device."""


class FakeCuda:
    """The stand-in runtime: ``advanced`` (the fake ``nvmath.sparse.advanced``),
    ``device_type`` (``'cpu'``), ``make_current`` (per thread, as cuda.core).

    Args:
        make_current_works: ``False`` makes :meth:`make_current` do nothing (a backend
            that relied on it would then fail: the negative control of the thread test).
        fail: ``{method: exception}`` raised by the next call of that method.
    """

    device_type = "cpu"

    def __init__(self, make_current_works: bool = True) -> None:
        self._current = threading.local()
        self.make_current_works = make_current_works
        self.calls: list[tuple[str, int, torch.device]] = []
        self.made_current: list[tuple[int, torch.device]] = []
        self.fail: dict[str, BaseException] = {}
        self.advanced = types.SimpleNamespace(
            DirectSolver=self._direct_solver_class(), DirectSolverOptions=DirectSolverOptions,
            DirectSolverMatrixType=MatrixType)

    def make_current(self, device: torch.device) -> None:
        self.made_current.append((threading.get_ident(), device))
        if self.make_current_works:
            self._current.device = device

    def check(self, method: str, device: torch.device) -> None:
        """Record the call; raise as cuda.core does where ``device`` is not current."""
        self.calls.append((method, threading.get_ident(), device))
        if getattr(self._current, "device", None) != device:
            raise NotCurrentError("CUDAError: Device 0 is not yet initialized, perhaps you "
                                  "forgot to call .set_current() first?")
        if method in self.fail:
            raise self.fail.pop(method)

    def count(self, method: str) -> int:
        return sum(1 for name, _, _ in self.calls if name == method)

    def threads(self, method: str) -> set[int]:
        return {thread for name, thread, _ in self.calls if name == method}

    def _direct_solver_class(self) -> type:
        runtime = self

        class DirectSolver:
            def __init__(self, a: Any, b: Any, *,
                         options: DirectSolverOptions | None = None, **_: Any) -> None:
                # an explicit batch: sequences of matrices and right-hand sides
                self.batch = isinstance(a, (list, tuple))
                if self.batch != isinstance(b, (list, tuple)) or \
                        (self.batch and len(a) != len(b)):
                    raise TypeError("batched LHS and RHS must be sequences of one length")
                members = list(zip(a, b)) if self.batch else [(a, b)]
                runtime.check("DirectSolver", members[0][0].device)
                for matrix, rhs in members:
                    if matrix.layout != torch.sparse_csr or \
                            matrix.crow_indices().dtype != torch.int32:
                        raise TypeError("the LHS must be a CSR tensor with int32 indices")
                    if rhs.dim() != 2 or rhs.stride(0) != 1:
                        raise TypeError("the RHS must be a column-major matrix")
                self.members = [DirectSolver(matrix, rhs, options=options)
                                for matrix, rhs in members] if self.batch else []
                self.a, self.b = a, b
                self.kind = (options or DirectSolverOptions()).sparse_system_type
                self.device = members[0][0].device
                self.lu: Any = None
                self.planned = self.freed = False

            def plan(self) -> Any:
                runtime.check("plan", self.device)
                self.planned = True
                for member in self.members:
                    member.planned = True
                return types.SimpleNamespace()

            def factorize(self) -> Any:
                runtime.check("factorize", self.device)
                assert self.planned and not self.freed
                if self.batch:
                    infos = [member._factorize().info for member in self.members]
                    return types.SimpleNamespace(info=max(infos))
                return self._factorize()

            def _factorize(self) -> Any:
                a = self.a
                matrix = sp.csr_matrix((a.values().numpy(), a.col_indices().numpy(),
                                        a.crow_indices().numpy()), shape=tuple(a.shape)).tocsc()
                symmetric = self.kind != MatrixType.GENERAL
                try:
                    self.lu = spla.splu(matrix, permc_spec="MMD_AT_PLUS_A",
                                        diag_pivot_thresh=0.0 if symmetric else 1.0,
                                        options={"SymmetricMode": symmetric})
                except RuntimeError:                  # exactly singular
                    self.lu = None
                    return types.SimpleNamespace(info=1)
                pivots = self.lu.U.diagonal()
                bad = np.flatnonzero(pivots <= 0) if self.kind == MatrixType.SPD else \
                    np.flatnonzero(pivots == 0)
                if bad.size:
                    self.lu = None
                    return types.SimpleNamespace(info=int(bad[0]) + 1)
                return types.SimpleNamespace(info=0)

            def solve(self) -> Any:
                runtime.check("solve", self.device)
                if self.batch:
                    return [member._solve() for member in self.members]
                return self._solve()

            def _solve(self) -> torch.Tensor:
                assert self.lu is not None, "solve() before a successful factorize()"
                x = self.lu.solve(np.ascontiguousarray(self.b.numpy()))
                return torch.from_numpy(np.asarray(x)).to(self.b.dtype)

            def free(self) -> None:
                runtime.check("free", self.device)
                self.freed = True

        return DirectSolver


class FakeDevice:
    """cuda.core's ``Device`` for :class:`~torchfit.linalg.backends.cudss.NvmathRuntime`:
    records ``Device(index).set_current()`` calls (``FakeDevice.current``: thread -> index)."""

    current: dict[int, int] = {}

    def __init__(self, index: int) -> None:
        self.index = index

    def set_current(self) -> None:
        FakeDevice.current[threading.get_ident()] = self.index
