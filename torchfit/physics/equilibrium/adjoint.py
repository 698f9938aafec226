"""The implicit-function adjoint: the equilibrium as a ``torch.autograd.Function``.

Forward returns ``x*`` ``(F, n_dofs)`` of ``(params, fixed_values)`` (the equilibrium's
cached solution, or a new solve). Backward solves ``K^T lam = g`` on the free dofs with the
factors stored with the solution and returns ``-(dR/dparams)^T lam`` (and, for the
Dirichlet values, the same through ``R`` plus ``g`` on the fixed dofs); the forward-mode
jvp solves ``K dx = -(dR/dparams) v - (dR/dfixed) d_fixed``. ``dR/dparams`` products come
from the model's ``param_derivative`` where it has one and only the parameters are
differentiated (:func:`params_jvp`, :func:`params_vjp`), else from autograd of the
residual at the solution (:func:`residual_at_solution`). Newton is never unrolled: one
solve per product and factor, no factorisation.
"""
from __future__ import annotations

from typing import Any, Protocol

import torch
from torch import Tensor

from ...linalg import active_scopes, within
from .cache import Solution, SolutionCache
from .dirichlet import DirichletReduction
from .model import ModelExtensions


class SolvedEquilibrium(Protocol):
    """What the adjoint uses of :class:`~torchfit.physics.Equilibrium`."""

    reduction: DirichletReduction
    extensions: ModelExtensions
    cache: SolutionCache

    def solution(self, params: Tensor, fixed_values: Tensor, x_init: Any) -> Solution:
        """The solution at ``(params, fixed_values)``, cached or solved."""

    def param_derivative(self, solution: Solution) -> Any:
        """The model's ``param_derivative`` at ``solution`` (built once; it becomes the
        anchor of warm starts)."""


class EquilibriumFunction(torch.autograd.Function):
    """``x*(params, fixed_values)`` with the implicit-function backward and jvp."""

    @staticmethod
    def forward(params: Tensor, fixed_values: Tensor, x_init: Tensor | None,
                eq: SolvedEquilibrium) -> Tensor:  # type: ignore[override]
        return eq.solution(params, fixed_values, x_init).x.clone()

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple, output: Tensor) -> None:
        params, fixed_values, _, eq = inputs
        ctx.eq = eq
        ctx.solution = eq.solution(params, fixed_values, None)  # cache hit: no new work
        # autograd runs a CUDA backward on a thread of its own, outside the caller's
        # counting scopes: there its solves are counted where the forward was
        ctx.scopes = active_scopes()
        ctx.set_materialize_grads(False)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad_x: Tensor | None) -> tuple:  # type: ignore[override]
        if grad_x is None:
            return None, None, None, None
        with within(active_scopes() or ctx.scopes):
            return _backward(ctx, grad_x)

    @staticmethod
    def jvp(ctx: Any, d_params: Tensor | None, d_fixed: Tensor | None, *_: Any) -> Tensor:  # type: ignore[override]
        return _jvp(ctx, d_params, d_fixed)


def _backward(ctx: Any, grad_x: Tensor) -> tuple:
    """The vector-Jacobian product of :class:`EquilibriumFunction` (one transposed solve)."""
    eq: SolvedEquilibrium = ctx.eq
    sol: Solution = ctx.solution
    need_params, need_fixed = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
    if eq.extensions.has_param_derivative and need_params and not need_fixed:
        return params_vjp(eq, sol, grad_x), None, None, None
    free = eq.reduction.free_dofs.to(grad_x.device)
    lam = eq.reduction.solve(sol.factors, grad_x[:, free], transpose=True)
    with torch.enable_grad():
        residual, leaves = residual_at_solution(eq, sol, need_params, need_fixed)
        grads = torch.autograd.grad(residual, leaves, grad_outputs=-lam, allow_unused=True)
    grads = [torch.zeros_like(t) if g is None else g for t, g in zip(leaves, grads)]
    grad_params = grads.pop(0) if need_params else None
    grad_fixed = None
    if need_fixed:
        # Dirichlet values move the fixed dofs directly and the free ones through R.
        grad_fixed = grads.pop(0) + grad_x[:, eq.reduction.fixed_dofs.to(grad_x.device)]
    return grad_params, grad_fixed, None, None


def _jvp(ctx: Any, d_params: Tensor | None, d_fixed: Tensor | None) -> Tensor:
    """The Jacobian-vector product of :class:`EquilibriumFunction` (one solve)."""
    eq: SolvedEquilibrium = ctx.eq
    sol: Solution = ctx.solution
    if eq.extensions.has_param_derivative and d_params is not None and d_fixed is None:
        return params_jvp(eq, sol, d_params)
    tangents = [d for d in (d_params, d_fixed) if d is not None]
    # (dR/dparams) v + (dR/dfixed) d_fixed by the transpose-of-transpose trick:
    # forward-mode AD cannot nest inside this jvp, and two reverse passes through
    # the element-vectorised residual cost no solve.
    with torch.enable_grad():
        residual, leaves = residual_at_solution(eq, sol, d_params is not None,
                                                d_fixed is not None)
        probe = torch.zeros_like(residual, requires_grad=True)
        grads = torch.autograd.grad(residual, leaves, probe, create_graph=True,
                                    allow_unused=True)
        pairing = sum((g * d).sum() for g, d in zip(grads, tangents) if g is not None)
        d_residual = None
        if isinstance(pairing, Tensor) and pairing.requires_grad:
            (d_residual,) = torch.autograd.grad(pairing, probe, allow_unused=True)
    if d_residual is None:
        d_residual = torch.zeros_like(residual)
    dx_free = -eq.reduction.solve(sol.factors, d_residual.detach())
    return eq.reduction.full(dx_free, torch.zeros_like(sol.fixed_values) if d_fixed is None
                             else d_fixed)


def params_jvp(eq: SolvedEquilibrium, sol: Solution, d_params: Tensor) -> Tensor:
    """``(dx*/dparams) d_params`` ``(F, n_dofs)`` by the model's ``param_derivative``: one
    solve with the stored factors, zero on the Dirichlet dofs."""
    free = eq.reduction.free_dofs.to(sol.x.device)
    d_residual = eq.param_derivative(sol).jvp(d_params)[:, free]
    dx_free = -eq.reduction.solve(sol.factors, d_residual.detach())
    return eq.reduction.full(dx_free, torch.zeros_like(sol.fixed_values))


def params_vjp(eq: SolvedEquilibrium, sol: Solution, grad_x: Tensor) -> Tensor:
    """``(dx*/dparams)^T grad_x`` ``(n_params,)`` for ``grad_x`` ``(F, n_dofs)`` by the
    model's ``param_derivative``: one transposed solve with the stored factors."""
    free = eq.reduction.free_dofs.to(grad_x.device)
    lam = eq.reduction.solve(sol.factors, grad_x[:, free], transpose=True)
    lam_full = lam.new_zeros(lam.shape[0], eq.reduction.model.n_dofs).index_copy(1, free, lam)
    return -eq.param_derivative(sol).vjp(lam_full)


def residual_at_solution(eq: SolvedEquilibrium, sol: Solution, wrt_params: bool,
                         wrt_fixed: bool) -> tuple[Tensor, list[Tensor]]:
    """``R_free(x*, params)`` with leaves for the inputs asked for (call under enable_grad).

    The stored full solution is used as is unless the Dirichlet values must be
    differentiated, which avoids rebuilding ``x`` in the common case.
    """
    eq.cache.anchor(sol)
    params = sol.params.detach().requires_grad_(wrt_params)
    leaves = [params] if wrt_params else []
    if wrt_fixed:
        fixed_values = sol.fixed_values.detach().requires_grad_(True)
        free = eq.reduction.free_dofs.to(sol.x.device)
        x = eq.reduction.full(sol.x[:, free].detach(), fixed_values)
        leaves.append(fixed_values)
    else:
        x = sol.x.detach()
    return eq.reduction.free_residual(x, params), leaves

