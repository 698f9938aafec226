"""``amg`` backend: conjugate gradients preconditioned by smoothed-aggregation AMG (pyamg).

For large 3-D bodies a direct factorisation's fill grows faster than the cost of an
algebraic-multigrid preconditioned CG (``docs/notes/amg.md`` has the measured
crossover). This backend keeps the :class:`~.base.Factor` contract:

* **"factorisation"** (counted as one in :mod:`..counters`): pyamg's smoothed-aggregation
  hierarchy of the matrix (``smoothed_aggregation_solver`` with :data:`HIERARCHY`'s
  options; its coarsest level factorised here too), built once per matrix and reused by
  every solve with it (forward, adjoint, ``J v``, blocks of right-hand sides). The
  near-nullspace is, in this order of preference, the modes registered for the pattern
  with :meth:`AmgBackend.set_near_nullspace` (the elastic equilibria register the 6
  rigid-body modes of the free dofs, built from the rest positions), the 3 translations
  where the pattern is made of full 3x3 blocks (3 dofs per node, interleaved), else the
  constant vector.
* **solve** (counted as one per call, as every backend): preconditioned CG in float64
  (one V-cycle per iteration), every column of a block iterated together, each to
  ``||b - A x|| <= rtol ||b||`` (default ``rtol = 1e-10``, torch-fem's default too). The
  matrix is symmetric, so ``transpose=True`` is the same solve. A factor is not
  ``refinable``: the refinement step a linear equilibrium makes after a direct solve
  would be one more full solve here, and is skipped.
* **fallback** to a direct backend (``pardiso`` where installed, else ``scipy``), with
  the contract of ``banded``'s: a nonsymmetric matrix, a diagonal that is not positive
  or a hierarchy pyamg cannot build go to the direct backend at factorisation time; a
  solve in which CG meets a direction of non-positive curvature (an indefinite Newton
  tangent) or does not converge in ``max_iter`` iterations factorises the same matrix
  directly (one more counted factorisation), keeps that factor for every later solve,
  and solves with it.

pyamg is an optional dependency (the extra ``torchfit[amg]``):
:func:`amg_available` says whether it imports. Level-1 vector operations run with one
BLAS thread (:func:`threadpoolctl.threadpool_limits`): on vectors of this size extra
OpenBLAS threads only spin (5x slower V-cycles on a loaded 2-core machine).
"""
from __future__ import annotations

import dataclasses
import weakref
from typing import Any, Callable

import numpy as np
import scipy.sparse as sp
import torch
from threadpoolctl import threadpool_limits
from torch import Tensor

from ..counters import SolveCounters, count_factorization, count_solve, credit
from ..errors import SingularMatrixError, cpu_only
from ..pattern import SparsePattern

AMG_EXTRA = "pip install 'torchfit[amg]' (pyamg)"

#: keyword arguments of ``pyamg.smoothed_aggregation_solver`` (measured choice:
#: ``docs/notes/amg.md``)
HIERARCHY: dict[str, Any] = {
    "improve_candidates": None,
    "max_coarse": 500,
    "coarse_solver": "splu",
    "presmoother": ("gauss_seidel", {"sweep": "forward"}),
    "postsmoother": ("gauss_seidel", {"sweep": "backward"}),
}


class AmgUnavailableError(ImportError):
    """``backend='amg'`` without pyamg installed."""


def amg_available() -> bool:
    """Whether pyamg imports here."""
    try:
        import pyamg  # noqa: F401
    except ImportError:
        return False
    return True


def _pyamg() -> Any:
    try:
        import pyamg
    except ImportError as err:
        raise AmgUnavailableError(f"backend=amg needs pyamg, which is not installed here: "
                                  f"{AMG_EXTRA}, or choose backend=pardiso or scipy") from err
    return pyamg


def translation_modes(n: int, block: int) -> np.ndarray:
    """``(n, block)``: unit translations of interleaved ``block``-dof nodes."""
    modes = np.zeros((n, block))
    for axis in range(block):
        modes[axis::block, axis] = 1.0
    return modes


def _block_size(pattern: SparsePattern, block: int = 3) -> int:
    """``block`` when the pattern is made of full ``block x block`` blocks, else 1."""
    n = pattern.shape[0]
    if n % block:
        return 1
    rows = pattern.row_indices.cpu().numpy() // block
    cols = pattern.col_indices.cpu().numpy() // block
    blocks = np.unique(rows * (n // block) + cols).size
    return block if blocks * block * block == pattern.nnz else 1


def pcg(matrix: sp.csr_matrix, preconditioner: Callable[[np.ndarray], np.ndarray],
        rhs: np.ndarray, rtol: float, max_iter: int) -> tuple[np.ndarray, bool, bool, int]:
    """Preconditioned CG on the columns of ``rhs`` ``(n, c)`` at once.

    Returns ``(x, converged, positive, iterations)``: ``positive`` is False when some
    search direction had ``p^T A p <= 0`` (the matrix is not positive definite).
    """
    x = np.zeros_like(rhs)
    r = rhs.copy()
    target = rtol * np.linalg.norm(rhs, axis=0)
    active = np.nonzero(np.linalg.norm(r, axis=0) > target)[0]
    p = np.zeros_like(rhs)
    rz = np.zeros(rhs.shape[1])
    iterations = 0
    while active.size and iterations < max_iter:
        z = np.stack([preconditioner(np.ascontiguousarray(r[:, j])) for j in active], axis=1)
        rz_new = np.einsum("ij,ij->j", r[:, active], z)
        if iterations == 0:
            p[:, active] = z
        else:
            p[:, active] = z + (rz_new / rz[active]) * p[:, active]
        rz[active] = rz_new
        q = matrix @ p[:, active]
        curvature = np.einsum("ij,ij->j", p[:, active], q)
        if not (curvature > 0).all():
            return x, False, False, iterations
        alpha = rz[active] / curvature
        x[:, active] += alpha * p[:, active]
        r[:, active] -= alpha * q
        iterations += 1
        still = np.linalg.norm(r[:, active], axis=0) > target[active]
        active = active[still]
    return x, not active.size, True, iterations


def v_cycle(hierarchy: Any) -> Callable[[np.ndarray], np.ndarray]:
    """One V-cycle of a pyamg hierarchy from a zero start, as a function of the residual
    (pyamg's own ``aspreconditioner`` adds two residual products and norms per call)."""
    levels = hierarchy.levels

    def cycle(b: np.ndarray, lvl: int = 0) -> np.ndarray:
        if lvl == len(levels) - 1:
            return np.asarray(hierarchy.coarse_solver(levels[lvl].A, b)).reshape(b.shape)
        level = levels[lvl]
        x = np.zeros_like(b)
        level.presmoother(level.A, x, b)
        x += level.P @ cycle(level.R @ (b - level.A @ x), lvl + 1)
        level.postsmoother(level.A, x, b)
        return x

    return cycle


class AmgFactor:
    """The AMG hierarchy of one SPD matrix, reused by every solve with it.

    ``refinable = False``: a solve already reaches ``rtol``, so the iterative refinement a
    linear equilibrium makes after a direct solve (one more solve) is skipped with it.

    Attributes:
        levels, operator_complexity: of the hierarchy; ``iterations``: CG iterations of
        the last solve (the most of its columns); ``direct``: the direct factor once a
        solve fell back (``None`` before).
    """

    def __init__(self, matrix: sp.csr_matrix, hierarchy: Any, rtol: float, max_iter: int,
                 dtype: torch.dtype, direct: Callable[[], Any]) -> None:
        self._matrix = matrix
        self._hierarchy = hierarchy
        self._vcycle = v_cycle(hierarchy)
        self._rtol = rtol
        self._max_iter = max_iter
        self._dtype = dtype
        self._make_direct = direct
        self.levels = len(hierarchy.levels)
        self.operator_complexity = float(hierarchy.operator_complexity())
        self.iterations = 0
        self.direct: Any = None

    @property
    def refinable(self) -> bool:
        return self.direct is not None

    def solve(self, rhs: Tensor, transpose: bool = False) -> Tensor:
        # A is symmetric: A^T x = b is the same solve.
        if rhs.device.type != "cpu":
            raise cpu_only("amg", rhs.device)
        if self.direct is not None:
            return self.direct.solve(rhs, transpose)
        count_solve(rhs)
        b = rhs.detach().to(torch.float64).numpy().reshape(rhs.shape[0], -1)
        with threadpool_limits(limits=1, user_api="blas"):
            x, converged, positive, self.iterations = pcg(
                self._matrix, self._vcycle, b, self._rtol, self._max_iter)
        if not (converged and positive):
            # an indefinite tangent or a stalled CG: the direct backend, from now on
            credit(SolveCounters(solves=-1, rhs_columns=-b.shape[1]))   # counted by the direct one
            self.direct = self._make_direct()
            return self.direct.solve(rhs, transpose)
        if not np.isfinite(x).all():
            raise SingularMatrixError("the AMG-CG solve produced NaN or infinite values")
        return torch.from_numpy(x.reshape(rhs.shape)).to(self._dtype)


@dataclasses.dataclass
class AmgBackend:
    """Smoothed-aggregation AMG-preconditioned CG (CPU, SPD; pyamg).

    Args:
        fallback: the direct backend of matrices CG cannot take (``get_backend('amg')``
            gives ``pardiso`` where installed, else ``scipy``).
        rtol: relative residual every column of a solve reaches.
        max_iter: CG iterations before a solve falls back to ``fallback``.

    Attributes:
        fallbacks: factorisations handed to ``fallback`` (at factorisation or in a solve).
    """

    fallback: Any
    rtol: float = 1e-10
    max_iter: int = 500
    hierarchy_options: dict = dataclasses.field(default_factory=lambda: dict(HIERARCHY))
    name: str = "amg"

    def __post_init__(self) -> None:
        _pyamg()
        self.fallbacks = 0
        self._modes: "weakref.WeakKeyDictionary[SparsePattern, np.ndarray]" = \
            weakref.WeakKeyDictionary()

    def _direct(self, pattern: SparsePattern, values: Tensor, symmetric: bool) -> Any:
        self.fallbacks += 1
        return self.fallback.factorize(pattern, values, symmetric)

    def set_near_nullspace(self, pattern: SparsePattern, modes: Tensor | np.ndarray) -> None:
        """Use ``modes`` ``(n, k)`` (e.g. the rigid-body modes of the free dofs) as the
        near-nullspace of every matrix of ``pattern``."""
        modes = np.ascontiguousarray(torch.as_tensor(modes).detach().cpu().numpy(),
                                     dtype=np.float64)
        if modes.ndim != 2 or modes.shape[0] != pattern.shape[0]:
            raise ValueError(f"near-nullspace modes must be ({pattern.shape[0]}, k), got "
                             f"{modes.shape}")
        self._modes[pattern] = modes

    def near_nullspace(self, pattern: SparsePattern) -> np.ndarray:
        """The registered modes, else translations of full 3x3 blocks, else constants."""
        modes = self._modes.get(pattern)
        if modes is None:
            modes = translation_modes(pattern.shape[0], _block_size(pattern))
            self._modes[pattern] = modes
        return modes

    def factorize(self, pattern: SparsePattern, values: Tensor, symmetric: bool) -> Any:
        if values.device.type != "cpu":
            raise cpu_only("amg", values.device)
        if not torch.isfinite(values).all():
            raise SingularMatrixError("system matrix has NaN or infinite entries")
        if not symmetric or not bool((pattern.diagonal(values.detach()) > 0).all()):
            return self._direct(pattern, values, symmetric)
        matrix = pattern.to_scipy(values.detach().to(torch.float64)).tocsr()
        try:
            with threadpool_limits(limits=1, user_api="blas"):
                hierarchy = _pyamg().smoothed_aggregation_solver(
                    matrix, B=self.near_nullspace(pattern), **self.hierarchy_options)
        except (ValueError, np.linalg.LinAlgError, RuntimeError):
            return self._direct(pattern, values, symmetric)
        # the coarsest level's factorisation is made on its first use: make it here
        coarsest = hierarchy.levels[-1].A
        hierarchy.coarse_solver(coarsest, np.zeros(coarsest.shape[0]))
        count_factorization()
        return AmgFactor(matrix, hierarchy, self.rtol, self.max_iter, values.dtype,
                         lambda: self._direct(pattern, values, symmetric))
