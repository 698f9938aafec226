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

Extensions a model may offer (all optional, detected once):

* ``tangent_values(x, params, projected=True)``: a positive semi-definite modification
  of the tangent (e.g. the eigenvalue-clamped Hessian of stable neo-Hookean). Newton
  uses it for its search direction while a frame is far from equilibrium; the
  factorisation kept for the adjoint and jvp is always the exact ``dR/dx`` at ``x*``.
* ``param_derivative(x, params)``: an object with ``jvp(v) -> (F, n_dofs)`` (``dR/dparams
  v``) and ``vjp(w (F, n_dofs)) -> (n_params,)``. When present, backward and jvp use it
  instead of reverse-mode autograd of the residual (it is built once per solution). If
  it also has ``matmul(V (n_params, k)) -> (F, n_dofs, k)`` (a new tensor),
  :meth:`Equilibrium.jacobian` takes all ``k`` directions of every frame from one call.

The whole Jacobian: :meth:`Equilibrium.jacobian` returns ``(dx*/dparams) V`` for ``k``
directions at once (``V`` ``(n_params, k)``): one solve with ``k`` right-hand sides per
stored factor (``F`` solves, ``F k`` columns; one solve of ``F k`` columns for a shared
factor), no factorisation when the solution is cached. With few parameters this is the
dense Jacobian in the time of about one forward-mode product per frame block, where
``k`` separate jvps cost ``k F`` solves and ``k`` passes through the model.

Warm start: with ``warm_start=True`` (the default), a new parameter vector with the
same Dirichlet values starts Newton from an earlier solution (Levenberg-Marquardt and
Gauss-Newton evaluate nearby points one after the other): the one derivatives were last
taken at (a solver's linearisation point) while it is alive, else the most recently used
one. A trial point after a rejected step thus starts from the point the solver's model
linearises, not from the rejected trial, which near a fold may sit in another equilibrium.
Simulations that are not part of a solver's sequence (a synthetic target, a baseline) run
inside :meth:`Equilibrium.independent`: they start cold and never seed a later warm start
(they are still found again at the same parameters), so that where a frame has several
equilibria what a fit sees does not depend on them.
Convergence is still judged against the reference residual of the cold start, so results
agree with a cold start to the Newton tolerance where the equilibrium is unique; a warm
start that fails falls back to the cold start.
"""
from __future__ import annotations

import contextlib
import dataclasses
import inspect
import math
import warnings
import weakref
from typing import Any, Callable, Iterator, Protocol

import torch
from torch import Tensor

from ..errors import SimulationError
from ..linalg import SparsePattern, csr_matrix
from ..linalg.backends import Backend, Factor, SingularMatrixError, get_backend
from ..linalg.cudss import gpu_memory_error


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
        """``dR/dx`` contributions ``(F or 1, tangent_pattern.n_contrib)``.

        A model may accept a keyword ``projected: bool = False`` (see the module
        docstring); models without it are called without it.
        """


class NewtonConvergenceError(SimulationError):
    """Newton did not bring a frame to equilibrium; the message names frame and residual."""


@dataclasses.dataclass
class NewtonOptions:
    """Newton settings (residual norms are per frame, in force units)."""

    max_iter: int = 50
    rtol: float = 1e-10      # relative to the residual norm at the (cold) start of the frame
    atol: float = 1e-12      # absolute floor
    max_backtracks: int = 30
    # Models with a projected (PSD) tangent: a frame uses it while far from equilibrium
    # and switches to the exact tangent (quadratic convergence) once its residual is below
    # exact_below * reference or a projected step reduced it by less than the factor
    # `stagnation` (projected Newton only converges linearly where the projection is
    # active). A step whose line search fails switches to the other tangent.
    exact_below: float = 0.1
    stagnation: float = 0.5
    # A warm start (from the last solution) that has not converged after this many
    # iterations gives way to the cold start.
    warm_max_iter: int = 10
    # Give up early on a frame whose residual has not halved in this many iterations
    # (a diverging or stalled Newton; 0 disables the check). Once per frame, a model with
    # an energy and a projected tangent that stalls below exact_below * reference with a
    # flat energy (a saddle at a fold: the exact step points uphill, projected steps creep
    # along the negative curvature) instead finishes at that equilibrium with the exact
    # tangent and a line search on ||R|| alone.
    stall_iter: int = 10


@dataclasses.dataclass(eq=False)  # identity semantics: kept in a WeakSet
class _Solution:
    params: Tensor
    fixed_values: Tensor
    x: Tensor                  # (F, n_dofs), full positions
    factors: list[Factor]      # one shared factor (linear model) or one per frame
    newton_iterations: list[int]
    reference: Tensor | None = None        # (F,) residual norms of the cold start
    param_derivative: Any = None           # model.param_derivative at x*, built lazily
    warm_started: bool = False
    seeds: bool = True         # may warm-start another point (False: an independent() solve)


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
        warm_start: start Newton from the last solution with the same Dirichlet values.
        linear_refinement: iterative-refinement steps after the solve of a linear model.
    """

    def __init__(self, model: EquilibriumModel, fixed_dofs: Tensor, backend: str | Backend = "scipy",
                 newton: NewtonOptions | None = None, cache_size: int = 2,
                 allow_no_dirichlet: bool = False, warm_start: bool = True,
                 linear_refinement: int = 0) -> None:
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
        # position of every dof among the free ones (-1: Dirichlet)
        self.free_positions = torch.full((model.n_dofs,), -1, dtype=torch.long)
        self.free_positions[self.free_dofs] = torch.arange(self.free_dofs.numel())
        # CSR layouts of dR_free/dparams, one per entry pattern (EquilibriumLinearization)
        self._layouts: list[_FreeMatrixLayout] = []
        if self.free_dofs.numel() == 0:
            raise ValueError("every degree of freedom is fixed; nothing to solve")
        self.backend = get_backend(backend)
        self.newton = newton or NewtonOptions()
        self.cache_size = cache_size
        self._cache: list[_Solution] = []
        # Solutions still referenced by a live autograd graph (ctx.solution).
        self._alive: weakref.WeakSet[_Solution] = weakref.WeakSet()
        # The solution derivatives were last taken at (the first choice of a warm start).
        self._anchor: weakref.ref[_Solution] | None = None
        # Reduced (free-free) tangent pattern and the slots it takes, built once.
        self.free_pattern, self._free_slots = model.tangent_pattern.submatrix(
            self.free_dofs, self.free_dofs)
        self.last_newton_iterations: list[int] = []
        self.last_warm_started = False
        self.warm_start = bool(warm_start)
        self._independent = False     # inside independent(): cold starts, no seeds
        # Linear models: steps of iterative refinement after the solve (one residual and
        # one solve with the same factor each; removes the round-off of a far start).
        self.linear_refinement = int(linear_refinement)
        self._accepts_projected = _accepts_keyword(model.tangent_values, "projected")
        self._has_param_derivative = callable(getattr(model, "param_derivative", None))
        # a symmetric model with an energy (R = dEnergy/dx) gets the energy line search
        self._has_energy = bool(model.symmetric) and callable(getattr(model, "energy", None))
        self._has_residual_and_energy = callable(getattr(model, "residual_and_energy", None))
        # the residual of one frame depends on that frame's positions only (no per-frame
        # loads): Newton's line search then evaluates the frames still iterating alone
        self._frame_independent = bool(getattr(model, "frame_independent", False))

    # -- public -----------------------------------------------------------------------
    @property
    def n_fixed(self) -> int:
        return int(self.fixed_dofs.numel())

    def __call__(self, params: Tensor, fixed_values: Tensor,
                 x_init: Tensor | Callable[[], Tensor] | None = None) -> Tensor:
        """Positions at equilibrium, ``(F, n_dofs)``.

        Args:
            params: the model's physical field, e.g. ``(n_springs,)`` stiffness.
            fixed_values: ``(F, n_fixed)`` prescribed Dirichlet values per frame (ordered
                as the sorted ``fixed_dofs``); differentiable too.
            x_init: ``(F, n_dofs)`` cold start of Newton (non-linear models), or a
                function returning it (called only when no warm start is used);
                defaults to zeros with the Dirichlet values inserted.
        """
        if fixed_values.dim() != 2 or fixed_values.shape[1] != self.n_fixed:
            raise ValueError(f"Dirichlet values must have shape (frames, {self.n_fixed}), got "
                             f"{tuple(fixed_values.shape)}")
        if not torch.isfinite(fixed_values).all():
            bad = torch.nonzero(~torch.isfinite(fixed_values))[0].tolist()
            raise ValueError(f"Dirichlet value of frame {bad[0]}, fixed dof "
                             f"{int(self.fixed_dofs[bad[1]])} is NaN or infinite")
        if isinstance(x_init, Tensor):
            self._check_x_init(x_init, fixed_values.shape[0])
        return _EquilibriumFunction.apply(params, fixed_values, x_init, self)

    def _check_x_init(self, x_init: Tensor, n_frames: int) -> None:
        if x_init.shape != (n_frames, self.model.n_dofs):
            raise ValueError(f"x_init must have shape {(n_frames, self.model.n_dofs)}, "
                             f"got {tuple(x_init.shape)}")

    def linearized_start(self, params: Tensor, fixed_values: Tensor, x_ref: Tensor) -> Tensor:
        """One Newton step from ``x_ref`` that moves the Dirichlet dofs to their values.

        ``x = x_ref + dx`` with ``dx`` equal to ``fixed_values - x_ref`` on the Dirichlet
        dofs and ``K_ff dx_f = -(R_f(x_ref) + K_fd dx_d)`` on the free ones (exact tangent
        at ``x_ref``). From the rest shape of an elastic body this is the linear-elastic
        solution: a good cold start for Newton. ``x_ref`` is ``(1, n_dofs)`` (one
        factorisation for every frame) or ``(F, n_dofs)``. No gradient flows through it.
        """
        with torch.no_grad():
            n_frames = fixed_values.shape[0]
            if x_ref.dim() != 2 or x_ref.shape[0] not in (1, n_frames) \
                    or x_ref.shape[1] != self.model.n_dofs:
                raise ValueError(f"x_ref must have shape (1 or {n_frames}, {self.model.n_dofs}), "
                                 f"got {tuple(x_ref.shape)}")
            params = params.detach()
            fixed = self.fixed_dofs.to(x_ref.device)
            free = self.free_dofs.to(x_ref.device)
            contributions = self._tangent(x_ref, params)
            values = self.model.tangent_pattern.assemble(contributions)
            dx = x_ref.new_zeros(n_frames, self.model.n_dofs)
            dx[:, fixed] = fixed_values.detach() - x_ref[:, fixed]
            coupling = self.model.tangent_pattern.matvec(values, dx)[:, free]
            residual = self.model.residual(x_ref, params)[:, free]
            factors = [self.backend.factorize(self.free_pattern, v[self._free_slots.to(v.device)],
                                              self.model.symmetric) for v in values]
            dx[:, free] = -self._solve(factors, (residual + coupling).expand(n_frames, -1))
            return x_ref + dx

    def jacobian(self, params: Tensor, fixed_values: Tensor, directions: Tensor,
                 x_init: Tensor | Callable[[], Tensor] | None = None,
                 observe: Tensor | None = None) -> Tensor:
        """``(dx*/dparams) directions`` of every frame, ``(F, n_dofs, k)`` (no graph), or
        ``observe (dx*/dparams) directions``, ``(F, n_rows, k)``.

        Args:
            params: the model's field (as for ``__call__``).
            fixed_values: ``(F, n_fixed)`` Dirichlet values (held fixed: zero rows there).
            directions: ``(n_params, k)`` parameter directions ``V``.
            x_init: cold start if the solution must be computed (as for ``__call__``).
            observe: optional sparse ``(n_rows, n_dofs)`` matrix applied to every frame's
                columns as soon as they are solved (what a problem observes of the
                positions): the ``(F, n_dofs, k)`` result is then never formed.

        The solution for ``(params, fixed_values)`` is taken from the cache (or computed
        exactly as the forward does). ``K dX = -(dR/dparams) V`` is then solved with the
        stored factors: one solve with ``k`` right-hand sides per frame (``F`` solves,
        ``F k`` columns; blocks of frames for a shared factor), no new
        factorisation. ``(dR/dparams) V`` comes from the model's
        ``param_derivative(...).matmul`` when it has one, else one ``jvp`` of it per column,
        else the generic autograd route of :meth:`__call__`'s jvp, column by column.
        Column ``j`` equals the forward-mode jvp along ``directions[:, j]``.
        """
        if fixed_values.dim() != 2 or fixed_values.shape[1] != self.n_fixed:
            raise ValueError(f"Dirichlet values must have shape (frames, {self.n_fixed}), got "
                             f"{tuple(fixed_values.shape)}")
        if directions.dim() != 2 or directions.shape[0] != params.numel():
            raise ValueError(f"directions must have shape ({params.numel()}, k), got "
                             f"{tuple(directions.shape)}")
        if isinstance(x_init, Tensor):
            self._check_x_init(x_init, fixed_values.shape[0])
        with torch.no_grad():
            sol = self.solution(params, fixed_values, x_init)
        directions = directions.detach().to(sol.x)
        out = self._residual_directions(sol, directions)      # (F, n_dofs, k), overwritten
        free = self.free_dofs.to(out.device)
        if observe is not None:
            return self._observed_jacobian(sol, out, observe)
        for start, stop, dx_free in self._solve_directions(sol, out):
            out[start:stop].zero_()               # the Dirichlet rows stay 0
            out[start:stop, free, :] = -dx_free
        return out

    def _solve_directions(self, sol: _Solution, rhs: Tensor):
        """Yield ``(start, stop, K^{-1} rhs)`` for frames ``start:stop`` on the free dofs,
        ``(stop - start, n_free, k)``, for ``rhs`` ``(F, n_dofs, k)``. One shared factor:
        frames in blocks of about 1024 right-hand sides (one solve of all ``F k`` columns
        was 3.6x slower with PARDISO on the arm: 9,216 columns); else one solve per frame.
        A block is read before it is yielded, so the caller may overwrite it in ``rhs``."""
        free = self.free_dofs.to(rhs.device)
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

    def _observed_jacobian(self, sol: _Solution, rhs: Tensor, observe: Tensor) -> Tensor:
        """``-observe K^{-1} rhs`` per frame, ``(F, n_rows, k)``, for ``rhs``
        ``(F, n_dofs, k)`` (the residual directions). Only the free columns of ``observe``
        matter: Dirichlet dofs do not move."""
        if observe.dim() != 2 or observe.shape[1] != self.model.n_dofs:
            raise ValueError(f"observe must be a (rows, {self.model.n_dofs}) matrix, got "
                             f"{tuple(observe.shape)}")
        free = self.free_dofs.to(rhs.device)
        with warnings.catch_warnings():   # "sparse CSR tensor support is in beta state"
            warnings.simplefilter("ignore", UserWarning)
            if observe.layout == torch.strided:
                observe_free = observe.to(rhs)[:, free]
            else:
                entries = observe.to_sparse_coo().coalesce()
                rows, cols = entries.indices()
                columns = self.free_positions.to(cols.device)[cols]
                keep = columns >= 0
                observe_free = torch.sparse_coo_tensor(
                    torch.stack([rows[keep], columns[keep]]), entries.values()[keep],
                    (observe.shape[0], free.numel())).coalesce().to_sparse_csr().to(rhs)
            out = rhs.new_empty(rhs.shape[0], observe.shape[0], rhs.shape[2])
            for start, stop, dx_free in self._solve_directions(sol, rhs):
                count, k = stop - start, dx_free.shape[2]
                observed = observe_free @ dx_free.permute(1, 0, 2).reshape(free.numel(), -1)
                out[start:stop] = -observed.reshape(-1, count, k).permute(1, 0, 2)
        return out

    def _free_matrix_layout(self, rows: Tensor, cols: Tensor, shape: tuple[int, int],
                            n_frames: int) -> "_FreeMatrixLayout | None":
        """The CSR layout for this entry pattern (cached: one per pattern in use), or
        ``None`` when the entries repeat a position (then the products use jvp/vjp)."""
        layouts = self._layouts
        for layout in layouts:
            if layout.matches(rows, cols, shape):
                return layout if layout.unique else None
        layout = _FreeMatrixLayout(rows, cols, shape, n_frames, self.free_positions,
                                   self.free_dofs.numel())
        layouts.append(layout)
        del layouts[:-4]          # a handful of frame counts, never unbounded
        return layout if layout.unique else None

    def free_position(self, dofs: Tensor) -> Tensor:
        """Rows of ``dofs`` among the free dofs (the layout of
        :meth:`EquilibriumLinearization.free_jvp`); a Dirichlet dof is an error."""
        positions = self.free_positions[torch.as_tensor(dofs, dtype=torch.long).cpu()]
        if bool((positions < 0).any()):
            raise ValueError("a Dirichlet dof has no free position (its derivative is 0)")
        return positions

    def linearization(self, params: Tensor, fixed_values: Tensor,
                      x_init: Tensor | Callable[[], Tensor] | None = None
                      ) -> EquilibriumLinearization:
        """The solution at ``(params, fixed_values)`` with explicit derivative products
        (:class:`EquilibriumLinearization`), for models with ``param_derivative``.

        The solution is taken from the cache or computed exactly as :meth:`__call__` does
        (same Newton, same factorisation, same errors); no autograd graph is built.
        """
        if not self._has_param_derivative:
            raise TypeError(f"{type(self.model).__name__} has no param_derivative: use the "
                            "differentiable call (autograd) for its derivative products")
        if fixed_values.dim() != 2 or fixed_values.shape[1] != self.n_fixed:
            raise ValueError(f"Dirichlet values must have shape (frames, {self.n_fixed}), got "
                             f"{tuple(fixed_values.shape)}")
        if isinstance(x_init, Tensor):
            self._check_x_init(x_init, fixed_values.shape[0])
        with torch.no_grad():
            return EquilibriumLinearization(self, self.solution(params, fixed_values, x_init))

    def _residual_directions(self, sol: _Solution, directions: Tensor) -> Tensor:
        """``(dR/dparams) V`` ``(F, n_dofs, k)`` at the solution (a fresh tensor)."""
        k = directions.shape[1]
        if self._has_param_derivative:
            derivative = self._param_derivative(sol)
            if callable(getattr(derivative, "matmul", None)):
                return derivative.matmul(directions).detach().to(sol.x)   # a new tensor
            return torch.stack([derivative.jvp(directions[:, j]).detach().to(sol.x)
                                for j in range(k)], dim=-1)
        out = sol.x.new_zeros(sol.x.shape[0], self.model.n_dofs, k)
        if k == 0:
            return out
        free = self.free_dofs.to(sol.x.device)
        with torch.enable_grad():
            residual, leaves = _residual_at_solution(self, sol, True, False)
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

    def adopt(self, params: Tensor, fixed_values: Tensor, x: Tensor,
              factors: list[Factor] | None = None) -> list[Factor]:
        """Register a known solution ``x`` ``(F, n_dofs)`` of ``(params, fixed_values)``.

        For callers that stored or recomputed an equilibrium themselves (a time
        integrator replaying its steps for an adjoint): no Newton iteration is run; the
        exact tangent at ``x`` is factorised (one counted factorisation per stored factor,
        none when ``factors`` from an earlier solve of the same point are handed in) and
        the solution is cached, so that a following call with the same ``params`` and
        ``fixed_values`` returns ``x`` and its backward, jvp and :meth:`jacobian` are the
        usual implicit-function adjoint with that factor. The caller vouches that
        ``R(x, params) = 0`` on the free dofs; the Dirichlet dofs of ``x`` are replaced by
        ``fixed_values``. Returns the factors used.
        """
        params = params.detach()
        fixed_values = fixed_values.detach()
        cached = self._lookup(params, fixed_values)
        if cached is not None:
            return cached.factors
        if x.dim() != 2 or x.shape != (fixed_values.shape[0], self.model.n_dofs):
            raise ValueError(f"x must have shape {(fixed_values.shape[0], self.model.n_dofs)}, "
                             f"got {tuple(x.shape)}")
        x = self._full(x.detach()[:, self.free_dofs.to(x.device)], fixed_values)
        if factors is None:
            factors = self._factorize(x, params)
        sol = _Solution(params.clone(), fixed_values.clone(), x, list(factors),
                        [0] * x.shape[0])
        self._remember(sol)
        return sol.factors

    def restore(self, solution: _Solution) -> None:
        """Put a solution that :meth:`solution` returned earlier back into the cache (with its
        factors and its parameter derivative): no Newton, no factorisation."""
        if not any(sol is solution for sol in self._cache):
            self._remember(solution)

    def clear_cache(self) -> None:
        self._cache.clear()
        self._alive = weakref.WeakSet()
        self._anchor = None

    @contextlib.contextmanager
    def independent(self) -> Iterator[None]:
        """Within: every new solve starts cold (from ``x_init``, not from an earlier
        solution) and its solution never warm-starts a later one, unless derivatives are
        taken at it or it is asked for again outside. A solution already cached at the same
        parameters and Dirichlet values is returned as it is (no new solve).

        For simulations beside a solver's sequence: a synthetic target, the homogeneous
        baseline of a report. Where a frame has several equilibria (a fold), a warm start
        from them would put the fit on their branch.
        """
        before = self._independent
        self._independent = True
        try:
            yield
        finally:
            self._independent = before

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

    def _tangent(self, x: Tensor, params: Tensor, projected: bool = False) -> Tensor:
        """Tangent contributions ``(F or 1, n_contrib)`` (exact unless ``projected``)."""
        if projected and self._accepts_projected:
            return self.model.tangent_values(x, params, projected=True)
        return self.model.tangent_values(x, params)

    def _free_values(self, contributions: Tensor) -> Tensor:
        slots = self._free_slots.to(contributions.device)
        return self.model.tangent_pattern.assemble(contributions)[..., slots]

    def _energy(self, x: Tensor, params: Tensor) -> Tensor:
        """The model's energy per frame ``(F,)`` (the Dirichlet dofs' part is constant)."""
        return self.model.energy(x, params).detach()

    def _evaluate(self, x_frames: Tensor, frames: Tensor, x_all: Tensor, params: Tensor,
                  with_energy: bool) -> tuple[Tensor, Tensor | None]:
        """Free residual (and energy) at positions ``x_frames`` of the frames ``frames``.

        A model whose residual does not depend on the frame (``frame_independent``, e.g.
        elasticity: the frames differ only in their Dirichlet values) is evaluated on those
        frames alone; any other (per-frame loads) on every frame of ``x_all`` with
        ``x_frames`` put in.
        """
        if self._frame_independent or frames.numel() == x_all.shape[0]:
            x = x_frames
        else:
            x = x_all.clone()
            x[frames] = x_frames
        if with_energy:
            residual, energy = self._residual_and_energy(x, params)
        else:
            residual, energy = self._free_residual(x, params), None
        if x is not x_frames:
            residual = residual[frames]
            energy = None if energy is None else energy[frames]
        return residual, energy

    def _residual_and_energy(self, x: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
        """Free residual ``(F, n_free)`` and energy ``(F,)`` (one pass where the model
        offers ``residual_and_energy``: one SVD per element instead of two)."""
        if self._has_residual_and_energy:
            residual, energy = self.model.residual_and_energy(x, params)
            return residual[:, self.free_dofs.to(x.device)], energy.detach()
        return self._free_residual(x, params), self._energy(x, params)

    def _factorize(self, x: Tensor, params: Tensor) -> list[Factor]:
        """Factors of the exact tangent: one shared or one per frame."""
        values = self._free_values(self._tangent(x, params))
        return [self.backend.factorize(self.free_pattern, v, self.model.symmetric) for v in values]

    def _solve(self, factors: list[Factor], rhs: Tensor, transpose: bool = False) -> Tensor:
        """Solve per frame; ``rhs`` is ``(F, n_free)``. One shared factor takes all frames."""
        if len(factors) == 1:
            return factors[0].solve(rhs.T.contiguous(), transpose=transpose).to(rhs.device).T
        return torch.stack([f.solve(r, transpose=transpose).to(rhs.device)
                            for f, r in zip(factors, rhs)])

    def _cold_start(self, params: Tensor, fixed_values: Tensor,
                    x_init: Tensor | Callable[[], Tensor] | None) -> Tensor:
        n_frames = fixed_values.shape[0]
        free = self.free_dofs.to(params.device)
        if x_init is None:
            x_free = params.new_zeros(n_frames, free.numel())
        else:
            if callable(x_init) and not isinstance(x_init, Tensor):
                x_init = x_init()
                self._check_x_init(x_init, n_frames)
            x_free = x_init.detach()[:, free]
        return self._full(x_free, fixed_values)

    def _warm_source(self, fixed_values: Tensor) -> _Solution | None:
        """The solution derivatives were last taken at, else the most recently used one
        (unless it came from :meth:`independent`), if it has the same Dirichlet values;
        ``None`` inside :meth:`independent`."""
        if not self.warm_start or self.model.linear or self._independent:
            return None
        anchor = self._anchor() if self._anchor is not None else None
        recent = [sol for sol in self._cache[-1:] if sol.seeds]
        for sol in ([anchor] if anchor is not None else []) + recent:
            if sol.fixed_values.shape == fixed_values.shape and sol.reference is not None \
                    and torch.equal(sol.fixed_values, fixed_values):
                return sol
        return None

    def _solve_forward(self, params: Tensor, fixed_values: Tensor,
                       x_init: Tensor | Callable[[], Tensor] | None) -> _Solution:
        n_frames = fixed_values.shape[0]
        if self.model.linear:
            # Any start gives the solution in one step: skip a start that must be computed.
            x = self._cold_start(params, fixed_values, x_init if isinstance(x_init, Tensor) else None)
            x_free = x[:, self.free_dofs.to(x.device)]
            residual = self._free_residual(x, params)
            factors = self._factorize(x, params)
            x = self._full(x_free - self._solve(factors, residual), fixed_values)
            for _ in range(self.linear_refinement):
                x_free = x[:, self.free_dofs.to(x.device)]
                x = self._full(x_free - self._solve(factors, self._free_residual(x, params)),
                               fixed_values)
            if not torch.isfinite(x).all():
                raise SingularMatrixError("the linear solve produced non-finite positions; "
                                          "check that all stiffnesses are positive and finite")
            return _Solution(params, fixed_values, x, factors, [1] * n_frames)
        source = self._warm_source(fixed_values)
        if source is not None:
            try:
                sol = self._newton(params, fixed_values, source.x.detach().clone(),
                                   source.reference, max_iter=min(self.newton.warm_max_iter,
                                                                  self.newton.max_iter))
                sol.warm_started = True
                return sol
            except (NewtonConvergenceError, SingularMatrixError):
                pass   # the cold start below decides (and reports a failure)
        return self._newton(params, fixed_values, self._cold_start(params, fixed_values, x_init))

    def _newton(self, params: Tensor, fixed_values: Tensor, x: Tensor,
                reference: Tensor | None = None, max_iter: int | None = None) -> _Solution:
        opts = self.newton
        max_iter = opts.max_iter if max_iter is None else max_iter
        n_frames = x.shape[0]
        free = self.free_dofs.to(x.device)
        if self._has_energy:
            # one pass (one decomposition per element) for both; the tangent at x reuses it
            residual, energy = self._residual_and_energy(x, params)
        else:
            residual, energy = self._free_residual(x, params), None
        norms = torch.linalg.vector_norm(residual, dim=1)
        if reference is None:
            reference = norms.clone()
        targets = torch.clamp(opts.rtol * reference, min=opts.atol)
        iterations = [0] * n_frames
        can_project = self._accepts_projected
        # Per frame: exact tangent (True) or the model's projected one (False).
        exact = ~(norms > opts.exact_below * reference) if can_project else \
            torch.ones(n_frames, dtype=torch.bool, device=x.device)
        history = [norms]
        # An energy (the residual is its gradient) makes the line search an Armijo search
        # on it as well: a projected (PSD) Newton direction always descends the energy,
        # not always ||R|| (inverted elements, folds), so a step is taken when either the
        # energy or ||R|| decreases enough.
        energies = [energy]
        stalled = False
        # Frames finishing at a saddle of the energy (below): exact tangent, ||R|| line search.
        saddle = torch.zeros(n_frames, dtype=torch.bool, device=x.device)
        window = torch.zeros(n_frames, dtype=torch.long, device=x.device)  # stall window start
        for _ in range(max_iter):
            active = norms > targets
            if not bool(active.any()):
                break
            if opts.stall_iter and len(history) > opts.stall_iter:
                back = len(history) - 1 - opts.stall_iter
                before = history[-1 - opts.stall_iter]
                stuck = active & ~(norms <= 0.5 * before) & (window <= back)
                if energy is not None:
                    # still descending the energy: not stalled (nonconvex stretches)
                    earlier = energies[-1 - opts.stall_iter]
                    stuck &= ~(energy < earlier - 1e-10 * earlier.abs())
                    # Stuck close to equilibrium with the energy flat: x sits at a saddle (a
                    # fold), where the exact step points uphill and the projected one only
                    # creeps along the negative curvature (hundreds of iterations). Finish
                    # at the saddle instead, once per frame: it is an equilibrium, found to
                    # the tolerance with the exact tangent in a few steps.
                    near_equilibrium = norms <= opts.exact_below * reference
                    finish = stuck & ~saddle & near_equilibrium & can_project
                    if bool(finish.any()):
                        saddle = saddle | finish
                        exact = exact | finish
                        window = torch.where(finish, len(history), window)
                        stuck = stuck & ~finish
                if bool(stuck.any()):
                    stalled = True
                    break
            frames = torch.nonzero(active).reshape(-1)
            use_exact = exact[frames]
            contributions = None
            if bool(use_exact.any()):
                contributions = self._tangent(x[frames], params)
            if not bool(use_exact.all()):
                projected = self._tangent(x[frames], params, projected=True)
                contributions = projected if contributions is None else torch.where(
                    use_exact[:, None], contributions.expand_as(projected), projected)
            values = self._free_values(contributions)
            if values.shape[0] == 1 and frames.numel() > 1:
                factors = [self.backend.factorize(self.free_pattern, values[0],
                                                  self.model.symmetric)]
            else:
                factors = [self.backend.factorize(self.free_pattern, v, self.model.symmetric)
                           for v in values]
            step = torch.zeros_like(residual)
            step[frames] = self._solve(factors, -residual[frames])
            slope = (residual * step).sum(dim=1)        # dEnergy/dalpha at alpha = 0
            if energy is not None and can_project:
                # an exact tangent that is not positive definite can point uphill: take
                # the projected one for those frames instead
                uphill = active & (slope >= 0) & exact & ~saddle
                if bool(uphill.any()):
                    again = torch.nonzero(uphill).reshape(-1)
                    projected = self._free_values(self._tangent(x[again], params, projected=True))
                    redo = [self.backend.factorize(self.free_pattern, v, self.model.symmetric)
                            for v in projected]
                    step[again] = self._solve(redo, -residual[again])
                    slope = (residual * step).sum(dim=1)
                    exact = exact & ~uphill
            # Backtracking on ||R|| (and the energy), per frame, on the active frames only
            # (a converged frame costs nothing while a hard one is still iterating).
            x_a, step_a, norms_a = x[frames], step[frames], norms[frames]
            slope_a, targets_a, fixed_a = slope[frames], targets[frames], fixed_values[frames]
            energy_a = energy[frames] if energy is not None else None
            alpha = torch.ones(frames.numel(), dtype=x.dtype, device=x.device)
            energy_trial = energy_a
            for _ in range(opts.max_backtracks):
                x_trial = self._full(x_a[:, free] + alpha[:, None] * step_a, fixed_a)
                residual_trial, energy_trial = self._evaluate(x_trial, frames, x, params,
                                                              energy_a is not None)
                norms_trial = torch.linalg.vector_norm(residual_trial, dim=1)
                ok = (norms_trial <= (1 - 1e-4 * alpha) * norms_a) | (norms_trial <= targets_a)
                if energy_a is not None:
                    ok |= (slope_a < 0) & (energy_trial <= energy_a + 1e-4 * alpha * slope_a) \
                        & ~saddle[frames]
                    ok &= torch.isfinite(energy_trial)
                ok &= torch.isfinite(norms_trial)
                if bool(ok.all()):
                    break
                alpha = torch.where(ok, alpha, alpha * 0.5)
            if can_project:
                # A failed line search tries the other tangent next; close to equilibrium
                # the exact one (quadratic convergence).
                exact_a = exact[frames]
                slow = ~exact_a & (norms_trial > opts.stagnation * norms_a)
                near = norms_trial <= opts.exact_below * reference[frames]
                exact = exact.clone()
                exact[frames] = torch.where(~ok, ~exact_a, exact_a | near | slow)
                exact = exact | saddle
            for f in frames.tolist():
                iterations[f] += 1
            finite = torch.isfinite(norms_trial)
            if energy_a is not None:
                finite &= torch.isfinite(energy_trial)
                energy = energy.clone()
                energy[frames] = torch.where(finite, energy_trial, energy_a)
                energies.append(energy)
            keep = ~finite[:, None]
            x = x.clone()
            x[frames] = torch.where(keep, x_a, x_trial)
            residual = residual.clone()
            residual[frames] = torch.where(keep, residual[frames], residual_trial)
            norms = norms.clone()
            norms[frames] = torch.where(finite, norms_trial, norms_a)
            history.append(norms)
        if bool((norms > targets).any()) or not torch.isfinite(norms).all():
            frame = int(torch.argmax(torch.nan_to_num(norms / targets, nan=math.inf)))
            why = (f"its residual stopped decreasing (not halved in {opts.stall_iter} iterations)"
                   if stalled else f"after {max_iter} iterations")
            raise NewtonConvergenceError(
                f"Newton did not converge in frame {frame}: residual norm "
                f"{float(norms[frame]):.3e} > tolerance {float(targets[frame]):.3e}, {why}; "
                f"raise newton.max_iter, reduce the load step, or check the material parameters")
        # The adjoint needs the exact tangent at the solution itself.
        factors = self._factorize(x, params)
        return _Solution(params, fixed_values, x, factors, iterations, reference)

    def solution(self, params: Tensor, fixed_values: Tensor, x_init: Tensor | None) -> _Solution:
        params = params.detach()
        fixed_values = fixed_values.detach()
        cached = self._lookup(params, fixed_values)
        if cached is not None:
            # a point a solver asks for again is the solver's: it may seed warm starts
            cached.seeds = cached.seeds or not self._independent
            return cached
        try:
            sol = self._solve_forward(params, fixed_values, x_init)
        except torch.cuda.OutOfMemoryError as err:
            # one line naming the size and what to lower, not a traceback from the allocator
            raise gpu_memory_error(
                "the equilibrium solve", f"{fixed_values.shape[0]} frame(s) of "
                f"{self.free_dofs.numel():,} free dofs, {self.free_pattern.nnz:,} stored "
                f"tangent entries, {self.backend.name} backend", err) from None
        sol.params, sol.fixed_values = params.clone(), fixed_values.clone()
        sol.seeds = not self._independent
        self._remember(sol)
        self.last_newton_iterations = sol.newton_iterations
        self.last_warm_started = sol.warm_started
        return sol

    def _param_derivative(self, sol: _Solution) -> Any:
        self._anchor = weakref.ref(sol)
        if sol.param_derivative is None:
            sol.param_derivative = self.model.param_derivative(sol.x.detach(), sol.params)
        return sol.param_derivative


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
        need_params, need_fixed = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        if eq._has_param_derivative and need_params and not need_fixed:
            return _params_vjp(eq, sol, grad_x), None, None, None
        free = eq.free_dofs.to(grad_x.device)
        lam = eq._solve(sol.factors, grad_x[:, free], transpose=True)
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
        if eq._has_param_derivative and d_params is not None and d_fixed is None:
            return _params_jvp(eq, sol, d_params)
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


def _params_jvp(eq: Equilibrium, sol: _Solution, d_params: Tensor) -> Tensor:
    """``(dx*/dparams) d_params`` ``(F, n_dofs)`` by the model's ``param_derivative``: one
    solve with the stored factors, zero on the Dirichlet dofs."""
    free = eq.free_dofs.to(sol.x.device)
    d_residual = eq._param_derivative(sol).jvp(d_params)[:, free]
    dx_free = -eq._solve(sol.factors, d_residual.detach())
    return eq._full(dx_free, torch.zeros_like(sol.fixed_values))


def _params_vjp(eq: Equilibrium, sol: _Solution, grad_x: Tensor) -> Tensor:
    """``(dx*/dparams)^T grad_x`` ``(n_params,)`` for ``grad_x`` ``(F, n_dofs)`` by the
    model's ``param_derivative``: one transposed solve with the stored factors."""
    free = eq.free_dofs.to(grad_x.device)
    lam = eq._solve(sol.factors, grad_x[:, free], transpose=True)
    lam_full = lam.new_zeros(lam.shape[0], eq.model.n_dofs).index_copy(1, free, lam)
    return -eq._param_derivative(sol).vjp(lam_full)


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
    engine: on poisson2d N = 64 one ``J v`` or ``J^T w`` drops from about 0.8 ms to about
    0.3 ms, of which 0.2 ms is the triangular solve (docs/solvers/time_to_accuracy.md).
    """

    def __init__(self, equilibrium: Equilibrium, solution: _Solution) -> None:
        self._eq = equilibrium
        self._solution = solution
        self.x = solution.x
        self.n_frames = int(solution.x.shape[0])
        self._matrices: tuple[Tensor, Tensor] | None = None

    def jvp(self, d_params: Tensor) -> Tensor:
        """``(dx*/dparams) d_params`` ``(F, n_dofs)`` for ``d_params`` ``(n_params,)``."""
        return _params_jvp(self._eq, self._solution, d_params.to(self.x))

    def vjp(self, grad_x: Tensor) -> Tensor:
        """``(dx*/dparams)^T grad_x`` ``(n_params,)`` for ``grad_x`` ``(F, n_dofs)``."""
        return _params_vjp(self._eq, self._solution, grad_x.to(self.x))

    def free_jvp(self, d_params: Tensor) -> Tensor:
        """``(dx*_free/dparams) d_params`` ``(n_free, F)`` (free dofs in the order of
        ``free_dofs``; :meth:`Equilibrium.free_position` finds a dof's row)."""
        d_params = d_params.to(self.x)
        matrices = self._param_matrices()
        if matrices is None:
            free = self._eq.free_dofs.to(self.x.device)
            d_residual = self._eq._param_derivative(self._solution).jvp(d_params)[:, free].T
        else:
            d_residual = (matrices[0] @ d_params).view(-1, self.n_frames)
        return -self._solve_free(d_residual.detach(), transpose=False)

    def free_vjp(self, grad_free: Tensor) -> Tensor:
        """``(dx*_free/dparams)^T grad_free`` ``(n_params,)`` for ``grad_free``
        ``(n_free, F)``."""
        lam = self._solve_free(grad_free.to(self.x), transpose=True)
        matrices = self._param_matrices()
        if matrices is None:
            free = self._eq.free_dofs.to(self.x.device)
            lam_full = lam.new_zeros(self.n_frames, self._eq.model.n_dofs).index_copy(1, free, lam.T)
            return -self._eq._param_derivative(self._solution).vjp(lam_full)
        return -(matrices[1] @ lam.reshape(-1))

    def _solve_free(self, rhs: Tensor, transpose: bool) -> Tensor:
        factors = self._solution.factors
        if len(factors) == 1:
            # SuperLU returns column-major blocks: row gathers on them are 10x slower
            return factors[0].solve(rhs.contiguous(), transpose=transpose).to(rhs).contiguous()
        rows = rhs.T.contiguous()          # one frame per row: contiguous right-hand sides
        return torch.stack([f.solve(row, transpose=transpose).to(rhs)
                            for f, row in zip(factors, rows)], dim=1)

    def _param_matrices(self) -> tuple[Tensor, Tensor] | None:
        """``dR_free/dparams`` as CSR ``(n_free * F, n_params)`` (row ``i * F + f``) and its
        transpose, or ``None`` when the model's derivative has no ``matrix_entries``."""
        if self._matrices is None:
            derivative = self._eq._param_derivative(self._solution)
            if not callable(getattr(derivative, "matrix_entries", None)):
                return None
            rows, cols, values, shape = derivative.matrix_entries()
            layout = self._eq._free_matrix_layout(rows, cols, shape, self.n_frames)
            if layout is None:
                return None
            self._matrices = layout.matrices(values.detach())
        return self._matrices


class _FreeMatrixLayout:
    """The CSR structure of ``dR_free/dparams`` and of its transpose for one entry pattern
    of a model's ``matrix_entries`` (``(F * n_dofs, n_params)``, row ``f * n_dofs + dof``):
    Dirichlet rows dropped, rows renumbered ``free_position * F + f``. Built once per
    pattern; :meth:`matrices` then only gathers the values (two index_selects), where
    building the CSR from COO entries costs more than a factorisation (10 ms against 5 ms
    on poisson2d N = 64)."""

    def __init__(self, rows: Tensor, cols: Tensor, shape: tuple[int, int], n_frames: int,
                 free_positions: Tensor, n_free: int) -> None:
        self.rows, self.cols, self.shape = rows.clone(), cols.clone(), tuple(shape)
        n_dofs = shape[0] // n_frames
        frame = torch.div(rows, n_dofs, rounding_mode="floor")
        position = free_positions.to(rows.device)[rows % n_dofs]
        kept = torch.nonzero(position >= 0).reshape(-1)
        free_rows = position[kept] * n_frames + frame[kept]
        kept_cols = cols[kept]
        n_rows, n_cols = n_free * n_frames, shape[1]
        key = free_rows * n_cols + kept_cols
        self.unique = bool(torch.unique(key).numel() == key.numel())
        self.size = (n_rows, n_cols)
        order = torch.argsort(key)
        self.perm = kept[order]
        self.crow = _crow(free_rows[order], n_rows)
        self.col = kept_cols[order].contiguous()
        order_t = torch.argsort(kept_cols * n_rows + free_rows)
        self.perm_t = kept[order_t]
        self.crow_t = _crow(kept_cols[order_t], n_cols)
        self.col_t = free_rows[order_t].contiguous()

    def matches(self, rows: Tensor, cols: Tensor, shape: tuple[int, int]) -> bool:
        return tuple(shape) == self.shape and rows.shape == self.rows.shape and \
            torch.equal(rows, self.rows) and torch.equal(cols, self.cols)

    def matrices(self, values: Tensor) -> tuple[Tensor, Tensor]:
        matrix = csr_matrix(self.crow, self.col, values.index_select(0, self.perm), self.size)
        transpose = csr_matrix(self.crow_t, self.col_t, values.index_select(0, self.perm_t),
                               (self.size[1], self.size[0]))
        return matrix, transpose


def _crow(sorted_rows: Tensor, n_rows: int) -> Tensor:
    """CSR row pointers of row indices sorted ascending."""
    counts = torch.bincount(sorted_rows, minlength=n_rows)
    return torch.cat([counts.new_zeros(1), torch.cumsum(counts, 0)])


def _residual_at_solution(eq: Equilibrium, sol: _Solution, wrt_params: bool,
                          wrt_fixed: bool) -> tuple[Tensor, list[Tensor]]:
    """``R_free(x*, params)`` with leaves for the inputs asked for (call under enable_grad).

    The stored full solution is used as is unless the Dirichlet values must be
    differentiated, which avoids rebuilding ``x`` in the common case.
    """
    eq._anchor = weakref.ref(sol)
    params = sol.params.detach().requires_grad_(wrt_params)
    leaves = [params] if wrt_params else []
    if wrt_fixed:
        fixed_values = sol.fixed_values.detach().requires_grad_(True)
        x = eq._full(sol.x[:, eq.free_dofs.to(sol.x.device)].detach(), fixed_values)
        leaves.append(fixed_values)
    else:
        x = sol.x.detach()
    return eq._free_residual(x, params), leaves


def _accepts_keyword(function: Callable[..., Any], name: str) -> bool:
    """Whether ``function`` takes a keyword argument ``name`` (or ``**kwargs``)."""
    try:
        parameters = inspect.signature(function).parameters
    except (TypeError, ValueError):  # pragma: no cover - builtins
        return False
    return name in parameters or any(p.kind is inspect.Parameter.VAR_KEYWORD
                                     for p in parameters.values())
