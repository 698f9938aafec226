"""The first-order system integrated by torchdiffeq (``odeint_adjoint``).

State ``y = [x_free, v_free]``, ``y' = [v_free, a_free(t, x, v; params)]`` with the
Dirichlet dofs placed on their trajectory at every ``t``
(:meth:`~.system.DynamicSystem.acceleration`). Methods: the adaptive ``dopri5`` (also
``dopri8``, ``bosh3``, ``adaptive_heun``: tolerances ``rtol``, ``atol``) and the fixed-step
``rk4``, ``midpoint``, ``euler`` (step ``step_size``).

Derivatives:

* ``J^T w``: ``torchdiffeq.odeint_adjoint`` with the physical parameters as its
  ``adjoint_params`` (the continuous adjoint integrated backward in time, memory
  independent of the number of steps). Its graph is built once per parameter vector and
  kept with the trajectory, so repeated products do not integrate forward again.
* ``J v``: forward sensitivities ``s' = (df/dy) s + (df/dparams) v`` integrated beside
  the state by the same method (``torch.func.jvp`` of the right-hand side).

Both are accurate to the integration tolerance (not to round-off, as the implicit
integrator's discrete adjoint is): the dot-product test reaches ``1e-10`` with
``rtol = 1e-12``.

Stability: explicit methods need ``h`` times the fastest rate below a constant (``rk4``:
2.8); the rate is ``omega_max`` (the stiffest mode,
:meth:`~.system.DynamicSystem.max_frequency`) or, where stiffness damping overdamps it,
``beta omega_max^2`` (:func:`fastest_rate`). A fixed step that blows up, or an adaptive step
that collapses, raises :class:`~.errors.UnstableStepError` naming ``integrator=implicit``.

Trial budget (adaptive methods, ``trial_factor > 0``): the point derivatives were last
taken at is the *anchor* (a solver's accepted point); an integration at other parameters
(a solver's trial) may evaluate the right-hand side at most ``trial_factor`` times as often
as the anchor's integration did, and past that raises
:class:`~torchfit.physics.equilibrium.TrialBudgetExceeded`, which solvers treat as a failed
trial. A step that makes the material much stiffer, or ``beta`` much larger, makes the
adaptive step collapse to the stability limit: without the budget one such trial runs for
many minutes before the line search shortens it.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import torch
from torch import Tensor

from ..equilibrium import TrialBudgetExceeded
from .errors import DynamicsInputError, NonFiniteStateError, UnstableStepError
from .system import DynamicSystem, TrajectoryFunction, check_output_times

ADAPTIVE_METHODS = ("dopri5", "dopri8", "bosh3", "adaptive_heun")
FIXED_METHODS = ("rk4", "midpoint", "euler")
METHODS = ADAPTIVE_METHODS + FIXED_METHODS
#: ``h omega_max`` an explicit method tolerates on the imaginary axis (0: none, it needs damping)
STABILITY_LIMIT = {"rk4": 2.83, "dopri5": 3.3, "dopri8": 4.0, "bosh3": 1.7, "midpoint": 0.0,
                   "euler": 0.0, "adaptive_heun": 0.0}
#: A state this many rest extents (at least 1) away from the rest shape has blown up
BLOWUP_FACTOR = 1e3


def fastest_rate(omega_max: float, alpha: float, beta: float) -> float:
    """The largest ``|lambda|`` (1/s) of the damped modes ``lambda^2 + (alpha + beta
    omega^2) lambda + omega^2 = 0`` at the stiffest mode ``omega_max`` (rad/s): ``omega_max``
    while underdamped, the fast root ``~ alpha + beta omega_max^2`` once overdamped. What an
    explicit step must resolve (``h`` times it below the method's stability limit)."""
    damping = alpha + beta * omega_max ** 2
    if damping <= 2.0 * omega_max:
        return omega_max
    return 0.5 * (damping + math.sqrt(damping ** 2 - 4.0 * omega_max ** 2))


@dataclasses.dataclass
class _Solve:
    params: Tensor
    outputs: Tensor                 # (K, n_dofs)
    graph_out: Tensor | None = None     # odeint_adjoint's output (graph kept), free states
    graph_leaf: Tensor | None = None
    evaluations: int = 0            # right-hand sides of the forward integration


class TorchdiffeqIntegrator:
    """torchdiffeq integration of a :class:`DynamicSystem` (module docstring).

    Args:
        system: the dynamics.
        output_times: ``(K,)`` strictly increasing times ``>= t0``.
        method: one of :data:`METHODS`.
        rtol, atol: tolerances of the adaptive methods (forward and adjoint).
        step_size: step of the fixed-step methods (s); required for them.
        cache_size: solves kept, keyed by the parameters.
        trial_factor: adaptive methods: an integration away from the anchor (the point
            derivatives were last taken at) may evaluate the right-hand side at most this
            many times as often as the anchor's did (module docstring); 0: no limit.
    """

    name = "torchdiffeq"

    def __init__(self, system: DynamicSystem, output_times: Tensor | list[float],
                 method: str = "dopri5", rtol: float = 1e-8, atol: float = 1e-10,
                 step_size: float | None = None, cache_size: int = 2,
                 trial_factor: float = 0.0) -> None:
        if method not in METHODS:
            raise DynamicsInputError(f"unknown torchdiffeq method {method!r}; choose one of "
                                     f"{', '.join(METHODS)}")
        if method in FIXED_METHODS and not (step_size is not None and math.isfinite(step_size)
                                            and step_size > 0):
            raise DynamicsInputError(f"the fixed-step method {method} needs a step size > 0, got "
                                     f"{step_size!r}")
        for name, value in (("rtol", rtol), ("atol", atol)):
            if not (math.isfinite(value) and value > 0):
                raise DynamicsInputError(f"{name} = {value!r} must be a positive number")
        if not (math.isfinite(trial_factor) and trial_factor >= 0):
            raise DynamicsInputError(f"trial_factor = {trial_factor!r} must be a number >= 0 "
                                     "(0: no limit)")
        self.system = system
        self.method = method
        self.rtol, self.atol = float(rtol), float(atol)
        self.step_size = None if step_size is None else float(step_size)
        self.output_times = check_output_times(output_times, system.t0)
        self.cache_size = int(cache_size)
        self._cache: list[_Solve] = []
        self.evaluations = 0
        self.trial_factor = float(trial_factor)
        self._anchor: tuple[Tensor, int] | None = None     # (params, right-hand sides)
        # (evaluation count it may not reach, budget) during a trial's forward integration
        # only: the adjoint integrates backward through the same right-hand side, unlimited
        self._limit: tuple[int, int] | None = None
        rest = system.x0
        extent = float((rest.max() - rest.min()).abs()) if rest.numel() else 1.0
        self.blowup_distance = BLOWUP_FACTOR * max(extent, 1.0)

    @property
    def stored_states(self) -> int:
        """States kept for the gradient: the outputs and the adjoint's own (one)."""
        return len(self.output_times) + 1

    # -- the ODE ------------------------------------------------------------------------------
    def _times(self, like: Tensor) -> tuple[Tensor, bool]:
        t = self.output_times.to(like)
        t0 = self.system.t0
        if float(t[0]) > t0:
            return torch.cat([t.new_tensor([t0]), t]), True
        return t, False

    def _rhs(self, params: Tensor, guard: bool = True):
        system = self.system
        free = system.free_dofs
        n_free = free.numel()
        rest = system.x0[free]

        def f(t: Tensor, y: Tensor) -> Tensor:
            if self._limit is not None and self.evaluations >= self._limit[0]:
                raise self._over_budget(params, float(t.detach()), self._limit[1])
            t1 = t.reshape(1).to(y)
            x = system.full(y[None, :n_free], system.fixed_positions(t1))
            v = system.full(y[None, n_free:], system.fixed_velocities(t1))
            a = system.acceleration(t, x, v, params)[0]
            self.evaluations += 1
            if guard:
                self._guard(float(t.detach()), y[:n_free].detach(), rest.to(y), x.detach()[0],
                            v.detach()[0], a.detach(), params)
            return torch.cat([y[n_free:], a[free.to(a.device)]])

        return f

    def _guard(self, t: float, x_free: Tensor, rest: Tensor, x: Tensor, v: Tensor, a: Tensor,
               params: Tensor) -> None:
        """Raise on a blown-up or non-finite state (one check per right-hand side)."""
        distance = (x_free - rest).abs().max() if x_free.numel() else x_free.new_zeros(())
        if not bool(torch.isfinite(distance)) or float(distance) > self.blowup_distance:
            if bool(torch.isfinite(x).all()) or self.method in FIXED_METHODS:
                raise self._unstable(params, f"blew up by t = {t:.6g}")
        if bool(torch.isfinite(a).all()):
            return
        self.system.check_state(x, t)
        self.system.check_state(v, t, "velocity")
        dof = int(torch.nonzero(~torch.isfinite(a))[0])
        raise NonFiniteStateError(
            f"the state is not finite at t = {t:.6g}: the acceleration of vertex "
            f"{dof // self.system.vertex_dim} (dof {dof}) is {float(a[dof])} (a load or a "
            "parameter is not finite)")

    def _y0(self, like: Tensor) -> Tensor:
        system = self.system
        free = system.free_dofs.to(like.device)
        return torch.cat([system.x0.to(like)[free], system.v0.to(like)[free]])

    def _options(self) -> dict[str, Any]:
        options: dict[str, Any] = {"method": self.method}
        if self.method in FIXED_METHODS:
            options["options"] = {"step_size": self.step_size}
        else:
            options.update(rtol=self.rtol, atol=self.atol)
        return options

    def _positions(self, states: Tensor, times: Tensor) -> Tensor:
        """Full positions ``(K, n_dofs)`` from free states ``(K, 2 n_free)``."""
        n_free = self.system.free_dofs.numel()
        return self.system.full(states[:, :n_free], self.system.fixed_positions(times))

    def _integrate(self, params: Tensor, adjoint: bool,
                   budget: int | None = None) -> tuple[Tensor, Tensor | None, Tensor | None]:
        from torchdiffeq import odeint, odeint_adjoint

        times, prepended = self._times(params)
        y0 = self._y0(params)
        self._limit = None if budget is None else (self.evaluations + budget, budget)
        try:
            if adjoint:
                with torch.enable_grad():
                    leaf = params.detach().requires_grad_(True)
                    states = odeint_adjoint(self._rhs(leaf), y0, times, adjoint_params=(leaf,),
                                            **self._options())
                    states = states[1:] if prepended else states
            else:
                leaf = None
                with torch.no_grad():
                    states = odeint(self._rhs(params), y0, times, **self._options())
                states = states[1:] if prepended else states
        except AssertionError as error:       # torchdiffeq: "underflow in dt"
            raise self._unstable(params, f"failed: its adaptive step collapsed ({error})") from None
        finally:
            self._limit = None
        self._check(states.detach(), params)
        return states, leaf, prepended

    def _check(self, states: Tensor, params: Tensor) -> None:
        """The outputs are finite and not blown up (the right-hand side checks every stage)."""
        n_free = self.system.free_dofs.numel()
        rest = self.system.x0.to(states)[self.system.free_dofs.to(states.device)]
        far = ~torch.isfinite(states).all(dim=1) | \
            ((states[:, :n_free] - rest).abs().amax(dim=1) > self.blowup_distance)
        if bool(far.any()):
            k = int(torch.nonzero(far)[0])
            raise self._unstable(params, f"blew up by t = {float(self.output_times[k]):.6g}")

    def _rates(self, params: Tensor) -> tuple[float, float, str]:
        """``(omega_max, fastest rate, its words)`` at ``params``."""
        field, alpha, beta = self.system.split(params.detach())
        omega = self.system.max_frequency(field)
        rate = fastest_rate(omega, float(alpha), float(beta))
        words = f"the stiffest mode, omega_max = {omega:.4g} rad/s"
        if rate > omega:
            words += (f", overdamped by beta = {float(beta):.4g} s: its fast rate is "
                      f"{rate:.4g}/s")
        return omega, rate, words

    def _over_budget(self, params: Tensor, t: float, budget: int) -> TrialBudgetExceeded:
        anchor = self._anchor[1] if self._anchor is not None else 0
        words = self._rates(params)[2]
        return TrialBudgetExceeded(
            f"torchdiffeq/{self.method} reached its trial budget of {budget} right-hand sides "
            f"by t = {t:.4g} s ({self.trial_factor:g} x the anchor's {anchor}; {words}): a "
            "failed trial", budget)

    def _unstable(self, params: Tensor, why: str) -> UnstableStepError:
        omega, rate, words = self._rates(params)
        limit = STABILITY_LIMIT.get(self.method, 0.0)
        if self.method in FIXED_METHODS:
            if limit > 0 and rate > 0:
                detail = (f" (step {self.step_size:g} s; {words}, needs a step below about "
                          f"{limit / rate:.3g} s)")
            else:
                detail = (f" (step {self.step_size:g} s; {self.method} is unstable for an "
                          f"undamped oscillation at any step; omega_max = {omega:.4g} rad/s)")
        else:
            detail = f" ({words})"
        return UnstableStepError(
            f"the explicit integrator torchdiffeq/{self.method} {why}{detail}; use "
            "problem.integrator=implicit (backward Euler or BDF2, unconditionally stable) or a "
            "smaller step")

    # -- public -------------------------------------------------------------------------------
    def trial_budget(self, params: Tensor) -> int | None:
        """Right-hand sides an integration at ``params`` may take (``None``: no limit): a
        trial (not the anchor's parameters) of an adaptive method with ``trial_factor > 0``
        gets ``trial_factor`` x the anchor's count."""
        anchor = self._anchor
        if self.trial_factor <= 0 or self.method in FIXED_METHODS or anchor is None or \
                (anchor[0].shape == params.shape and torch.equal(anchor[0], params)):
            return None
        return max(1, math.ceil(self.trial_factor * anchor[1]))

    def _take_anchor(self, solve: _Solve) -> None:
        """Derivatives are taken at ``solve``: the trials' reference from now on."""
        self._anchor = (solve.params, solve.evaluations)

    def solve(self, params: Tensor) -> _Solve:
        """The forward integration at ``params`` (cached by value), with the adjoint graph;
        a trial's is limited by :meth:`trial_budget`."""
        params = params.detach()
        for i, solve in enumerate(self._cache):
            if solve.params.shape == params.shape and torch.equal(solve.params, params):
                self._cache.append(self._cache.pop(i))
                return solve
        self.system.check_params(params)
        before = self.evaluations
        states, leaf, _ = self._integrate(params, adjoint=True, budget=self.trial_budget(params))
        outputs = self._positions(states.detach(), self.output_times.to(params))
        solve = _Solve(params.clone(), outputs, states, leaf, self.evaluations - before)
        self._cache.append(solve)
        while len(self._cache) > self.cache_size:
            self._cache.pop(0)
        return solve

    def __call__(self, params: Tensor) -> Tensor:
        """Positions ``(K, n_dofs)`` at the output times (reverse and forward mode)."""
        return TrajectoryFunction.apply(params, self)

    def jacobian(self, params: Tensor, directions: Tensor) -> Tensor:
        """``(d positions / d params) V`` ``(K, n_dofs, k)`` by forward sensitivities."""
        params = params.detach()
        self._take_anchor(self.solve(params))
        return self._sensitivities(params, directions.detach().to(params))

    def clear_cache(self) -> None:
        self._cache.clear()
        self._anchor = None

    # -- the TrajectoryFunction protocol ---------------------------------------------------------
    def run(self, params: Tensor) -> _Solve:
        return self.solve(params)

    def adjoint(self, solve: _Solve, grad_outputs: Tensor) -> Tensor:
        self._take_anchor(solve)
        return self._adjoint(solve, grad_outputs)

    def tangents(self, solve: _Solve, V: Tensor) -> Tensor:
        self._take_anchor(solve)
        return self._sensitivities(solve.params, V)

    # -- derivatives ----------------------------------------------------------------------------
    def _adjoint(self, solve: _Solve, grad_outputs: Tensor) -> Tensor:
        n_free = self.system.free_dofs.numel()
        free = self.system.free_dofs.to(grad_outputs.device)
        grad_states = torch.zeros_like(solve.graph_out)
        grad_states[:, :n_free] = grad_outputs[:, free]
        try:
            (grad,) = torch.autograd.grad(solve.graph_out, solve.graph_leaf, grad_states,
                                          retain_graph=True, allow_unused=True)
        except AssertionError as error:
            raise self._unstable(solve.params, f"failed: its adjoint step collapsed ({error})") from None
        return torch.zeros_like(solve.params) if grad is None else grad

    @staticmethod
    def _tangent_columns(value: Tensor, p_leaf: Tensor, y_leaf: Tensor, V: Tensor,
                         S: Tensor) -> Tensor:
        """``(df/dparams) V + (df/dy) S`` ``(n_state, k)`` for ``V`` ``(n_params, k)`` and
        ``S`` ``(n_state, k)``; ``value = f(t, y_leaf; p_leaf)`` with its graph.

        Two reverse passes for all ``k`` columns: ``g(u) = (df/d(p, y))^T u`` with a probe
        ``u``, then the batched derivative of ``<g(u), (v_j, s_j)>`` in ``u``
        (``is_grads_batched``: ``torch.vmap`` over the second pass). Reverse mode because
        this runs inside a custom Function's forward-mode rule, where forward-mode AD
        cannot nest.
        """
        probe = torch.zeros_like(value, requires_grad=True)
        g_p, g_y = torch.autograd.grad(value, (p_leaf, y_leaf), probe, create_graph=True,
                                       allow_unused=True)
        pairs = [(g, d) for g, d in ((g_p, V), (g_y, S)) if g is not None and g.requires_grad]
        if not pairs:
            return value.new_zeros(value.numel(), V.shape[1])
        (columns,) = torch.autograd.grad([g for g, _ in pairs], probe,
                                         [d.T.contiguous().to(g) for g, d in pairs],
                                         is_grads_batched=True, allow_unused=True)
        if columns is None:
            return value.new_zeros(value.numel(), V.shape[1])
        return columns.T

    def _sensitivities(self, params: Tensor, V: Tensor) -> Tensor:
        """Forward sensitivities of the positions along the columns of ``V`` (n_params, k).

        One augmented solve: the state ``y`` (``2 n_free``) and its ``k`` tangent columns
        ``S = dy/dparams V`` (``2 n_free x k``) integrated together by one ``odeint`` call,
        ``S' = (df/dy) S + (df/dparams) V``; every right-hand side forms all ``k`` columns
        in two reverse passes (:meth:`_tangent_columns`), whatever ``k``.
        """
        from torchdiffeq import odeint

        times, prepended = self._times(params)
        n_state = 2 * self.system.free_dofs.numel()
        k = V.shape[1]
        rhs = self._rhs
        tangent_columns = self._tangent_columns

        def augmented(t: Tensor, z: Tensor) -> Tensor:
            y, s = z[:n_state], z[n_state:].reshape(n_state, k)
            with torch.enable_grad():
                p_leaf = params.detach().requires_grad_(True)
                y_leaf = y.detach().requires_grad_(True)
                value = rhs(p_leaf, guard=False)(t, y_leaf)
                columns = tangent_columns(value, p_leaf, y_leaf, V, s)
            return torch.cat([value.detach(), columns.reshape(-1).detach()])

        z0 = torch.cat([self._y0(params), params.new_zeros(n_state * k)])
        with torch.no_grad():
            z = odeint(augmented, z0, times, **self._options())
        if prepended:
            z = z[1:]
        s = z[:, n_state:].reshape(-1, n_state, k)[:, :n_state // 2, :]
        out = params.new_zeros(s.shape[0], self.system.n_dofs, k)
        out[:, self.system.free_dofs.to(out.device), :] = s
        return out
