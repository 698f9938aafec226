"""Parameter-space preconditioners for CGLS built from the parameterisation's ``D``.

For a field seen through an elliptic solve (``J = -A^{-1} dR/dk``) the Gauss-Newton
matrix ``J^T J`` acts like an inverse Laplacian on the parameters: smooth changes of the
field are seen strongly, rough ones weakly. The graph Laplacian ``D^T D`` of the
parameter neighbours (``D`` the difference operator the caller hands over; solvers never
build it) is then a cheap approximate inverse. Gauss-Newton shifts it
(:class:`DifferencePreconditioner`), Levenberg-Marquardt scales it by the Jacobian's
column norms (:class:`ColumnScaledLaplacian`); the Laplacian itself lives here, once.
Measured effects: ``docs/notes/gauss_newton.md``, ``docs/notes/levenberg_marquardt.md``.
"""
from __future__ import annotations

import warnings

import torch
from torch import Tensor

from .base import SolverConfigError
from .total_variation import check_difference_operator


def compressed_rows(matrix: Tensor) -> Tensor:
    """``matrix`` (sparse COO or CSR) as CSR, for ``torch.mv`` at one product per CGLS
    iteration (CSR is the faster layout on the CPU: ``docs/notes/gauss_newton.md``)."""
    with warnings.catch_warnings():   # "sparse CSR support is in beta": mv is all we use
        warnings.simplefilter("ignore", UserWarning)
        return matrix.coalesce().to_sparse_csr() if matrix.layout == torch.sparse_coo \
            else matrix.to_sparse_csr()


class GraphLaplacian:
    """``v (n,) -> D^T D v``, with ``D^T D`` formed once (CSR).

    Args:
        D: ``(n_edges, n)`` sparse difference operator of the parameterisation, or
            ``None`` (a clear error: the preconditioner needs it).
        like: a tensor with ``n`` entries and the dtype and device of ``theta``.
    Attributes:
        degree: the largest diagonal entry of ``D^T D`` (most neighbours of a parameter).
    """

    def __init__(self, D: Tensor | None, like: Tensor) -> None:
        if D is None:
            raise SolverConfigError(
                "solver.preconditioner=difference needs the difference operator D of the "
                "parameterisation (pass D=parameterization.difference_operator()), or set "
                "solver.preconditioner=none")
        D, _, _ = check_difference_operator(D, like.numel(), dtype=like.dtype, device=like.device)
        with warnings.catch_warnings():   # the sparse-sparse product goes through beta kernels
            warnings.simplefilter("ignore", UserWarning)
            laplacian = torch.sparse.mm(D.t().coalesce(), D).coalesce()
        self.degree = float(torch.sparse.sum(D * D, dim=0).to_dense().max())
        self._L = compressed_rows(laplacian)

    def __call__(self, v: Tensor) -> Tensor:
        return torch.mv(self._L, v)


class DifferencePreconditioner:
    """``M v = D^T D v + s v`` for CGLS (Gauss-Newton's ``preconditioner=difference``).

    The shift ``s`` bounds how much a rough mode is favoured over a smooth one (at most
    ``(||D||^2 + s) / s``); the solver starts with a large shift (close to
    unpreconditioned CGLS, the linear model being poor for rough changes far from the
    solution) and lowers it as the misfit falls.

    Args:
        D: ``(n_edges, n)`` sparse difference operator of the parameterisation (a clear
            error when ``None``).
        like: ``theta`` (``n`` entries; its dtype and device).
    Attributes:
        degree: the largest diagonal entry of ``D^T D``, the unit of :attr:`shift`.
        shift: ``s`` relative to :attr:`degree` (set by the solver).
    """

    def __init__(self, D: Tensor | None, like: Tensor) -> None:
        self._laplacian = GraphLaplacian(D, like)
        self.degree = self._laplacian.degree
        self.shift = 0.0

    def __call__(self, v: Tensor) -> Tensor:
        return self._laplacian(v) + (self.shift * self.degree) * v


class ColumnScaledLaplacian:
    """``s -> C^{-1} (D^T D + eps I) C^{-1} s`` (Levenberg-Marquardt's ``difference``).

    ``C = diag(c)`` holds the Jacobian's column norms at one linearisation; the solver
    estimates them and passes ``inverse_norms = 1 / c`` (a tensor it can save).
    """

    def __init__(self, laplacian: GraphLaplacian, inverse_norms: Tensor, shift: float) -> None:
        self.laplacian = laplacian
        self.inverse_norms = inverse_norms
        self.shift = shift

    def __call__(self, s: Tensor) -> Tensor:
        v = self.inverse_norms * s
        return self.inverse_norms * (self.laplacian(v) + self.shift * v)


__all__ = ["ColumnScaledLaplacian", "DifferencePreconditioner", "GraphLaplacian",
           "compressed_rows"]
