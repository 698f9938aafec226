"""Derivative products without an autograd graph: explicit products and whole Jacobians.

:class:`EquilibriumLinearization` gives ``J v`` / ``J^T w`` at one solution, and
:func:`solution_jacobian` the Jacobian of many parameter directions at once. Both reuse the
factors stored with the solution (no factorisation). The Jacobian solves
``K dX = -(dR/dparams) V`` for ``V`` ``(n_params, k)``: one solve with ``k`` right-hand sides per
stored factor (``F`` solves, ``F k`` columns; blocks of frames of about 1024 columns for a
shared factor), optionally observed frame by frame (``observe`` ``(n_rows, n_dofs)``) so
that ``(F, n_dofs, k)`` is never formed. ``(dR/dparams) V`` comes from the model's
``param_derivative(...).matmul`` when it has one, else one ``jvp`` of it per column, else
autograd of the residual, column by column.
"""
from __future__ import annotations

import warnings
from typing import Iterator, Protocol

import torch
from torch import Tensor

from ...linalg import FreeMatrixLayout
from .adjoint import SolvedEquilibrium, params_jvp, params_vjp, residual_at_solution
from .cache import Solution


class FreeMatrixLayouts:
    """The CSR layouts of ``dR_free/dparams`` in use, one per entry pattern of a model's
    ``matrix_entries`` (a handful of frame counts, never unbounded)."""

    def __init__(self, free_positions: Tensor, n_free: int) -> None:
        self.free_positions = free_positions
        self.n_free = n_free
        self.entries: list[FreeMatrixLayout] = []

    def find(self, rows: Tensor, cols: Tensor, shape: tuple[int, int],
             n_frames: int) -> FreeMatrixLayout | None:
        """The CSR layout for this entry pattern (made on first use), or ``None`` when the
        entries repeat a position (then the products use jvp/vjp)."""
        layouts = self.entries
        for layout in layouts:
            if layout.matches(rows, cols, shape):
                return layout if layout.unique else None
        layout = FreeMatrixLayout(rows, cols, shape, n_frames, self.free_positions, self.n_free)
        layouts.append(layout)
        del layouts[:-4]          # a handful of frame counts, never unbounded
        return layout if layout.unique else None


class LinearizedEquilibrium(SolvedEquilibrium, Protocol):
    """What the explicit products use of :class:`~torchfit.physics.Equilibrium`."""

    matrix_layouts: FreeMatrixLayouts


class EquilibriumLinearization:
    """The equilibrium at one parameter vector with explicit products, no autograd graph.

    ``x`` ``(F, n_dofs)`` is the solution. :meth:`jvp` and :meth:`vjp` are the
    derivative products with respect to the parameters (Dirichlet values held fixed) on
    full states; :meth:`free_jvp` and :meth:`free_vjp` the same on the free dofs laid out
    ``(n_free, F)`` (what a solve takes and returns, so no reordering): each is one solve
    with the factors stored with the solution (kept alive as long as this object is) and
    one product with ``dR/dparams``. Where the model's ``param_derivative`` has
    ``matrix_entries()`` (a sparse ``(F * n_dofs, n_params)``), that product is one CSR
    matrix-vector product with its free rows (layout built once per pattern by the
    equilibrium, values gathered on first use here).

    The arithmetic is the autograd Function's jvp and backward without the autograd
    engine (its cost: docs/notes/equilibrium.md).
    """

    def __init__(self, equilibrium: LinearizedEquilibrium, solution: Solution) -> None:
        self._eq = equilibrium
        self._solution = solution
        self.x = solution.x
        self.n_frames = int(solution.x.shape[0])
        self._matrices: tuple[Tensor, Tensor] | None = None

    def jvp(self, d_params: Tensor) -> Tensor:
        """``(dx*/dparams) d_params`` ``(F, n_dofs)`` for ``d_params`` ``(n_params,)``."""
        return params_jvp(self._eq, self._solution, d_params.to(self.x))

    def vjp(self, grad_x: Tensor) -> Tensor:
        """``(dx*/dparams)^T grad_x`` ``(n_params,)`` for ``grad_x`` ``(F, n_dofs)``."""
        return params_vjp(self._eq, self._solution, grad_x.to(self.x))

    def free_jvp(self, d_params: Tensor) -> Tensor:
        """``(dx*_free/dparams) d_params`` ``(n_free, F)`` (free dofs in the order of
        ``free_dofs``; :meth:`Equilibrium.free_position` finds a dof's row)."""
        d_params = d_params.to(self.x)
        matrices = self._param_matrices()
        if matrices is None:
            free = self._eq.reduction.free_dofs.to(self.x.device)
            d_residual = self._eq.param_derivative(self._solution).jvp(d_params)[:, free].T
        else:
            d_residual = (matrices[0] @ d_params).view(-1, self.n_frames)
        return -self._solve_free(d_residual.detach(), transpose=False)

    def free_vjp(self, grad_free: Tensor) -> Tensor:
        """``(dx*_free/dparams)^T grad_free`` ``(n_params,)`` for ``grad_free``
        ``(n_free, F)``."""
        lam = self._solve_free(grad_free.to(self.x), transpose=True)
        matrices = self._param_matrices()
        if matrices is None:
            free = self._eq.reduction.free_dofs.to(self.x.device)
            n_dofs = self._eq.reduction.model.n_dofs
            lam_full = lam.new_zeros(self.n_frames, n_dofs).index_copy(1, free, lam.T)
            return -self._eq.param_derivative(self._solution).vjp(lam_full)
        return -(matrices[1] @ lam.reshape(-1))

    def _solve_free(self, rhs: Tensor, transpose: bool) -> Tensor:
        factors = self._solution.factors
        if len(factors) == 1:
            # SuperLU returns column-major blocks: made contiguous once (row gathers)
            return factors[0].solve(rhs.contiguous(), transpose=transpose).to(rhs).contiguous()
        rows = rhs.T.contiguous()          # one frame per row: contiguous right-hand sides
        return torch.stack([f.solve(row, transpose=transpose).to(rhs)
                            for f, row in zip(factors, rows)], dim=1)

    def _param_matrices(self) -> tuple[Tensor, Tensor] | None:
        """``dR_free/dparams`` as CSR ``(n_free * F, n_params)`` (row ``i * F + f``) and its
        transpose, or ``None`` when the model's derivative has no ``matrix_entries``."""
        if self._matrices is None:
            derivative = self._eq.param_derivative(self._solution)
            if not callable(getattr(derivative, "matrix_entries", None)):
                return None
            rows, cols, values, shape = derivative.matrix_entries()
            layout = self._eq.matrix_layouts.find(rows, cols, shape, self.n_frames)
            if layout is None:
                return None
            self._matrices = layout.matrices(values.detach())
        return self._matrices


def solution_jacobian(eq: SolvedEquilibrium, sol: Solution, directions: Tensor,
                      observe: Tensor | None = None) -> Tensor:
    """``(dx*/dparams) directions`` of every frame, ``(F, n_dofs, k)``, or ``observe
    (dx*/dparams) directions``, ``(F, n_rows, k)``, at the solution ``sol`` (Dirichlet rows
    0); ``directions`` ``(n_params, k)``."""
    directions = directions.detach().to(sol.x)
    out = residual_directions(eq, sol, directions)      # (F, n_dofs, k), overwritten
    free = eq.reduction.free_dofs.to(out.device)
    if observe is not None:
        return observed_jacobian(eq, sol, out, observe)
    for start, stop, dx_free in solve_directions(eq, sol, out):
        out[start:stop].zero_()               # the Dirichlet rows stay 0
        out[start:stop, free, :] = -dx_free
    return out


def residual_directions(eq: SolvedEquilibrium, sol: Solution, directions: Tensor) -> Tensor:
    """``(dR/dparams) V`` ``(F, n_dofs, k)`` at the solution (a fresh tensor)."""
    k = directions.shape[1]
    if eq.extensions.has_param_derivative:
        derivative = eq.param_derivative(sol)
        if callable(getattr(derivative, "matmul", None)):
            return derivative.matmul(directions).detach().to(sol.x)   # a new tensor
        return torch.stack([derivative.jvp(directions[:, j]).detach().to(sol.x)
                            for j in range(k)], dim=-1)
    out = sol.x.new_zeros(sol.x.shape[0], eq.reduction.model.n_dofs, k)
    if k == 0:
        return out
    free = eq.reduction.free_dofs.to(sol.x.device)
    with torch.enable_grad():
        residual, leaves = residual_at_solution(eq, sol, True, False)
        probe = torch.zeros_like(residual, requires_grad=True)
        (grad,) = torch.autograd.grad(residual, leaves, probe, create_graph=True,
                                      allow_unused=True)
        if grad is None or not grad.requires_grad:
            return out                           # R does not depend on params
        for j in range(k):
            (column,) = torch.autograd.grad((grad * directions[:, j]).sum(), probe,
                                            retain_graph=True, allow_unused=True)
            if column is not None:
                out[:, free, j] = column.detach()
    return out


def solve_directions(eq: SolvedEquilibrium, sol: Solution,
                     rhs: Tensor) -> Iterator[tuple[int, int, Tensor]]:
    """Yield ``(start, stop, K^{-1} rhs)`` for frames ``start:stop`` on the free dofs,
    ``(stop - start, n_free, k)``, for ``rhs`` ``(F, n_dofs, k)``. One shared factor:
    frames in blocks of about 1024 right-hand sides (docs/notes/equilibrium.md); else
    one solve per frame. A block is read before it is yielded, so the caller may overwrite
    it in ``rhs``."""
    free = eq.reduction.free_dofs.to(rhs.device)
    n_frames, k = rhs.shape[0], rhs.shape[2]
    if len(sol.factors) == 1:
        block = max(1, 1024 // max(k, 1))
        for start in range(0, n_frames, block):
            stop = min(start + block, n_frames)
            columns = rhs[start:stop, free, :].permute(1, 0, 2).reshape(free.numel(), -1)
            dx_free = sol.factors[0].solve(columns.contiguous()).to(rhs)
            yield start, stop, dx_free.reshape(free.numel(), stop - start, k).permute(1, 0, 2)
        return
    for f, factor in enumerate(sol.factors):
        yield f, f + 1, factor.solve(rhs[f, free, :].contiguous()).to(rhs)[None]


def observed_jacobian(eq: SolvedEquilibrium, sol: Solution, rhs: Tensor,
                      observe: Tensor) -> Tensor:
    """``-observe K^{-1} rhs`` per frame, ``(F, n_rows, k)``, for ``rhs``
    ``(F, n_dofs, k)`` (the residual directions). Only the free columns of ``observe``
    matter: Dirichlet dofs do not move."""
    if observe.dim() != 2 or observe.shape[1] != eq.reduction.model.n_dofs:
        raise ValueError(f"observe must be a (rows, {eq.reduction.model.n_dofs}) matrix, got "
                         f"{tuple(observe.shape)}")
    free = eq.reduction.free_dofs.to(rhs.device)
    with warnings.catch_warnings():   # "sparse CSR tensor support is in beta state"
        warnings.simplefilter("ignore", UserWarning)
        if observe.layout == torch.strided:
            observe_free = observe.to(rhs)[:, free]
        else:
            entries = observe.to_sparse_coo().coalesce()
            rows, cols = entries.indices()
            columns = eq.reduction.free_positions.to(cols.device)[cols]
            keep = columns >= 0
            observe_free = torch.sparse_coo_tensor(
                torch.stack([rows[keep], columns[keep]]), entries.values()[keep],
                (observe.shape[0], free.numel())).coalesce().to_sparse_csr().to(rhs)
        out = rhs.new_empty(rhs.shape[0], observe.shape[0], rhs.shape[2])
        for start, stop, dx_free in solve_directions(eq, sol, rhs):
            count, k = stop - start, dx_free.shape[2]
            observed = observe_free @ dx_free.permute(1, 0, 2).reshape(free.numel(), -1)
            out[start:stop] = -observed.reshape(-1, count, k).permute(1, 0, 2)
    return out
