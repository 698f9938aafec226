"""``cg``: Jacobi-preconditioned conjugate gradients in torch, batched over right-hand sides,
on any device (CUDA included). It has no factorisation to reuse: its "factor" keeps the
matrix and the preconditioner, so that the calling code is the same as for a direct one."""
from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from ..cg import batched_cg
from ..counters import count_factorization, count_solve
from ..errors import SingularMatrixError
from ..pattern import SparsePattern


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
        count_solve(rhs)
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
        count_factorization()
        max_iter = self.max_iter or max(100, 10 * pattern.shape[0])
        return CGFactor(pattern, values, self.rtol, max_iter)
