"""Linear test systems: a tridiagonal SPD matrix of spring stiffnesses, and a linear
equilibrium model on any given sparse matrix (the differentiable linear solve of the
backend tests: ``A x = f`` with ``A = matrix + diag(shift)``, ``shift`` the parameters)."""
from __future__ import annotations

from typing import Callable

import torch

from torchfit.linalg import SparsePattern


def chain_pattern(n: int) -> tuple[SparsePattern, Callable[[torch.Tensor], torch.Tensor]]:
    """Tridiagonal SPD matrix ``sum_i k_i (e_i - e_{i+1})(.)^T + I`` as a function of k."""
    rows, cols = [], []
    for i in range(n - 1):
        rows += [i, i, i + 1, i + 1]
        cols += [i, i + 1, i, i + 1]
    rows += list(range(n))
    cols += list(range(n))
    pattern = SparsePattern(torch.tensor(rows), torch.tensor(cols), (n, n))

    def values(k: torch.Tensor) -> torch.Tensor:
        local = torch.stack([k, -k, -k, k], dim=1).reshape(-1)
        return pattern.assemble(torch.cat([local, torch.ones(n, dtype=k.dtype)]))

    return pattern, values


class MatrixModel:
    """``R(x, shift) = A x + shift * x - loads`` for a fixed CSR matrix ``A`` (``values`` on
    ``pattern``), ``shift`` ``(n,)`` the parameters and ``loads`` ``(F, n)``: a linear
    :class:`~torchfit.physics.EquilibriumModel` whose tangent ``A + diag(shift)`` is the
    same for every frame (one shared factor)."""

    linear = True

    def __init__(self, pattern: SparsePattern, values: torch.Tensor, loads: torch.Tensor,
                 symmetric: bool = True) -> None:
        n = pattern.shape[0]
        self.n_dofs = n
        self.symmetric = symmetric
        self.pattern, self.values, self.loads = pattern, values, loads
        diagonal = torch.arange(n, device=pattern.device)
        self.tangent_pattern = SparsePattern(torch.cat([pattern.row_indices, diagonal]),
                                             torch.cat([pattern.col_indices, diagonal]), (n, n))

    def residual(self, x: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
        return self.pattern.matvec(self.values.to(x), x) + shift * x - self.loads.to(x)

    def tangent_values(self, x: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.values.to(shift), shift])[None]


def linear_equilibrium(pattern: SparsePattern, values: torch.Tensor, backend: str,
                       frames: int = 2, seed: int = 0):
    """``(eq, shift, fixed_values)``: the :class:`MatrixModel` of ``values`` as an
    equilibrium with dof 0 fixed (``frames`` random loads and Dirichlet values) and the
    parameters ``shift`` (0.1 on the diagonal, as the grid matrices have), all on the
    device of ``values``."""
    from torchfit.physics import Equilibrium

    g = torch.Generator().manual_seed(seed)
    n = pattern.shape[0]
    loads = torch.randn(frames, n, dtype=values.dtype, generator=g).to(values.device)
    eq = Equilibrium(MatrixModel(pattern, values, loads), torch.tensor([0]), backend=backend)
    shift = torch.full((n,), 0.1, dtype=values.dtype).to(values.device)
    fixed = torch.randn(frames, 1, dtype=values.dtype, generator=g).to(values.device)
    return eq, shift, fixed


def gradients(eq, shift: torch.Tensor, fixed: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Gradients of ``||x*||^2`` with respect to the parameters and the Dirichlet values."""
    leaves = (shift.detach().clone().requires_grad_(True),
              fixed.detach().clone().requires_grad_(True))
    return torch.autograd.grad(eq(*leaves).square().sum(), leaves)
