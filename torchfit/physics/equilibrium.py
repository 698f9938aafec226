"""The generic differentiable equilibrium ``x*(theta)`` with ``R(x*, theta) = 0``.

A physics model supplies its residual ``R(x, params)`` (net force, written in torch,
vectorised over elements and frames) and the values of its sparse tangent
``K = dR/dx`` on a pattern built once per mesh. :class:`Equilibrium` then

* handles Dirichlet degrees of freedom once for every problem: prescribed values per
  frame, residual and tangent restricted to the free dofs;
* solves the free dofs by Newton with a backtracking line search on ``||R||``
  (a linear model is solved with one factorisation and one solve);
* differentiates the solution by the implicit function theorem: backward solves
  ``K^T lam = g`` and returns ``-(dR/dparams)^T lam`` (autograd of the residual);
  the forward-mode jvp solves ``K dx = -(dR/dparams) v``. Newton is never unrolled.

The factorisation of ``K(x*)`` made in forward is kept with the solution. Calling the
equilibrium again with the same parameters and Dirichlet values (as the solvers'
``J v`` products do) returns the stored solution without any new factorisation, so
every backward and jvp at one parameter vector reuses one factorisation. Solutions are
found again while they are among the ``cache_size`` most recent ones *or* while an
autograd graph that used them is alive (a solver's linearisation holds its graph), so
evaluating other points in between never forces a refactorisation.
"""
from __future__ import annotations

import dataclasses
import math
import weakref
from typing import Any, Protocol

import torch
from torch import Tensor

from ..linalg import SparsePattern
from ..linalg.backends import Backend, Factor, SingularMatrixError, get_backend


class EquilibriumModel(Protocol):
    """What a physics model provides to :class:`Equilibrium`.

    Attributes:
        n_dofs: number of scalar degrees of freedom per frame.
        tangent_pattern: ``n_dofs x n_dofs`` pattern of ``dR/dx``.
        linear: ``R`` is affine in ``x`` with a frame-independent tangent.
        symmetric: the tangent is symmetric (an energy Hessian).
    """

    n_dofs: int
    tangent_pattern: SparsePattern
    linear: bool
    symmetric: bool

    def residual(self, x: Tensor, params: Tensor) -> Tensor:
        """Net force ``(F, n_dofs)`` at positions ``x`` ``(F, n_dofs)``."""

    def tangent_values(self, x: Tensor, params: Tensor) -> Tensor:
        """``dR/dx`` contributions ``(F or 1, tangent_pattern.n_contrib)``."""


class NewtonConvergenceError(RuntimeError):
    """Newton did not bring a frame to equilibrium; the message names frame and residual."""


@dataclasses.dataclass
class NewtonOptions:
    """Newton settings (residual norms are per frame, in force units)."""

    max_iter: int = 50
    rtol: float = 1e-10      # relative to the residual norm at the start of the frame
    atol: float = 1e-12      # absolute floor
    max_backtracks: int = 30


@dataclasses.dataclass(eq=False)  # identity semantics: kept in a WeakSet
class _Solution:
    params: Tensor
    fixed_values: Tensor
    x: Tensor                  # (F, n_dofs), full positions
    factors: list[Factor]      # one shared factor (linear model) or one per frame
    newton_iterations: list[int]


class Equilibrium:
    """Differentiable equilibrium solve of a model with Dirichlet dofs.

    Args:
        model: the physics (see :class:`EquilibriumModel`).
        fixed_dofs: ``(n_fixed,)`` indices of Dirichlet dofs (must not be empty unless
            ``allow_no_dirichlet``: a pure-traction elastic problem is singular).
        backend: linear-solve backend, ``'scipy'`` or ``'cg'``.
        newton: :class:`NewtonOptions` for non-linear models.
        cache_size: number of (parameters, solution, factorisations) kept; 2 lets a
            Levenberg-Marquardt trial point be evaluated without dropping the current
            point's factorisation.
    """

    def __init__(self, model: EquilibriumModel, fixed_dofs: Tensor, backend: str | Backend = "scipy",
                 newton: NewtonOptions | None = None, cache_size: int = 2,
                 allow_no_dirichlet: bool = False) -> None:
        fixed = torch.as_tensor(fixed_dofs, dtype=torch.long).reshape(-1)
        if fixed.numel() == 0 and not allow_no_dirichlet:
            raise ValueError("the system has no Dirichlet (fixed) degree of freedom, so its "
                             "stiffness matrix is singular; fix at least one node")
        if fixed.numel() and (fixed.min() < 0 or fixed.max() >= model.n_dofs):
            raise ValueError(f"fixed dofs out of range [0, {model.n_dofs})")
        if torch.unique(fixed).numel() != fixed.numel():
            raise ValueError("fixed dofs contain duplicates")
        self.model = model
        self.fixed_dofs = torch.sort(fixed).values
        is_free = torch.ones(model.n_dofs, dtype=torch.bool)
        is_free[self.fixed_dofs] = False
        self.free_dofs = torch.nonzero(is_free).reshape(-1)
        if self.free_dofs.numel() == 0:
            raise ValueError("every degree of freedom is fixed; nothing to solve")
        self.backend = get_backend(backend)
        self.newton = newton or NewtonOptions()
        self.cache_size = cache_size
        self._cache: list[_Solution] = []
        # Solutions still referenced by a live autograd graph (ctx.solution).
        self._alive: weakref.WeakSet[_Solution] = weakref.WeakSet()
        # Reduced (free-free) tangent pattern and the slots it takes, built once.
        self.free_pattern, self._free_slots = model.tangent_pattern.submatrix(
            self.free_dofs, self.free_dofs)
        self.last_newton_iterations: list[int] = []

    # -- public -----------------------------------------------------------------------
    @property
    def n_fixed(self) -> int:
        return int(self.fixed_dofs.numel())

    def __call__(self, params: Tensor, fixed_values: Tensor, x_init: Tensor | None = None) -> Tensor:
        """Positions at equilibrium, ``(F, n_dofs)``.

        Args:
            params: the model's physical field, e.g. ``(n_springs,)`` stiffness.
            fixed_values: ``(F, n_fixed)`` prescribed Dirichlet values per frame (ordered
                as the sorted ``fixed_dofs``); differentiable too.
            x_init: ``(F, n_dofs)`` start of Newton (non-linear models); defaults to
                zeros with the Dirichlet values inserted.
        """
        if fixed_values.dim() != 2 or fixed_values.shape[1] != self.n_fixed:
            raise ValueError(f"Dirichlet values must have shape (frames, {self.n_fixed}), got "
                             f"{tuple(fixed_values.shape)}")
        if not torch.isfinite(fixed_values).all():
            bad = torch.nonzero(~torch.isfinite(fixed_values))[0].tolist()
            raise ValueError(f"Dirichlet value of frame {bad[0]}, fixed dof "
                             f"{int(self.fixed_dofs[bad[1]])} is NaN or infinite")
        if x_init is not None and x_init.shape != (fixed_values.shape[0], self.model.n_dofs):
            raise ValueError(f"x_init must have shape {(fixed_values.shape[0], self.model.n_dofs)}, "
                             f"got {tuple(x_init.shape)}")
        return _EquilibriumFunction.apply(params, fixed_values, x_init, self)

    def clear_cache(self) -> None:
        self._cache.clear()
        self._alive = weakref.WeakSet()

    # -- internals --------------------------------------------------------------------
    def _lookup(self, params: Tensor, fixed_values: Tensor) -> _Solution | None:
        def same(sol: _Solution) -> bool:
            return (sol.params.shape == params.shape and sol.fixed_values.shape == fixed_values.shape
                    and torch.equal(sol.params, params) and torch.equal(sol.fixed_values, fixed_values))

        for i, sol in enumerate(self._cache):
            if same(sol):
                self._cache.append(self._cache.pop(i))  # most recently used last
                return sol
        for sol in list(self._alive):
            if same(sol):
                self._remember(sol)
                return sol
        return None

    def _remember(self, sol: _Solution) -> None:
        self._cache.append(sol)
        self._alive.add(sol)
        while len(self._cache) > self.cache_size:
            self._cache.pop(0)

    def _full(self, x_free: Tensor, fixed_values: Tensor) -> Tensor:
        x = x_free.new_zeros(x_free.shape[0], self.model.n_dofs)
        x = x.index_copy(1, self.free_dofs.to(x.device), x_free)
        return x.index_copy(1, self.fixed_dofs.to(x.device), fixed_values)

    def _free_residual(self, x: Tensor, params: Tensor) -> Tensor:
        return self.model.residual(x, params)[:, self.free_dofs.to(x.device)]

    def _factorize(self, x: Tensor, params: Tensor) -> list[Factor]:
        contributions = self.model.tangent_values(x, params)
        values = self.model.tangent_pattern.assemble(contributions)[..., self._free_slots.to(x.device)]
        return [self.backend.factorize(self.free_pattern, v, self.model.symmetric) for v in values]

    def _solve(self, factors: list[Factor], rhs: Tensor, transpose: bool = False) -> Tensor:
        """Solve per frame; ``rhs`` is ``(F, n_free)``. One shared factor takes all frames."""
        if len(factors) == 1:
            return factors[0].solve(rhs.T.contiguous(), transpose=transpose).to(rhs.device).T
        return torch.stack([f.solve(r, transpose=transpose).to(rhs.device)
                            for f, r in zip(factors, rhs)])

    def _solve_forward(self, params: Tensor, fixed_values: Tensor, x_init: Tensor | None) -> _Solution:
        n_frames = fixed_values.shape[0]
        free = self.free_dofs.to(params.device)
        if x_init is None:
            x_free = params.new_zeros(n_frames, free.numel())
        else:
            x_free = x_init.detach()[:, free]
        x = self._full(x_free, fixed_values)
        if self.model.linear:
            residual = self._free_residual(x, params)
            factors = self._factorize(x, params)
            x = self._full(x_free - self._solve(factors, residual), fixed_values)
            if not torch.isfinite(x).all():
                raise SingularMatrixError("the linear solve produced non-finite positions; "
                                          "check that all stiffnesses are positive and finite")
            return _Solution(params, fixed_values, x, factors, [1] * n_frames)
        return self._newton(params, fixed_values, x)

    def _newton(self, params: Tensor, fixed_values: Tensor, x: Tensor) -> _Solution:
        opts = self.newton
        n_frames = x.shape[0]
        residual = self._free_residual(x, params)
        norms = torch.linalg.vector_norm(residual, dim=1)
        targets = torch.clamp(opts.rtol * norms, min=opts.atol)
        iterations = [0] * n_frames
        for _ in range(opts.max_iter):
            active = norms > targets
            if not bool(active.any()):
                break
            factors = self._factorize(x, params)
            step = self._solve(factors, -residual)
            step = torch.where(active[:, None], step, torch.zeros_like(step))
            # Backtracking on ||R||, per frame; converged frames stay where they are.
            alpha = torch.ones(n_frames, dtype=x.dtype, device=x.device)
            for _ in range(opts.max_backtracks):
                x_free_trial = x[:, self.free_dofs.to(x.device)] + alpha[:, None] * step
                x_trial = self._full(x_free_trial, fixed_values)
                residual_trial = self._free_residual(x_trial, params)
                norms_trial = torch.linalg.vector_norm(residual_trial, dim=1)
                ok = (norms_trial <= (1 - 1e-4 * alpha) * norms) | ~active | (norms_trial <= targets)
                ok &= torch.isfinite(norms_trial)
                if bool(ok.all()):
                    break
                alpha = torch.where(ok, alpha, alpha * 0.5)
            for f in torch.nonzero(active).reshape(-1).tolist():
                iterations[f] += 1
            x, residual, norms = x_trial, residual_trial, norms_trial
        if bool((norms > targets).any()) or not torch.isfinite(norms).all():
            frame = int(torch.argmax(torch.nan_to_num(norms / targets, nan=math.inf)))
            raise NewtonConvergenceError(
                f"Newton did not converge in frame {frame}: residual norm "
                f"{float(norms[frame]):.3e} > tolerance {float(targets[frame]):.3e} after "
                f"{opts.max_iter} iterations; raise newton.max_iter, reduce the load step, or "
                "check the material parameters")
        # The adjoint needs the tangent at the solution itself.
        factors = self._factorize(x, params)
        return _Solution(params, fixed_values, x, factors, iterations)

    def solution(self, params: Tensor, fixed_values: Tensor, x_init: Tensor | None) -> _Solution:
        params = params.detach()
        fixed_values = fixed_values.detach()
        cached = self._lookup(params, fixed_values)
        if cached is not None:
            return cached
        sol = self._solve_forward(params, fixed_values, x_init)
        sol.params, sol.fixed_values = params.clone(), fixed_values.clone()
        self._remember(sol)
        self.last_newton_iterations = sol.newton_iterations
        return sol


class _EquilibriumFunction(torch.autograd.Function):
    @staticmethod
    def forward(params: Tensor, fixed_values: Tensor, x_init: Tensor | None,
                eq: Equilibrium) -> Tensor:  # type: ignore[override]
        return eq.solution(params, fixed_values, x_init).x.clone()

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple, output: Tensor) -> None:
        params, fixed_values, _, eq = inputs
        ctx.eq = eq
        ctx.solution = eq.solution(params, fixed_values, None)  # cache hit: no new work
        ctx.set_materialize_grads(False)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad_x: Tensor | None) -> tuple:  # type: ignore[override]
        if grad_x is None:
            return None, None, None, None
        eq: Equilibrium = ctx.eq
        sol: _Solution = ctx.solution
        free = eq.free_dofs.to(grad_x.device)
        lam = eq._solve(sol.factors, grad_x[:, free], transpose=True)
        need_params, need_fixed = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        with torch.enable_grad():
            residual, leaves = _residual_at_solution(eq, sol, need_params, need_fixed)
            grads = torch.autograd.grad(residual, leaves, grad_outputs=-lam, allow_unused=True)
        grads = [torch.zeros_like(t) if g is None else g for t, g in zip(leaves, grads)]
        grad_params = grads.pop(0) if need_params else None
        grad_fixed = None
        if need_fixed:
            # Dirichlet values move the fixed dofs directly and the free ones through R.
            grad_fixed = grads.pop(0) + grad_x[:, eq.fixed_dofs.to(grad_x.device)]
        return grad_params, grad_fixed, None, None

    @staticmethod
    def jvp(ctx: Any, d_params: Tensor | None, d_fixed: Tensor | None, *_: Any) -> Tensor:  # type: ignore[override]
        eq: Equilibrium = ctx.eq
        sol: _Solution = ctx.solution
        tangents = [d for d in (d_params, d_fixed) if d is not None]
        # (dR/dparams) v + (dR/dfixed) d_fixed by the transpose-of-transpose trick:
        # forward-mode AD cannot nest inside this jvp, and two reverse passes through
        # the element-vectorised residual cost no solve.
        with torch.enable_grad():
            residual, leaves = _residual_at_solution(eq, sol, d_params is not None,
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
        dx_free = -eq._solve(sol.factors, d_residual.detach())
        return eq._full(dx_free, torch.zeros_like(sol.fixed_values) if d_fixed is None else d_fixed)


def _residual_at_solution(eq: Equilibrium, sol: _Solution, wrt_params: bool,
                          wrt_fixed: bool) -> tuple[Tensor, list[Tensor]]:
    """``R_free(x*, params)`` with leaves for the inputs asked for (call under enable_grad).

    The stored full solution is used as is unless the Dirichlet values must be
    differentiated, which avoids rebuilding ``x`` in the common case.
    """
    params = sol.params.detach().requires_grad_(wrt_params)
    leaves = [params] if wrt_params else []
    if wrt_fixed:
        fixed_values = sol.fixed_values.detach().requires_grad_(True)
        x = eq._full(sol.x[:, eq.free_dofs.to(sol.x.device)].detach(), fixed_values)
        leaves.append(fixed_values)
    else:
        x = sol.x.detach()
    return eq._free_residual(x, params), leaves
