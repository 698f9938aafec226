"""Sparse linear-solve backends: a factorisation object with ``solve``.

``scipy`` (CPU): SuperLU from scipy in *symmetric mode* for SPD systems (minimum
degree ordering on ``A^T + A`` and diagonal pivoting), the general COLAMD/partial
pivoting LU otherwise; always there.

``cg`` (any device, CUDA included): Jacobi-preconditioned conjugate gradients in
torch, batched over right-hand sides. It has no factorisation to reuse; its "factor"
keeps the matrix and preconditioner so that the calling code is the same.

``banded`` (CPU): LAPACK banded Cholesky (``cholesky_banded``) after a reverse
Cuthill-McKee ordering computed once per pattern, for long, thin meshes. Matrices that
are not symmetric positive definite (an indefinite tangent during Newton) and patterns
whose band is too wide fall back to the ``scipy`` backend.

``ldl`` (CPU): qdldl's sparse ``L D L^T`` (:mod:`.ldl`) with the ordering and symbolic
analysis made once per pattern and numeric-only refactorisations; matrices that are not
symmetric positive definite fall back to ``scipy``.

``pardiso`` (CPU, optional extra ``torchfit[pardiso]``): MKL PARDISO (:mod:`.pardiso`).
The symbolic analysis (ordering and symbolic factorisation, phase 11) is made once per
sparsity pattern and kept with it; every factorisation of that pattern is a numeric
factorisation (phase 22) into a slot of the same PARDISO handle, so the frames of one
mesh are live factors sharing one analysis. Symmetric matrices are factorised as
symmetric indefinite (Bunch-Kaufman ``LDL^T``: Newton tangents may be indefinite);
nonsymmetric ones by LU with scaling and weighted matching, which read the values in
the analysis, so there every factor gets its own analysis (the host structure is still
built once per pattern). :func:`default_backend` picks it for 3-D problems on the CPU
where it is installed.

``amg`` (CPU, optional extra ``torchfit[amg]``): CG preconditioned by pyamg's
smoothed-aggregation AMG (:mod:`.amg`), the hierarchy built once per matrix; non-SPD
matrices fall back to ``pardiso`` (else ``scipy``). :func:`default_backend` picks it for
3-D problems above :data:`AMG_MIN_DOFS` free dofs with few solves per factorisation.

Every factorisation and every solve is counted in :mod:`torchfit.linalg.counters`.
Measured speeds and the alternatives rejected: ``docs/linalg/backends.md``.
"""
from __future__ import annotations

import dataclasses
from typing import Protocol

import weakref

import numpy as np
import scipy.linalg as sla
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import reverse_cuthill_mckee
import torch
from torch import Tensor

from .cg import batched_cg
from .counters import COUNTERS
from .errors import SingularMatrixError, cpu_only
from .pardiso import (REAL_NONSYMMETRIC, REAL_SYMMETRIC_INDEFINITE, SINGULAR_CODES, PardisoError,
                      PardisoHandle, PardisoStructure, load_pardiso, pardiso_available)
from .amg import AmgBackend, amg_available
from .ldl import LdlBackend
from .pattern import SparsePattern


class Factor(Protocol):
    """A matrix prepared for repeated solves."""

    def solve(self, rhs: Tensor, transpose: bool = False) -> Tensor:
        """Solve ``A x = rhs`` (or ``A^T x = rhs``); ``rhs`` is ``(n,)`` or ``(n, c)``."""


class Backend(Protocol):
    name: str

    def factorize(self, pattern: SparsePattern, values: Tensor, symmetric: bool) -> Factor:
        ...


def _count_solve(rhs: Tensor) -> None:
    COUNTERS.solves += 1
    COUNTERS.rhs_columns += 1 if rhs.dim() == 1 else rhs.shape[1]


class ScipyFactor:
    def __init__(self, lu: "spla.SuperLU", symmetric: bool, dtype: torch.dtype) -> None:
        self._lu = lu
        self._symmetric = symmetric
        self._dtype = dtype

    def solve(self, rhs: Tensor, transpose: bool = False) -> Tensor:
        if rhs.device.type != "cpu":
            raise cpu_only("scipy", rhs.device)
        _count_solve(rhs)
        trans = "T" if (transpose and not self._symmetric) else "N"
        x = self._lu.solve(np.ascontiguousarray(rhs.detach().numpy()), trans=trans)
        return torch.from_numpy(np.asarray(x)).to(self._dtype)


@dataclasses.dataclass
class ScipyBackend:
    """Direct sparse LU from scipy (SuperLU), symmetric mode for SPD matrices."""

    name: str = "scipy"

    def factorize(self, pattern: SparsePattern, values: Tensor, symmetric: bool) -> ScipyFactor:
        if values.device.type != "cpu":
            raise cpu_only("scipy", values.device)
        if not torch.isfinite(values).all():
            raise SingularMatrixError("system matrix has NaN or infinite entries")
        matrix = pattern.to_scipy(values).tocsc()
        try:
            if symmetric:
                # SPD: fill-reducing ordering of A^T + A, no off-diagonal pivoting.
                lu = spla.splu(matrix, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                               options={"SymmetricMode": True})
            else:
                lu = spla.splu(matrix)
        except RuntimeError as err:
            raise SingularMatrixError(
                f"sparse factorisation failed ({err}); the system is singular: check "
                "that every connected part of the model has a Dirichlet (fixed) node and "
                "that all stiffnesses are positive") from err
        COUNTERS.factorizations += 1
        return ScipyFactor(lu, symmetric, values.dtype)


class CGFactor:
    def __init__(self, pattern: SparsePattern, values: Tensor, rtol: float, max_iter: int) -> None:
        self._pattern = pattern
        self._values = values.detach()
        diag = pattern.diagonal(self._values)
        if not (diag > 0).all():
            raise SingularMatrixError("CG backend needs a positive diagonal (an SPD matrix)")
        self._inv_diag = 1.0 / diag
        self._rtol = rtol
        self._max_iter = max_iter

    def solve(self, rhs: Tensor, transpose: bool = False) -> Tensor:
        # The matrix is symmetric (checked at factorisation), so A^T = A.
        _count_solve(rhs)
        columns = rhs.detach().reshape(rhs.shape[0], -1).T  # (c, n)
        curvature = []       # min p^T A p / p^T p of every iteration: <= 0 means not SPD

        def matvec(v: Tensor) -> Tensor:
            product = self._pattern.matvec(self._values, v)
            scale = (v * v).sum(dim=1)
            ratio = (v * product).sum(dim=1) / torch.where(scale > 0, scale, 1.0)
            curvature.append(torch.where(scale > 0, ratio, torch.inf).amin())
            return product

        x, converged, iterations = batched_cg(
            matvec, columns, preconditioner=lambda v: self._inv_diag * v, rtol=self._rtol,
            max_iter=self._max_iter)
        if curvature and float(torch.stack(curvature).min()) <= 0.0:
            raise SingularMatrixError(
                "the cg backend needs a symmetric positive definite matrix, and this one is "
                "not (CG met a direction d with d^T A d <= 0); check that all stiffnesses are "
                "positive, or use a direct backend (scipy, pardiso, cudss)")
        if not converged:
            raise SingularMatrixError(
                f"preconditioned CG did not reach rtol={self._rtol} in {iterations} "
                "iterations; the matrix may be singular or badly conditioned (use "
                "backend='scipy' on the CPU)")
        return x.T.reshape(rhs.shape)


@dataclasses.dataclass
class CGBackend:
    """Jacobi-preconditioned CG in torch (SPD matrices only), any device."""

    rtol: float = 1e-12
    max_iter: int | None = None
    name: str = "cg"

    def factorize(self, pattern: SparsePattern, values: Tensor, symmetric: bool) -> CGFactor:
        if not symmetric:
            raise ValueError("the cg backend needs a symmetric positive definite matrix")
        if not torch.isfinite(values).all():
            raise SingularMatrixError("system matrix has NaN or infinite entries")
        COUNTERS.factorizations += 1
        max_iter = self.max_iter or max(100, 10 * pattern.shape[0])
        return CGFactor(pattern, values, self.rtol, max_iter)


class BandedFactor:
    """Banded Cholesky factor of ``P A P^T`` (upper form) with the RCM permutation ``P``."""

    def __init__(self, band: np.ndarray, perm: np.ndarray, dtype: torch.dtype) -> None:
        self._band = band
        self._perm = perm
        self._dtype = dtype

    def solve(self, rhs: Tensor, transpose: bool = False) -> Tensor:
        # A is symmetric: A^T x = b is the same solve.
        if rhs.device.type != "cpu":
            raise cpu_only("banded", rhs.device)
        _count_solve(rhs)
        b = rhs.detach().numpy()
        x = np.empty_like(b)
        x[self._perm] = sla.cho_solve_banded((self._band, False), b[self._perm],
                                             check_finite=False)
        return torch.from_numpy(x).to(self._dtype)


class _BandPlan:
    """Per pattern: RCM permutation and where every CSR slot of the upper triangle goes."""

    def __init__(self, pattern: SparsePattern) -> None:
        n = pattern.shape[0]
        structure = pattern.to_scipy(torch.ones(pattern.nnz, dtype=torch.float64))
        self.perm = np.asarray(reverse_cuthill_mckee(structure.tocsr(), symmetric_mode=True),
                               dtype=np.int64)
        inverse = np.empty(n, dtype=np.int64)
        inverse[self.perm] = np.arange(n)
        rows = inverse[pattern.row_indices.cpu().numpy()]
        cols = inverse[pattern.col_indices.cpu().numpy()]
        upper = rows <= cols
        self.slots = np.nonzero(upper)[0]
        self.bandwidth = int((cols - rows)[upper].max()) if upper.any() else 0
        # upper form of LAPACK: ab[u + i - j, j] = A[i, j] for i <= j
        self.flat_index = (self.bandwidth + rows[upper] - cols[upper]) * n + cols[upper]
        self.n = n


@dataclasses.dataclass
class BandedBackend:
    """RCM + LAPACK banded Cholesky for SPD matrices with a narrow band (CPU).

    Falls back to :class:`ScipyBackend` when the matrix is not symmetric, not positive
    definite, or its RCM bandwidth exceeds ``max_bandwidth_fraction`` of its size.
    """

    max_bandwidth_fraction: float = 0.1
    name: str = "banded"

    def __post_init__(self) -> None:
        self._plans: "weakref.WeakKeyDictionary[SparsePattern, _BandPlan]" = weakref.WeakKeyDictionary()
        self._fallback = ScipyBackend()

    def plan(self, pattern: SparsePattern) -> _BandPlan:
        plan = self._plans.get(pattern)
        if plan is None:
            plan = _BandPlan(pattern)
            self._plans[pattern] = plan
        return plan

    def factorize(self, pattern: SparsePattern, values: Tensor, symmetric: bool) -> Factor:
        if values.device.type != "cpu":
            raise cpu_only("banded", values.device)
        if not symmetric:
            return self._fallback.factorize(pattern, values, symmetric)
        plan = self.plan(pattern)
        if plan.bandwidth > max(8, self.max_bandwidth_fraction * plan.n):
            return self._fallback.factorize(pattern, values, symmetric)
        if not torch.isfinite(values).all():
            raise SingularMatrixError("system matrix has NaN or infinite entries")
        band = np.zeros((plan.bandwidth + 1, plan.n))
        band.reshape(-1)[plan.flat_index] = values.detach().numpy()[plan.slots]
        try:
            factor = sla.cholesky_banded(band, lower=False, overwrite_ab=True, check_finite=False)
        except np.linalg.LinAlgError:
            # not positive definite (e.g. an indefinite Newton tangent): pivoted LU
            return self._fallback.factorize(pattern, values, symmetric)
        COUNTERS.factorizations += 1
        return BandedFactor(factor, plan.perm, values.dtype)


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
        _count_solve(rhs)
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
        analyses: phase-11 analyses made for this pattern and type so far.
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

    Raises :class:`~.pardiso.PardisoUnavailableError` (an ``ImportError`` naming
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
        COUNTERS.factorizations += 1
        return PardisoFactor(handle, mnum, a, symmetric, values.dtype, report)


#: free dofs above which :func:`default_backend` picks ``amg`` for a 3-D problem on the CPU
#: that makes few solves per factorisation (measured crossover: ``docs/linalg/amg.md``)
AMG_MIN_DOFS = 20_000
#: the most solves (right-hand-side columns) per factorisation for which ``amg`` is picked
#: (a forward solve and its adjoint: 2; a dense Jacobian: one per parameter, 192 on the arm)
AMG_MAX_SOLVES = 4


def default_backend(dim: int, device: torch.device | str = "cpu", n_dofs: int | None = None,
                    solves_per_factor: int = 1) -> str:
    """The backend a new problem should use: ``'pardiso'`` for 3-D problems on the CPU
    when MKL PARDISO is installed (several times faster than SuperLU there), else
    ``'scipy'``; but ``'amg'`` (pyamg installed) for a 3-D CPU problem of more than
    :data:`AMG_MIN_DOFS` free dofs (``n_dofs``, when the caller knows it) whose use makes at
    most :data:`AMG_MAX_SOLVES` solves per factorisation (``solves_per_factor``: a
    simulation and its gradient, not a Jacobian's many columns, where the factor's cheap
    solves win at every size measured); on CUDA ``'cudss'`` where nvmath-python and cuDSS
    import (``torchfit[cuda]``), else ``'cg'``; ``'cg'`` on any other device. (Existing
    problems keep their own defaults.)"""
    kind = torch.device(device).type
    if kind == "cuda":
        from .cudss import cudss_available

        return "cudss" if cudss_available() else "cg"
    if kind != "cpu":
        return "cg"
    if int(dim) == 3 and n_dofs is not None and n_dofs > AMG_MIN_DOFS \
            and solves_per_factor <= AMG_MAX_SOLVES and amg_available():
        return "amg"
    if int(dim) == 3 and pardiso_available():
        return "pardiso"
    return "scipy"


def get_backend(name: str | Backend) -> Backend:
    """``'scipy'``, ``'banded'``, ``'ldl'``, ``'pardiso'``, ``'amg'``, ``'cudss'`` or ``'cg'``
    (or an object with ``factorize``).

    ``'pardiso'`` without its extra raises :class:`~.pardiso.PardisoUnavailableError`,
    ``'cudss'`` without CUDA or ``torchfit[cuda]`` :class:`~.cudss.CudssUnavailableError`.
    """
    if not isinstance(name, str):
        return name
    if name == "scipy":
        return ScipyBackend()
    if name == "banded":
        return BandedBackend()
    if name == "ldl":
        return LdlBackend(fallback=ScipyBackend())
    if name == "pardiso":
        return PardisoBackend()
    if name == "cg":
        return CGBackend()
    if name == "amg":
        return AmgBackend(fallback=PardisoBackend() if pardiso_available() else ScipyBackend())
    if name == "cudss":
        from .cudss import CudssBackend

        return CudssBackend()
    raise ValueError(f"unknown linear-solve backend {name!r}; choose 'scipy' (CPU direct), "
                     "'banded' (CPU banded Cholesky, SPD), 'ldl' (CPU sparse LDL^T, "
                     "SPD, qdldl), 'pardiso' (CPU, MKL PARDISO, "
                     "optional extra), 'amg' (CPU, AMG-preconditioned CG, pyamg), 'cudss' (CUDA sparse direct, optional extra "
                     "torchfit[cuda]) or 'cg' (torch CG, CPU or CUDA)")
