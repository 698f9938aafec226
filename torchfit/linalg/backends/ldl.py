"""``ldl`` backend: sparse ``L D L^T`` of symmetric positive definite matrices (qdldl).

qdldl (the factorisation inside the OSQP solver; a wheel on PyPI, a dependency of
torchfit) computes ``P A P^T = L D L^T`` with an AMD fill-reducing ordering and no
pivoting. Its ``update`` re-runs only the numeric factorisation of a matrix with the
same pattern, which SuperLU (scipy) cannot: SuperLU orders and analyses the pattern
again on every factorisation. So the ordering and the symbolic analysis are made once
per pattern here, and every further factorisation of that pattern is numeric only:

* a :class:`_LdlPlan` per pattern keeps the structure qdldl reads (the upper triangle in
  CSC order, which for a symmetric matrix is the lower triangle of the pattern's CSR
  order: no sort at factorisation time) and a pool of qdldl solvers;
* a factorisation takes a solver whose factor is no longer referenced from the pool and
  updates its values (``update``: numeric only), or makes a new one (ordering, symbolic
  and numeric) when every solver of the pattern holds a live factor; a factor returns
  its solver to the pool when it is garbage collected.

Measured against SuperLU (faster factorisations, slower solves at large sizes):
``docs/notes/ldl.md``, ``scripts/bench/factorization.py``.

Without pivoting, ``L D L^T`` is only trustworthy for positive definite matrices: a
factorisation whose ``D`` has an entry that is not positive (an indefinite Newton
tangent, a singular matrix) and a nonsymmetric matrix go to SuperLU (the ``scipy``
backend), which pivots and reports singular matrices.
"""
from __future__ import annotations

import dataclasses
import weakref
from typing import Any

import numpy as np
import scipy.sparse as sp
import torch
from torch import Tensor

from ..counters import count_analysis, count_factorization, count_solve
from ..errors import SingularMatrixError, cpu_only
from ..pattern import SparsePattern


def _qdldl() -> Any:
    try:
        import qdldl
    except ImportError as err:       # a dependency of torchfit: a broken environment
        raise ImportError("backend=ldl needs qdldl, a dependency of torchfit: reinstall "
                          "torchfit (pip install -c constraints.txt -e .) or choose "
                          "backend=scipy") from err
    return qdldl


class _LdlPlan:
    """Per pattern: the upper-triangle CSC structure and a pool of qdldl solvers.

    Attributes:
        slots: ``(nnz_upper,)`` CSR slots of the pattern whose values make the upper
            triangle's CSC data, in order.
        analyses: solvers made for this pattern (each one ordering + symbolic analysis, also
            counted in the open counting scopes).
    """

    def __init__(self, pattern: SparsePattern) -> None:
        n = pattern.shape[0]
        rows = pattern.row_indices.cpu().numpy()
        cols = pattern.col_indices.cpu().numpy()
        # CSR order is (row, col) sorted; its lower triangle (col <= row) read row by row
        # is the upper triangle of the symmetric matrix read column by column (CSC).
        lower = cols <= rows
        self.slots = np.nonzero(lower)[0]
        self.indices = cols[lower].astype(np.int32)
        self.indptr = np.zeros(n + 1, dtype=np.int32)
        np.cumsum(np.bincount(rows[lower], minlength=n), out=self.indptr[1:])
        self.n = n
        self.has_diagonal = bool(np.bincount(rows[lower & (cols == rows)], minlength=n).all())
        self._free: list = []
        self.analyses = 0

    def upper(self, values: np.ndarray) -> sp.csc_matrix:
        return sp.csc_matrix((values[self.slots], self.indices, self.indptr),
                             shape=(self.n, self.n))

    def acquire(self, upper: sp.csc_matrix):
        """A solver holding the factorisation of ``upper`` (raises qdldl's RuntimeError
        when the matrix is not quasi-definite; the solver then stays in the pool)."""
        if self._free:
            solver = self._free.pop()
            try:
                solver.update(upper, upper=True)
            except RuntimeError:
                self._free.append(solver)
                raise
            return solver
        solver = _qdldl().Solver(upper, upper=True)
        self.analyses += 1
        count_analysis()
        return solver

    def release(self, solver) -> None:
        self._free.append(solver)


class LdlFactor:
    """A numeric ``L D L^T`` factorisation (SPD); solves ``(n,)`` or ``(n, k)`` right-hand
    sides (column by column). ``A`` is symmetric, so ``transpose`` changes nothing."""

    def __init__(self, plan: _LdlPlan, solver, dtype: torch.dtype) -> None:
        self._solver = solver
        self._dtype = dtype
        self._finalizer = weakref.finalize(self, plan.release, solver)
        self._finalizer.atexit = False

    def solve(self, rhs: Tensor, transpose: bool = False) -> Tensor:
        if rhs.device.type != "cpu":
            raise cpu_only("ldl", rhs.device)
        count_solve(rhs)
        b = rhs.detach().to(torch.float64).numpy()
        if b.ndim == 1:
            x = self._solver.solve(b)
        else:
            x = np.empty_like(b)
            for column in range(b.shape[1]):
                x[:, column] = self._solver.solve(np.ascontiguousarray(b[:, column]))
        return torch.from_numpy(x).to(self._dtype)


#: pattern -> plan, shared by every LdlBackend (every equilibrium makes a backend of its
#: own; the ordering and the solver pool must outlive it)
_LDL_PLANS: "weakref.WeakKeyDictionary[SparsePattern, _LdlPlan]" = weakref.WeakKeyDictionary()


@dataclasses.dataclass
class LdlBackend:
    """Sparse ``L D L^T`` (qdldl) for SPD matrices; the rest goes to ``fallback`` (the
    pivoting SuperLU of the ``scipy`` backend, handed in by
    :func:`~.choice.get_backend`). ``fallbacks`` counts the factorisations handed over.
    """

    fallback: Any
    name: str = "ldl"

    def __post_init__(self) -> None:
        self.fallbacks = 0

    def plan(self, pattern: SparsePattern) -> _LdlPlan:
        """The plan of ``pattern`` (made once per pattern, shared by every backend)."""
        plan = _LDL_PLANS.get(pattern)
        if plan is None:
            plan = _LDL_PLANS[pattern] = _LdlPlan(pattern)
        return plan

    def factorize(self, pattern: SparsePattern, values: Tensor, symmetric: bool):
        if values.device.type != "cpu":
            raise cpu_only("ldl", values.device)
        if not torch.isfinite(values).all():
            raise SingularMatrixError("system matrix has NaN or infinite entries")
        plan = self.plan(pattern) if symmetric else None
        if plan is None or not plan.has_diagonal:
            return self._hand_over(pattern, values, symmetric)
        upper = plan.upper(values.detach().to(torch.float64).numpy())
        try:
            solver = plan.acquire(upper)
        except RuntimeError:             # a zero pivot: singular or not quasi-definite
            return self._hand_over(pattern, values, symmetric)
        pivots = solver.factors()[1]
        if not (pivots > 0).all():       # indefinite: LDL^T without pivoting is unsafe
            plan.release(solver)
            return self._hand_over(pattern, values, symmetric)
        count_factorization()
        return LdlFactor(plan, solver, values.dtype)

    def _hand_over(self, pattern: SparsePattern, values: Tensor, symmetric: bool):
        self.fallbacks += 1
        return self.fallback.factorize(pattern, values, symmetric)

