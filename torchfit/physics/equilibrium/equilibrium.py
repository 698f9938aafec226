"""The entry point of the differentiable equilibrium ``x*(params)``: :class:`Equilibrium`.

It ties the Dirichlet reduction, Newton, the solution cache and the adjoint together.

:class:`Equilibrium` takes a model (:class:`~.model.EquilibriumModel`) and its Dirichlet
dofs. Called with ``params`` and the Dirichlet values ``(F, n_fixed)`` of ``F`` frames it
returns the positions ``(F, n_dofs)`` at equilibrium, differentiable in both by the
implicit-function adjoint (:mod:`.adjoint`). The solution and the factors of the exact
tangent at ``x*`` are cached (:mod:`.cache`): calling again at the same parameters and
Dirichlet values (a solver's ``J v`` and ``J^T w`` products, :meth:`Equilibrium.jacobian`,
:meth:`Equilibrium.linearization`) costs no Newton iteration and no factorisation, and
every backward and jvp at one parameter vector reuses one factorisation.
:meth:`Equilibrium.warm_start_state` / :meth:`Equilibrium.restore_warm_start_state` carry
what the next warm start reads into another process (a run's checkpoint), so that its next
solve starts, and ends, bit for bit where the saving process's would have. Counted work
(:mod:`torchfit.linalg.counters`): a linear model, one factorisation (shared by all frames)
and one solve per new point; a non-linear one, see :mod:`.newton`; each derivative
product, one solve per stored factor.
"""
from __future__ import annotations

from typing import Any, Callable, ContextManager

import torch
from torch import Tensor

from ...linalg import Backend, Factor, gpu_memory_error
from .adjoint import EquilibriumFunction
from .cache import Solution, SolutionCache
from .dirichlet import DirichletReduction
from .linearization import EquilibriumLinearization, FreeMatrixLayouts, solution_jacobian
from .model import EquilibriumModel
from .newton import NewtonOptions, NewtonSolver


class Equilibrium:
    """Differentiable equilibrium solve of a model with Dirichlet dofs.

    Args:
        model: the physics (see :class:`~.model.EquilibriumModel`).
        fixed_dofs: ``(n_fixed,)`` indices of Dirichlet dofs (must not be empty unless
            ``allow_no_dirichlet``: a pure-traction elastic problem is singular).
        backend: linear-solve backend, a name (``'scipy'``, ``'cg'``, ...) or object.
        newton: :class:`~.newton.NewtonOptions` for non-linear models (kept by reference).
        cache_size: number of (parameters, solution, factorisations) kept; 2 lets a
            Levenberg-Marquardt trial point be evaluated without dropping the current
            point's factorisation.
        warm_start: start Newton from an earlier solution with the same Dirichlet values
            (:meth:`~.cache.SolutionCache.warm_source`).
        linear_refinement: iterative-refinement steps after the solve of a linear model.

    Attributes:
        fixed_dofs, free_dofs: sorted ``(n_fixed,)`` and ``(n_free,)`` dof indices.
        free_positions: ``(n_dofs,)`` row of every dof among the free ones (``-1``: fixed).
        free_pattern: the free-free tangent pattern; ``backend``: the backend object.
        last_newton_iterations, last_warm_started: of the last point actually solved.
    """

    def __init__(self, model: EquilibriumModel, fixed_dofs: Tensor, backend: str | Backend = "scipy",
                 newton: NewtonOptions | None = None, cache_size: int = 2,
                 allow_no_dirichlet: bool = False, warm_start: bool = True,
                 linear_refinement: int = 0) -> None:
        self.model = model
        self.reduction = DirichletReduction(model, fixed_dofs, backend, allow_no_dirichlet)
        self.extensions = self.reduction.extensions
        self.fixed_dofs = self.reduction.fixed_dofs
        self.free_dofs = self.reduction.free_dofs
        self.free_positions = self.reduction.free_positions
        self.free_pattern = self.reduction.free_pattern
        self.backend = self.reduction.backend
        self.solver = NewtonSolver(self.reduction, newton or NewtonOptions(), linear_refinement)
        self.cache = SolutionCache(cache_size, warm_start)
        # CSR layouts of dR_free/dparams, one per entry pattern (EquilibriumLinearization)
        self.matrix_layouts = FreeMatrixLayouts(self.free_positions, self.free_dofs.numel())
        self.last_newton_iterations: list[int] = []
        self.last_warm_started = False

    # -- settings, kept by their owners ---------------------------------------------------
    @property
    def n_fixed(self) -> int:
        return self.reduction.n_fixed

    @property
    def newton(self) -> NewtonOptions:
        return self.solver.options

    @newton.setter
    def newton(self, options: NewtonOptions) -> None:
        self.solver.options = options

    @property
    def warm_start(self) -> bool:
        return self.cache.warm_start

    @warm_start.setter
    def warm_start(self, value: bool) -> None:
        self.cache.warm_start = bool(value)

    @property
    def cache_size(self) -> int:
        return self.cache.size

    @cache_size.setter
    def cache_size(self, value: int) -> None:
        self.cache.size = value

    @property
    def linear_refinement(self) -> int:
        return self.solver.linear_refinement

    @linear_refinement.setter
    def linear_refinement(self, value: int) -> None:
        self.solver.linear_refinement = int(value)

    # -- the differentiable call and the derivative products --------------------------------
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
        self.reduction.check_fixed_values(fixed_values)
        self.reduction.check_finite(fixed_values)
        if isinstance(x_init, Tensor):
            self.reduction.check_x_init(x_init, fixed_values.shape[0])
        return EquilibriumFunction.apply(params, fixed_values, x_init, self)

    def linearized_start(self, params: Tensor, fixed_values: Tensor, x_ref: Tensor) -> Tensor:
        """One Newton step from ``x_ref`` that moves the Dirichlet dofs to their values.

        ``x = x_ref + dx`` with ``dx`` equal to ``fixed_values - x_ref`` on the Dirichlet
        dofs and ``K_ff dx_f = -(R_f(x_ref) + K_fd dx_d)`` on the free ones (exact tangent
        at ``x_ref``). From the rest shape of an elastic body this is the linear-elastic
        solution: a good cold start for Newton. ``x_ref`` is ``(1, n_dofs)`` (one
        factorisation for every frame) or ``(F, n_dofs)``. No gradient flows through it.
        """
        return self.solver.linearized_start(params, fixed_values, x_ref)

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
        exactly as the forward does); ``K dX = -(dR/dparams) V`` is then solved with the
        stored factors, no new factorisation (:func:`~.linearization.solution_jacobian`).
        Column ``j`` equals the forward-mode jvp along ``directions[:, j]``.
        """
        self.reduction.check_fixed_values(fixed_values)
        if directions.dim() != 2 or directions.shape[0] != params.numel():
            raise ValueError(f"directions must have shape ({params.numel()}, k), got "
                             f"{tuple(directions.shape)}")
        if isinstance(x_init, Tensor):
            self.reduction.check_x_init(x_init, fixed_values.shape[0])
        with torch.no_grad():
            sol = self.solution(params, fixed_values, x_init)
        return solution_jacobian(self, sol, directions, observe)

    def free_position(self, dofs: Tensor) -> Tensor:
        """Rows of ``dofs`` among the free dofs (the layout of
        :meth:`EquilibriumLinearization.free_jvp`); a Dirichlet dof is an error."""
        return self.reduction.free_position(dofs)

    def linearization(self, params: Tensor, fixed_values: Tensor,
                      x_init: Tensor | Callable[[], Tensor] | None = None
                      ) -> EquilibriumLinearization:
        """The solution at ``(params, fixed_values)`` with explicit derivative products
        (:class:`~.linearization.EquilibriumLinearization`), for models with
        ``param_derivative``.

        The solution is taken from the cache or computed exactly as :meth:`__call__` does
        (same Newton, same factorisation, same errors); no autograd graph is built.
        """
        if not self.extensions.has_param_derivative:
            raise TypeError(f"{type(self.model).__name__} has no param_derivative: use the "
                            "differentiable call (autograd) for its derivative products")
        self.reduction.check_fixed_values(fixed_values)
        if isinstance(x_init, Tensor):
            self.reduction.check_x_init(x_init, fixed_values.shape[0])
        with torch.no_grad():
            return EquilibriumLinearization(self, self.solution(params, fixed_values, x_init))

    # -- solutions ----------------------------------------------------------------------------
    def solution(self, params: Tensor, fixed_values: Tensor,
                 x_init: Tensor | Callable[[], Tensor] | None) -> Solution:
        """The :class:`~.cache.Solution` at ``(params, fixed_values)``: cached, else solved
        (warm or cold, :mod:`.newton`) and cached. No graph."""
        params = params.detach()
        fixed_values = fixed_values.detach()
        cached = self.cache.lookup(params, fixed_values)
        if cached is not None:      # (the cache made it the seed unless independent)
            return cached
        try:
            source = None if self.model.linear else self.cache.warm_source(fixed_values)
            budget, warm_x = None, None
            if self.cache.is_anchor(source):    # a solver's trial point
                budget = self.newton.trial_budget(source.newton_iterations)
                if self.newton.trial_predictor and self.extensions.has_param_derivative:
                    warm_x = self.predicted_start(source, params)
            sol = self.solver.solve(params, fixed_values, x_init, source, budget, warm_x)
        except torch.cuda.OutOfMemoryError as err:
            # one line naming the size and what to lower, not a traceback from the allocator
            raise gpu_memory_error(
                "the equilibrium solve", f"{fixed_values.shape[0]} frame(s) of "
                f"{self.free_dofs.numel():,} free dofs, {self.free_pattern.nnz:,} stored "
                f"tangent entries, {self.backend.name} backend", err) from None
        sol.params, sol.fixed_values = params.clone(), fixed_values.clone()
        sol.seeds = not self.cache.is_independent
        self.cache.remember(sol)
        self.last_newton_iterations = sol.newton_iterations
        self.last_warm_started = sol.warm_started
        return sol

    def predicted_start(self, anchor: Solution, params: Tensor) -> Tensor:
        """The first-order predictor ``x_anchor + (dx*/dparams)(params - params_anchor)``
        ``(F, n_dofs)`` at the anchor's Dirichlet values: one solve per stored factor of
        the anchor, no factorisation."""
        step = (params - anchor.params).reshape(-1, 1)
        return anchor.x + solution_jacobian(self, anchor, step)[..., 0]

    def param_derivative(self, solution: Solution) -> Any:
        """The model's ``param_derivative`` at ``solution`` (built once, kept with it);
        derivatives are now taken there, so it becomes the anchor of warm starts."""
        self.cache.anchor(solution)
        if solution.param_derivative is None:
            solution.param_derivative = self.model.param_derivative(solution.x.detach(),
                                                                    solution.params)
        return solution.param_derivative

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
        cached = self.cache.lookup(params, fixed_values)
        if cached is not None:
            return cached.factors
        if x.dim() != 2 or x.shape != (fixed_values.shape[0], self.model.n_dofs):
            raise ValueError(f"x must have shape {(fixed_values.shape[0], self.model.n_dofs)}, "
                             f"got {tuple(x.shape)}")
        x = self.reduction.full(x.detach()[:, self.free_dofs.to(x.device)], fixed_values)
        if factors is None:
            factors = self.reduction.factorize(x, params)
        return self.cache.adopt(params, fixed_values, x, factors).factors

    def restore(self, solution: Solution) -> None:
        """Put a solution that :meth:`solution` returned earlier back into the cache (with its
        factors and its parameter derivative): no Newton, no factorisation."""
        self.cache.restore(solution)

    def warm_start_state(self) -> dict[str, Any]:
        """What the next warm start reads, as tensors for a checkpoint: the anchor and the
        most recently used solution (:meth:`~.cache.SolutionCache.seed_solutions`), each
        with its parameters, Dirichlet values, positions, reference residuals and Newton
        counts, and ``anchor`` (its index, ``-1``: none); ``{}`` for a linear model or
        without warm starts (the next solve does not depend on earlier ones)."""
        if self.model.linear or not self.cache.warm_start:
            return {}
        solutions, anchor = self.cache.seed_solutions()
        if not solutions:
            return {}
        return {"solutions": [_saved_solution(sol) for sol in solutions], "anchor": anchor}

    def restore_warm_start_state(self, state: dict[str, Any],
                                 device: torch.device | str | None = None) -> None:
        """Put back what :meth:`warm_start_state` saved (the exact tangent at each solution
        factorised once, as the solve that found it did; a point already cached is kept),
        the anchor included: the next solve starts exactly where it did in the process
        that saved it. ``{}``: nothing to do."""
        if not state:
            return
        restored = []
        for saved in state["solutions"]:
            params = saved["params"].to(device)
            fixed_values = saved["fixed_values"].to(device)
            sol = self.cache.lookup(params, fixed_values)
            if sol is None:
                x = saved["x"].to(device)
                reference = saved.get("reference")
                sol = Solution(params, fixed_values, x, self.reduction.factorize(x, params),
                               [int(i) for i in saved["newton_iterations"].tolist()],
                               None if reference is None else reference.to(device),
                               warm_started=bool(saved["warm_started"]),
                               seeds=bool(saved["seeds"]))
            restored.append(sol)
        self.cache.restore_seed_state(restored, int(state["anchor"]))

    def clear_cache(self) -> None:
        self.cache.clear()

    def use_backend(self, backend: str | Backend) -> None:
        """Solve with ``backend`` (a name or an object: a configured
        :class:`~torchfit.linalg.CudssBackend`, a stand-in in tests) from now on; the
        cached solutions, whose factors are the old backend's, are dropped."""
        self.reduction.use_backend(backend)
        self.backend = self.reduction.backend
        self.cache.clear()

    def independent(self) -> ContextManager[None]:
        """Within: every new solve starts cold (from ``x_init``, not from an earlier
        solution) and its solution never warm-starts a later one, unless derivatives are
        taken at it or it is asked for again outside. A solution already cached at the same
        parameters and Dirichlet values is returned as it is (no new solve).

        For simulations beside a solver's sequence: a synthetic target, the homogeneous
        baseline of a report. Where a frame has several equilibria (a fold), a warm start
        from them would put the fit on their branch.
        """
        return self.cache.independent()


def _saved_solution(sol: Solution) -> dict[str, Any]:
    """A solution's tensors and flags, detached copies (no factors: they are recomputed)."""
    saved: dict[str, Any] = {
        "params": sol.params.detach().clone(), "fixed_values": sol.fixed_values.detach().clone(),
        "x": sol.x.detach().clone(),
        "newton_iterations": torch.tensor(sol.newton_iterations, dtype=torch.long),
        "warm_started": bool(sol.warm_started), "seeds": bool(sol.seeds)}
    if sol.reference is not None:
        saved["reference"] = sol.reference.detach().clone()
    return saved
