"""Newton's method on the free dofs of every frame at once, and the forward solve.

:meth:`NewtonSolver.solve` returns the :class:`~.cache.Solution` at ``(params,
fixed_values)``: a linear model in one factorisation and one solve (plus
``linear_refinement`` steps of iterative refinement with the same factor); a non-linear one
by Newton with a backtracking line search on ``||R||`` per frame, from a warm start (an
earlier solution, at most ``warm_max_iter`` iterations, judged against the cold start's
reference residual) and else, or when that fails, from the cold start. A *trial* (a warm
start from the anchor, a solver's accepted point) has a budget instead of the cold-start
fallback (:attr:`NewtonOptions.trial_factor`): past it Newton stops with
:class:`TrialBudgetExceeded`, which solvers treat as a failed trial. The factors kept
with the solution are always those of the exact tangent at ``x*``.

Tangent choice (models with a projected, PSD tangent): a frame uses the projected tangent
while its residual is above ``exact_below * reference`` and switches to the exact one
(quadratic convergence) below it or when a projected step stagnates; a failed line search
tries the other tangent; an exact step that points uphill in the energy is redone with the
projected one. With an energy the line search accepts a step that decreases the energy
(Armijo) or ``||R||``. Stall rule: a frame whose residual has not halved in ``stall_iter``
iterations (with the energy not decreasing) stops Newton with
:class:`NewtonConvergenceError`, except once per frame close to equilibrium (a saddle at a
fold): that frame then finishes with the exact tangent and a line search on ``||R||`` alone.
Residual norms are per frame, in force units. Round-off floor: a frame that missed its
tolerance (``rtol`` x its start's residual, at least ``atol``) but whose residual is within
the rounding error of evaluating it (:meth:`NewtonSolver.roundoff_floor`: ``(n_row + 1) eps
||(|K| |x|)_free||``) is converged: the tolerance asked for more than the arithmetic can
give, and the point is an equilibrium to working precision. Counted work: one
factorisation per active frame and iteration (one for all when the tangent is shared), one more per frame whose
exact step is redone with the projected tangent, and one per frame at ``x*``.
"""
from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import math
from typing import Callable, Iterator

import torch
from torch import Tensor

from ...errors import SimulationError
from ...linalg import SingularMatrixError
from .cache import Solution
from .dirichlet import DirichletReduction


#: where set (:func:`newton_progress`), called after every Newton iteration with the
#: iteration, the number of frames converged and the number of frames
_PROGRESS: contextvars.ContextVar[Callable[[int, int, int], None] | None] = \
    contextvars.ContextVar("torchfit_newton_progress", default=None)


@contextlib.contextmanager
def newton_progress(report: Callable[[int, int, int], None]) -> Iterator[None]:
    """Within the block, ``report(iteration, frames_converged, n_frames)`` after every
    Newton iteration (a problem's first simulation shows its progress with it)."""
    token = _PROGRESS.set(report)
    try:
        yield
    finally:
        _PROGRESS.reset(token)


class NewtonConvergenceError(SimulationError):
    """Newton did not bring a frame to equilibrium; the message names frame and residual."""


class TrialBudgetExceeded(SimulationError):
    """A trial solve (warm-started from the anchor) did not converge within its budget
    (:attr:`NewtonOptions.trial_factor`); ``budget`` is its per-frame iteration limit. A
    solver sees a failed trial (Levenberg-Marquardt rejects the step, Gauss-Newton
    shortens it)."""

    def __init__(self, message: str, budget: int) -> None:
        super().__init__(message)
        self.budget = int(budget)


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
    # Trial budget: a solve warm-started from the anchor (a solver's trial point, see
    # cache.py) may spend at most max(trial_min_iter * frames, trial_factor * the anchor's
    # Newton iterations summed over its frames) frame-iterations (one factorisation each;
    # within warm_max_iter per frame); past it, or where that warm start fails, it raises
    # TrialBudgetExceeded instead of going on to the cold start (the long walk of a step
    # that is then usually rejected). 0 disables it: the default, because a budget also
    # cuts accepted steps and the short arm's fit ended worse, while without one a rejected
    # step costs under 2x an accepted iteration (docs/notes/equilibrium.md).
    trial_factor: float = 0.0
    trial_min_iter: int = 5
    # Start such a trial from the first-order predictor x_anchor + (dx/dparams) dparams
    # (one solve per stored factor of the anchor) instead of x_anchor.
    trial_predictor: bool = False

    def trial_budget(self, anchor_iterations: list[int]) -> int | None:
        """The budget in frame-iterations of a trial whose anchor took
        ``anchor_iterations`` per frame (``None``: no budget)."""
        if self.trial_factor <= 0:
            return None
        return max(int(self.trial_min_iter) * len(anchor_iterations),
                   math.ceil(self.trial_factor * sum(anchor_iterations)))


class NewtonSolver:
    """The forward solve of the reduced system (see the module docstring).

    Args:
        reduction: the Dirichlet reduction of the model (its residual, tangent, solves).
        options: :class:`NewtonOptions` (kept by reference: changes made to it apply to the
            next solve).
        linear_refinement: iterative-refinement steps after the solve of a linear model
            (one residual and one solve with the same factor each; removes the round-off of
            a far start).
    """

    def __init__(self, reduction: DirichletReduction, options: NewtonOptions,
                 linear_refinement: int = 0) -> None:
        self.reduction = reduction
        self.model = reduction.model
        self.extensions = reduction.extensions
        self.options = options
        self.linear_refinement = int(linear_refinement)

    def solve(self, params: Tensor, fixed_values: Tensor,
              x_init: Tensor | Callable[[], Tensor] | None,
              warm_source: Solution | None = None, budget: int | None = None,
              warm_x: Tensor | None = None) -> Solution:
        """The solution at ``(params, fixed_values)`` (detached inputs), from
        ``warm_source`` first where given (non-linear models only; from ``warm_x`` instead
        of its positions where given), else from ``x_init``. With ``budget`` (a trial:
        ``warm_source`` is the anchor) the warm start may take at most that many
        iterations and its failure raises :class:`TrialBudgetExceeded` (no cold start)."""
        n_frames = fixed_values.shape[0]
        if self.model.linear:
            # Any start gives the solution in one step: skip a start that must be computed.
            reduction = self.reduction
            x = self.cold_start(params, fixed_values,
                                x_init if isinstance(x_init, Tensor) else None)
            x_free = x[:, reduction.free_dofs.to(x.device)]
            residual = reduction.free_residual(x, params)
            factors = reduction.factorize(x, params)
            x = reduction.full(x_free - reduction.solve(factors, residual), fixed_values)
            # an iterative factor (amg) already solves to its tolerance: no refinement
            refine = self.linear_refinement if getattr(factors[0], "refinable", True) else 0
            for _ in range(refine):
                x_free = x[:, reduction.free_dofs.to(x.device)]
                correction = reduction.solve(factors, reduction.free_residual(x, params))
                x = reduction.full(x_free - correction, fixed_values)
            if not torch.isfinite(x).all():
                raise SingularMatrixError("the linear solve produced non-finite positions; "
                                          "check that all stiffnesses are positive and finite")
            return Solution(params, fixed_values, x, factors, [1] * n_frames)
        if warm_source is not None:
            start = warm_source.x if warm_x is None else warm_x
            try:
                sol = self.iterate(params, fixed_values, start.detach().clone(),
                                   warm_source.reference, max_iter=min(self.options.warm_max_iter,
                                                                       self.options.max_iter),
                                   budget=budget)
                sol.warm_started = True
                return sol
            except (NewtonConvergenceError, SingularMatrixError) as err:
                if budget is not None:
                    raise TrialBudgetExceeded(
                        f"trial simulation failed within its budget of {budget} Newton "
                        f"frame-iterations: {err}", budget) from None
                # else the cold start below decides (and reports a failure)
        return self.iterate(params, fixed_values, self.cold_start(params, fixed_values, x_init))

    def linearized_start(self, params: Tensor, fixed_values: Tensor, x_ref: Tensor) -> Tensor:
        """One Newton step from ``x_ref`` that moves the Dirichlet dofs to their values
        (see :meth:`torchfit.physics.Equilibrium.linearized_start`)."""
        reduction, model = self.reduction, self.model
        with torch.no_grad():
            n_frames = fixed_values.shape[0]
            if x_ref.dim() != 2 or x_ref.shape[0] not in (1, n_frames) \
                    or x_ref.shape[1] != model.n_dofs:
                raise ValueError(f"x_ref must have shape (1 or {n_frames}, {model.n_dofs}), "
                                 f"got {tuple(x_ref.shape)}")
            params = params.detach()
            fixed = reduction.fixed_dofs.to(x_ref.device)
            free = reduction.free_dofs.to(x_ref.device)
            contributions = reduction.tangent(x_ref, params)
            values = model.tangent_pattern.assemble(contributions)
            dx = x_ref.new_zeros(n_frames, model.n_dofs)
            dx[:, fixed] = fixed_values.detach() - x_ref[:, fixed]
            coupling = model.tangent_pattern.matvec(values, dx)[:, free]
            residual = model.residual(x_ref, params)[:, free]
            factors = [reduction.factorize_values(v[reduction.free_slots.to(v.device)])
                       for v in values]
            dx[:, free] = -reduction.solve(factors, (residual + coupling).expand(n_frames, -1))
            return self._collision_free_start(x_ref, dx, fixed)

    def _collision_free_start(self, x_ref: Tensor, dx: Tensor, fixed: Tensor) -> Tensor:
        """``x_ref + dx``; for a model with a contact term, the free dofs go only as far
        along ``dx`` as no contact is crossed from ``x_ref`` with the Dirichlet dofs moved
        (the linear step ignores the barrier and could pass through a fold)."""
        limit = getattr(self.model, "collision_free_step", None)
        if limit is None:
            return x_ref + dx
        moved = x_ref.expand_as(dx).clone()
        moved[:, fixed] += dx[:, fixed]
        alpha = limit(moved, x_ref + dx).to(dx)
        return moved + alpha[:, None] * (x_ref + dx - moved)

    def cold_start(self, params: Tensor, fixed_values: Tensor,
                   x_init: Tensor | Callable[[], Tensor] | None) -> Tensor:
        """The full start ``(F, n_dofs)``: ``x_init`` (or what the function ``x_init``
        returns) on the free dofs, zeros without it, the Dirichlet values in place."""
        n_frames = fixed_values.shape[0]
        free = self.reduction.free_dofs.to(params.device)
        if x_init is None:
            x_free = params.new_zeros(n_frames, free.numel())
        else:
            if callable(x_init) and not isinstance(x_init, Tensor):
                x_init = x_init()
                self.reduction.check_x_init(x_init, n_frames)
            x_free = x_init.detach()[:, free]
        return self.reduction.full(x_free, fixed_values)

    def iterate(self, params: Tensor, fixed_values: Tensor, x: Tensor,
                reference: Tensor | None = None, max_iter: int | None = None,
                budget: int | None = None) -> Solution:
        """Newton from the full start ``x`` ``(F, n_dofs)``; convergence is judged against
        ``reference`` (the cold start's residual norms; those of ``x`` without it). With
        ``budget``, an iteration that would take the frame-iterations (factorisations)
        past it raises :class:`TrialBudgetExceeded` instead."""
        opts = self.options
        max_iter = opts.max_iter if max_iter is None else max_iter
        n_frames = x.shape[0]
        free = self.reduction.free_dofs.to(x.device)
        if self.extensions.has_energy:
            # one pass (one decomposition per element) for both; the tangent at x reuses it
            residual, energy = self._residual_and_energy(x, params)
        else:
            residual, energy = self.reduction.free_residual(x, params), None
        norms = torch.linalg.vector_norm(residual, dim=1)
        if reference is None:
            reference = norms.clone()
        targets = torch.clamp(opts.rtol * reference, min=opts.atol)
        iterations = [0] * n_frames
        can_project = self.extensions.accepts_projected
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
            if budget is not None and sum(iterations) + frames.numel() > budget:
                raise TrialBudgetExceeded(
                    f"trial simulation stopped after {sum(iterations)} Newton frame-iterations "
                    f"(budget {budget}: newton trial_factor x the accepted point's)", budget)
            use_exact = exact[frames]
            contributions = None
            if bool(use_exact.any()):
                contributions = self.reduction.tangent(x[frames], params)
            if not bool(use_exact.all()):
                projected = self.reduction.tangent(x[frames], params, projected=True)
                contributions = projected if contributions is None else torch.where(
                    use_exact[:, None], contributions.expand_as(projected), projected)
            values = self.reduction.free_values(contributions)
            if values.shape[0] == 1 and frames.numel() > 1:
                factors = [self.reduction.factorize_values(values[0])]
            else:
                factors = [self.reduction.factorize_values(v) for v in values]
            step = torch.zeros_like(residual)
            step[frames] = self.reduction.solve(factors, -residual[frames])
            slope = (residual * step).sum(dim=1)        # dEnergy/dalpha at alpha = 0
            if energy is not None and can_project:
                # an exact tangent that is not positive definite can point uphill: take
                # the projected one for those frames instead
                uphill = active & (slope >= 0) & exact & ~saddle
                if bool(uphill.any()):
                    again = torch.nonzero(uphill).reshape(-1)
                    projected = self.reduction.free_values(
                        self.reduction.tangent(x[again], params, projected=True))
                    redo = [self.reduction.factorize_values(v) for v in projected]
                    step[again] = self.reduction.solve(redo, -residual[again])
                    slope = (residual * step).sum(dim=1)
                    exact = exact & ~uphill
            # Backtracking on ||R|| (and the energy), per frame, on the active frames only
            # (a converged frame costs nothing while a hard one is still iterating).
            x_a, step_a, norms_a = x[frames], step[frames], norms[frames]
            slope_a, targets_a, fixed_a = slope[frames], targets[frames], fixed_values[frames]
            energy_a = energy[frames] if energy is not None else None
            alpha = self._collision_free_step(x_a, step_a, fixed_a)
            energy_trial = energy_a
            for _ in range(opts.max_backtracks):
                x_trial = self.reduction.full(x_a[:, free] + alpha[:, None] * step_a, fixed_a)
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
            self._after_step(x)
            report = _PROGRESS.get()
            if report is not None:
                report(len(history) - 1, int((norms <= targets).sum()), n_frames)
        if bool((norms > targets).any()) and bool(torch.isfinite(norms).all()):
            # A tolerance below what the arithmetic can resolve is not a failure: a frame
            # whose residual is at its round-off floor is an equilibrium (module docstring).
            targets = torch.maximum(targets, self.roundoff_floor(x, params))
        if bool((norms > targets).any()) or not torch.isfinite(norms).all():
            frame = int(torch.argmax(torch.nan_to_num(norms / targets, nan=math.inf)))
            why = (f"its residual stopped decreasing (not halved in {opts.stall_iter} iterations)"
                   if stalled else f"after {max_iter} iterations")
            raise NewtonConvergenceError(
                f"Newton did not converge in frame {frame}: residual norm "
                f"{float(norms[frame]):.3e} > tolerance {float(targets[frame]):.3e}, {why}; "
                f"raise newton.max_iter, reduce the load step, or check the material parameters")
        # The adjoint needs the exact tangent at the solution itself.
        factors = self.reduction.factorize(x, params)
        return Solution(params, fixed_values, x, factors, iterations, reference)

    def roundoff_floor(self, x: Tensor, params: Tensor) -> Tensor:
        """The residual norm per frame ``(F,)`` below which ``||R(x)||`` is round-off:
        ``(n_row + 1) eps || (|K| |x|)_free ||`` with ``K`` the exact tangent at ``x``,
        ``n_row`` the most entries in one of its rows and ``eps`` the dtype's machine
        epsilon.

        Why this: a residual that is (locally) ``K x - b`` is evaluated with an error of at
        most ``gamma_n |K| |x|`` per component (Higham, *Accuracy and Stability of Numerical
        Algorithms*, 2nd ed., eq. 3.11, ``gamma_n = n eps / (1 - n eps)``, ``n`` the terms
        summed per row), and the positions themselves are known to ``eps |x|``, which moves
        ``R`` by ``K eps |x|``: a residual within that bound cannot be told from zero, and
        no Newton step can lower it. It scales with the positions, the stiffness and the
        step's inertia and damping terms (a large ``beta`` lifts it), which a fixed
        ``newton.rtol`` x the start's residual does not. One tangent assembly, paid only
        when a frame missed its tolerance."""
        with torch.no_grad():
            pattern = self.model.tangent_pattern
            values = pattern.assemble(self.reduction.tangent(x, params)).abs()
            size = pattern.matvec(values, x.abs())[:, self.reduction.free_dofs.to(x.device)]
            per_row = int((pattern.crow_indices[1:] - pattern.crow_indices[:-1]).max())
            eps = torch.finfo(x.dtype).eps
            return (per_row + 1) * eps * torch.linalg.vector_norm(size, dim=1)

    def _collision_free_step(self, x_a: Tensor, step_a: Tensor, fixed_a: Tensor) -> Tensor:
        """The line search's first step per active frame ``(F_a,)``: 1, or, for a model
        with a contact term (``collision_free_step(x0, x1)``), the largest step whose
        straight path passes through no contact (IPC's continuous collision detection)."""
        limit = getattr(self.model, "collision_free_step", None)
        if limit is None:
            return torch.ones(x_a.shape[0], dtype=x_a.dtype, device=x_a.device)
        free = self.reduction.free_dofs.to(x_a.device)
        return limit(x_a, self.reduction.full(x_a[:, free] + step_a, fixed_a)).to(x_a)

    def _after_step(self, x: Tensor) -> None:
        """Let a model with ``after_step(x)`` (the contact term: IPC's barrier stiffness
        update) see the positions after each Newton iteration."""
        after = getattr(self.model, "after_step", None)
        if after is not None:
            after(x)

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
        if self.extensions.frame_independent or frames.numel() == x_all.shape[0]:
            x = x_frames
        else:
            x = x_all.clone()
            x[frames] = x_frames
        if with_energy:
            residual, energy = self._residual_and_energy(x, params)
        else:
            residual, energy = self.reduction.free_residual(x, params), None
        if x is not x_frames:
            residual = residual[frames]
            energy = None if energy is None else energy[frames]
        return residual, energy

    def _residual_and_energy(self, x: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
        """Free residual ``(F, n_free)`` and energy ``(F,)`` (one pass where the model
        offers ``residual_and_energy``: one SVD per element instead of two)."""
        if self.extensions.has_residual_and_energy:
            residual, energy = self.model.residual_and_energy(x, params)
            return residual[:, self.reduction.free_dofs.to(x.device)], energy.detach()
        return self.reduction.free_residual(x, params), self._energy(x, params)

