"""``pardiso``: MKL PARDISO as a backend (CPU, the optional extra ``torchfit[pardiso]``; the
binding: :mod:`.pardiso_mkl`).

The symbolic analysis (ordering and symbolic factorisation, phase 11) is made once per
sparsity pattern and kept with it; every factorisation of that pattern is a numeric
factorisation (phase 22) into a slot of the same PARDISO handle, so the frames of one mesh
are live factors sharing one analysis. Symmetric matrices are factorised as symmetric
indefinite (Bunch-Kaufman ``L D L^T``: Newton tangents may be indefinite); nonsymmetric ones
by LU with scaling and weighted matching, which read the values in the analysis, so there
every factor gets its own analysis (the host structure is still built once per pattern).
"""
from __future__ import annotations

import dataclasses
import weakref

import numpy as np
import torch
from torch import Tensor

from ..counters import count_analysis, count_factorization, count_solve
from ..errors import SingularMatrixError, cpu_only
from ..pattern import SparsePattern
from .pardiso_mkl import (REAL_NONSYMMETRIC, REAL_SYMMETRIC_INDEFINITE, SINGULAR_CODES,
                          PardisoError, PardisoHandle, PardisoStructure, load_pardiso)


_SINGULAR_ADVICE = ("the system is singular: check that every connected part of the model "
                    "has a Dirichlet (fixed) node and that all stiffnesses are positive")


class PardisoFactor:
    """A numeric PARDISO factorisation: slot ``mnum`` of a :class:`PardisoHandle`.

    Solves (phase 33) take ``(n,)`` or ``(n, k)`` right-hand sides (``k`` columns in one
    call) and the transpose. The slot's memory is released (phase 0) when the factor is
    garbage collected; the handle lives as long as a plan or a factor needs it.
    """

    def __init__(self, handle: PardisoHandle, mnum: int, a: np.ndarray, symmetric: bool,
                 dtype: torch.dtype, report: dict[str, int]) -> None:
        self._handle = handle
        self._mnum = mnum
        self._a = a                  # phase 33 gets the values again
        self._symmetric = symmetric
        self._dtype = dtype
        self.report = report         # PARDISO's output of the factorisation (inertia, nnz)
        self._finalizer = weakref.finalize(self, handle.release, mnum)
        self._finalizer.atexit = False

    def solve(self, rhs: Tensor, transpose: bool = False) -> Tensor:
        if rhs.device.type != "cpu":
            raise cpu_only("pardiso", rhs.device)
        count_solve(rhs)
        b = rhs.detach().to(torch.float64).numpy()
        x = self._handle.solve(self._mnum, self._a, b,
                               transpose=bool(transpose and not self._symmetric))
        if not np.isfinite(x).all():
            raise SingularMatrixError("the PARDISO solve produced NaN or infinite values; "
                                      + _SINGULAR_ADVICE)
        return torch.from_numpy(x).to(self._dtype)


class PardisoPlan:
    """What one sparsity pattern keeps for PARDISO (per matrix type): the host structure
    (upper-triangle CSR and the map from the pattern's values) and the handles.

    Symmetric types: one handle holds the analysis and up to ``capacity`` live factors;
    a further handle (a second analysis) only when all of them are alive at once, or when
    MKL's thread limit changed since the analysis (``set_threads`` after a problem was
    built: a factorisation under another limit than its analysis can crash MKL).
    Nonsymmetric: the analysis depends on the values (scaling, matching), so every
    factor has a handle (and an analysis) of its own.

    Attributes:
        analyses: phase-11 analyses made for this pattern and type so far (each also
            counted in the open counting scopes: ``SolveCounters.analyses``).
    """

    def __init__(self, pattern: SparsePattern, mtype: int, capacity: int) -> None:
        self.mtype = mtype
        self.capacity = int(capacity)
        self.structure = PardisoStructure(pattern.row_indices.cpu().numpy(),
                                          pattern.col_indices.cpu().numpy(), pattern.shape[0],
                                          symmetric=mtype != REAL_NONSYMMETRIC)
        self.handles: list[PardisoHandle] = []
        self.analyses = 0

    def slot(self, a: np.ndarray) -> tuple[PardisoHandle, int]:
        """A handle analysed for this structure and a free factor slot in it."""
        library = load_pardiso()
        if self.mtype == REAL_NONSYMMETRIC:
            handle = PardisoHandle(library, self.structure, self.mtype, 1, a)
            self.analyses += 1
            count_analysis()
            return handle, handle.acquire()  # type: ignore[return-value]
        threads = library.max_threads()
        # a handle analysed under another limit is dropped here (its live factors keep it)
        self.handles = [handle for handle in self.handles if handle.threads == threads]
        for handle in reversed(self.handles):
            mnum = handle.acquire()
            if mnum is not None:
                return handle, mnum
        handle = PardisoHandle(library, self.structure, self.mtype, self.capacity, a)
        self.analyses += 1
        count_analysis()
        self.handles.append(handle)
        return handle, handle.acquire()  # type: ignore[return-value]


#: pattern -> {matrix type: plan}, shared by every PardisoBackend (every equilibrium makes
#: a backend of its own; the analysis must outlive it)
_PARDISO_PLANS: "weakref.WeakKeyDictionary[SparsePattern, dict[int, PardisoPlan]]" = \
    weakref.WeakKeyDictionary()


@dataclasses.dataclass
class PardisoBackend:
    """MKL PARDISO (CPU): analysis once per pattern, numeric factorisation per matrix.

    Args:
        capacity: live factors one analysis serves (PARDISO's ``maxfct``) before a second
            analysis of the same pattern is made; free slots cost no memory.

    Raises :class:`~.pardiso_mkl.PardisoUnavailableError` (an ``ImportError`` naming
    ``pip install 'torchfit[pardiso]'``) when pypardiso or MKL is missing.
    """

    capacity: int = 1024
    name: str = "pardiso"

    def __post_init__(self) -> None:
        load_pardiso()

    def plan(self, pattern: SparsePattern, symmetric: bool) -> PardisoPlan:
        """The plan of ``pattern`` for symmetric or nonsymmetric matrices (made once)."""
        mtype = REAL_SYMMETRIC_INDEFINITE if symmetric else REAL_NONSYMMETRIC
        plans = _PARDISO_PLANS.get(pattern)
        if plans is None:
            plans = _PARDISO_PLANS[pattern] = {}
        if mtype not in plans:
            if pattern.shape[0] != pattern.shape[1]:
                raise ValueError(f"PARDISO needs a square matrix, got {pattern.shape}")
            plans[mtype] = PardisoPlan(pattern, mtype, self.capacity)
        return plans[mtype]

    def factorize(self, pattern: SparsePattern, values: Tensor, symmetric: bool) -> PardisoFactor:
        if values.device.type != "cpu":
            raise cpu_only("pardiso", values.device)
        if not torch.isfinite(values).all():
            raise SingularMatrixError("system matrix has NaN or infinite entries")
        plan = self.plan(pattern, symmetric)
        a = plan.structure.gather(values.detach().to(torch.float64).numpy())
        try:
            handle, mnum = plan.slot(a)
        except PardisoError as err:      # an analysis that reads values (nonsymmetric)
            if err.code in SINGULAR_CODES:
                raise SingularMatrixError(f"sparse factorisation failed ({err}); "
                                          + _SINGULAR_ADVICE) from err
            raise
        report = handle.factorize(mnum, a)
        error, perturbed = report["error"], report["perturbed_pivots"]
        if error or perturbed:
            handle.release(mnum)
            if error and error not in SINGULAR_CODES:
                if error == -2:
                    raise MemoryError(str(PardisoError(error, 22)))
                raise PardisoError(error, 22)
            why = str(PardisoError(error, 22)) if error else (
                f"PARDISO perturbed {perturbed} pivot(s) smaller than 1e-13 ||A||")
            raise SingularMatrixError(f"sparse factorisation failed ({why}); "
                                      + _SINGULAR_ADVICE)
        count_factorization()
        return PardisoFactor(handle, mnum, a, symmetric, values.dtype, report)
