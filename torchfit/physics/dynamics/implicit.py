"""Implicit time integration (backward Euler, BDF2): every step is an equilibrium solve.

With step ``h`` from state ``n`` to ``n + 1`` both methods write the new velocity and
acceleration as affine functions of the new position (variable-step BDF2 coefficients
``c0, c1, c2``; backward Euler is ``c0 = 1/h, c1 = -1/h, c2 = 0``):

    v_{n+1} = c0 x_{n+1} + b_v,   b_v = c1 x_n + c2 x_{n-1}
    a_{n+1} = c0 v_{n+1} + c1 v_n + c2 v_{n-1} = c0^2 x_{n+1} + b_a,  b_a = c0 b_v + c1 v_n + c2 v_{n-1}

so the step is the root of the *step residual* (free dofs; Dirichlet dofs at ``x_D(t_{n+1})``)

    R(x; p) = s M (c0^2 x + b_a - g) + (alpha s M + beta K0(k)) (c0 x + b_v - v_ref) + R_el(x; k) - f(t_{n+1})

with ``p = [k, alpha, beta, (s,) b_a, b_v - v_ref, f, c0^2, c0]`` (``v_ref(t_{n+1})``: the
system's reference velocity, zero by default; ``g`` gravity, ``f`` the loads; ``s`` the
density scale where the system has one, else 1). :class:`StepModel` is an
:class:`~torchfit.physics.EquilibriumModel` of it, and each step is solved by the generic
:class:`~torchfit.physics.Equilibrium` (Newton with line search for a nonlinear material,
one factorisation and one solve for a linear one). Derivatives are the equilibrium's own
implicit-function adjoint per step: backward solves ``K_step^T lam = xbar`` with the step's
factor and takes ``-(dR/dp)^T lam``; ``p``'s history part ``(b_a, b_v)`` carries the
adjoint to the earlier states (a discrete adjoint of the whole trajectory, exact to round-off:
the dot-product test holds to 1e-12). ``J v`` propagates tangents forward with the same factors
(``Equilibrium.jacobian``, several directions at once for the dense Jacobian).

BDF2 starts with one backward Euler step (global order 2 is kept).

Memory (checkpointing). ``checkpoint_every = c``:

* ``c = 1``: every step's state ``(x, v)`` and its factorisation are kept with the
  trajectory: a gradient or ``J v`` costs one solve per step and no factorisation
  (``S + 1`` states and ``S`` factors stored, ``S`` steps).
* ``c > 1``: only the states at every ``c``-th step (and the one before it, BDF2's
  history) are kept; a gradient or ``J v`` recomputes one segment of ``c`` steps at a time
  from its checkpoint (the forward's Newton solves again) and factorises each step's
  tangent once: about ``2 S / c + c`` states and one factorisation alive at a time.
  ``c = ceil(sqrt(S))`` (``checkpoint_every=0``) balances the two.

Counters: every factorisation and solve goes through the linear-algebra backends and is
counted by :mod:`torchfit.linalg.counters` exactly as for quasistatic problems.
"""
from __future__ import annotations

import dataclasses
import inspect
import math
from typing import Any

import torch
from torch import Tensor

from ...linalg import SparsePattern
from ..equilibrium import Equilibrium, NewtonConvergenceError, NewtonOptions
from .errors import DynamicsInputError, NonFiniteStateError, UnstableStepError
from .system import DynamicSystem, TrajectoryFunction, check_output_times

SCHEMES = ("backward_euler", "bdf2")


class StepModel:
    """The step residual ``R(x; p)`` of one implicit step (module docstring) as an
    :class:`~torchfit.physics.EquilibriumModel` (one frame; ``p`` packs the physical
    parameters, the history terms, the external force and the two step coefficients)."""

    symmetric = True

    def __init__(self, system: DynamicSystem) -> None:
        self.system = system
        self.n_dofs = system.n_dofs
        self.linear = bool(system.elastic.linear)
        n = self.n_dofs
        diagonal = torch.arange(n)
        self.n_elastic = int(system.element_rows.numel())
        self.tangent_pattern = SparsePattern(torch.cat([system.element_rows.cpu(), diagonal]),
                                             torch.cat([system.element_cols.cpu(), diagonal]),
                                             (n, n))
        self.n_params = system.n_params + 3 * n + 2
        try:
            parameters = inspect.signature(system.elastic.tangent_values).parameters
        except (TypeError, ValueError):  # pragma: no cover - builtins
            parameters = {}
        self._projected = "projected" in parameters

    def pack(self, params: Tensor, b_a: Tensor, b_v: Tensor, force: Tensor, c_a: float,
             c_v: float) -> Tensor:
        """``p`` ``(n_params,)`` of one step."""
        coefficients = torch.tensor([c_a, c_v], dtype=params.dtype, device=params.device)
        return torch.cat([params, b_a, b_v, force, coefficients])

    def mass(self, p: Tensor) -> Tensor:
        """``s M`` ``(n_dofs,)``: the lumped mass at ``p``'s density scale."""
        return self.system.mass_scale(p) * self.system.mass.to(p)

    def unpack(self, p: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """``(k, alpha, beta, b_a, b_v, f, c_a, c_v)`` of ``p`` (the density scale:
        :meth:`mass`)."""
        m, n = self.system.n_params, self.n_dofs
        field, alpha, beta = self.system.split(p[:m])
        b_a, b_v, force = p[m:m + n], p[m + n:m + 2 * n], p[m + 2 * n:m + 3 * n]
        return field, alpha, beta, b_a, b_v, force, p[m + 3 * n], p[m + 3 * n + 1]

    def residual(self, x: Tensor, p: Tensor) -> Tensor:
        """``R(x; p)`` ``(F, n_dofs)`` for positions ``(F, n_dofs)``."""
        field, alpha, beta, b_a, b_v, force, c_a, c_v = self.unpack(p)
        mass = self.mass(p).to(x)
        v = c_v * x + b_v
        return mass * (c_a * x + b_a - self.system.gravity.to(x)) + alpha * mass * v + \
            beta * self.system.stiffness_matvec(field, v) + \
            self.system.elastic.residual(x, field) - force

    def tangent_values(self, x: Tensor, p: Tensor, projected: bool = False) -> Tensor:
        """``dR/dx`` contributions ``(F or 1, n_contrib)``: the elastic tangent plus
        ``beta c_v K0`` on the elastic slots, ``(c_a + alpha c_v) M`` on the diagonal."""
        field, alpha, beta, _, _, _, c_a, c_v = self.unpack(p)
        if projected and self._projected:
            elastic = self.system.elastic.tangent_values(x, field, projected=True)
        else:
            elastic = self.system.elastic.tangent_values(x, field)
        elastic = elastic + (beta * c_v) * self.system.rest_stiffness_contributions(field)[None]
        diagonal = ((c_a + alpha * c_v) * self.mass(p).to(elastic))[None]
        return torch.cat([elastic, diagonal.expand(elastic.shape[0], -1)], dim=1)

    def param_derivative(self, x: Tensor, p: Tensor) -> "StepParamDerivative":
        return StepParamDerivative(self, x.detach(), p.detach())


class StepParamDerivative:
    """``dR/dp`` of :class:`StepModel` at fixed positions ``x`` ``(1, n_dofs)``, as products
    (``jvp``, ``vjp``, ``matmul``; the ``c_a, c_v`` entries are constants: zero rows)."""

    def __init__(self, model: StepModel, x: Tensor, p: Tensor) -> None:
        self.model = model
        system = model.system
        self.system = system
        (self.field, self.alpha, self.beta, b_a, b_v, _, c_a, c_v) = model.unpack(p)
        self.x = x
        self.velocity = c_v * x[0] + b_v                               # (n,)
        self.mass = model.mass(p).to(x)                                # s M
        # dR/ds: M (a - g) + alpha M v, the inertia, weight and mass damping per unit scale
        self.scaled = system.density_scaled
        self.mass_rate: Tensor | None = None        # without a density scale: not read
        if self.scaled:
            unit_mass = system.mass.to(x)
            self.mass_rate = unit_mass * (c_a * x[0] + b_a - system.gravity.to(x)) + \
                self.alpha * unit_mass * self.velocity
        self.k0_velocity = system.stiffness_matvec(self.field, self.velocity)
        self.unit_forces = system.unit_element_forces(self.velocity)   # (n_field, d_el)
        elastic_derivative = getattr(system.elastic, "param_derivative", None)
        self.elastic = elastic_derivative(x, self.field) if elastic_derivative else None

    def _split(self, v: Tensor) -> tuple[Tensor, ...]:
        """``(d_field, d_alpha, d_beta, d_ba, d_bv, d_force, d_scale)`` of ``v`` (``d_scale``
        ``None`` without a density scale)."""
        m, n = self.system.n_params, self.model.n_dofs
        nf = self.system.n_field
        return (v[:nf], v[nf], v[nf + 1], v[m:m + n], v[m + n:m + 2 * n], v[m + 2 * n:m + 3 * n],
                v[nf + 2] if self.scaled else None)

    def _elastic_jvp(self, d_field: Tensor) -> Tensor:
        if self.elastic is not None:
            return self.elastic.jvp(d_field)[0]
        with torch.enable_grad():
            field = self.field.detach().requires_grad_(True)
            r = self.system.elastic.residual(self.x, field)
            probe = torch.zeros_like(r, requires_grad=True)
            (g,) = torch.autograd.grad(r, field, probe, create_graph=True)
            (out,) = torch.autograd.grad((g * d_field).sum(), probe)
        return out[0]

    def _elastic_vjp(self, w: Tensor) -> Tensor:
        if self.elastic is not None:
            return self.elastic.vjp(w[None])
        with torch.enable_grad():
            field = self.field.detach().requires_grad_(True)
            r = self.system.elastic.residual(self.x, field)
            (g,) = torch.autograd.grad(r, field, w[None])
        return g

    def jvp(self, v: Tensor) -> Tensor:
        """``(dR/dp) v`` ``(1, n_dofs)`` for ``v`` ``(n_params,)``."""
        d_field, d_alpha, d_beta, d_ba, d_bv, d_force, d_scale = self._split(v.to(self.x))
        out = self._elastic_jvp(d_field) \
            + self.beta * self.system.scatter_elements(self.unit_forces * d_field[:, None]) \
            + d_alpha * self.mass * self.velocity + d_beta * self.k0_velocity \
            + self.mass * d_ba + self.alpha * self.mass * d_bv \
            + self.beta * self.system.stiffness_matvec(self.field, d_bv) - d_force
        if d_scale is not None:
            out = out + d_scale * self.mass_rate
        return out[None]

    def vjp(self, w: Tensor) -> Tensor:
        """``(dR/dp)^T w`` ``(n_params,)`` for ``w`` ``(1, n_dofs)``."""
        w = w.to(self.x)[0]
        local = w[self.system.element_dofs.to(w.device)]               # (n_field, d_el)
        g_field = self._elastic_vjp(w) + self.beta * (local * self.unit_forces).sum(dim=1)
        g_alpha = (w * self.mass * self.velocity).sum()
        g_beta = (w * self.k0_velocity).sum()
        g_ba = self.mass * w
        g_bv = self.alpha * self.mass * w + self.beta * self.system.stiffness_matvec(self.field, w)
        zeros = w.new_zeros(2)
        g_scale = [(w * self.mass_rate).sum()[None]] if self.scaled else []
        return torch.cat([g_field, g_alpha[None], g_beta[None], *g_scale, g_ba, g_bv, -w, zeros])

    def matmul(self, V: Tensor) -> Tensor:
        """``(dR/dp) V`` ``(1, n_dofs, k)`` for ``V`` ``(n_params, k)``."""
        V = V.to(self.x)
        d_field, d_alpha, d_beta, d_ba, d_bv, d_force, d_scale = self._split(V)
        if self.elastic is not None and callable(getattr(self.elastic, "matmul", None)):
            elastic = self.elastic.matmul(d_field)[0]
        elif self.elastic is not None:
            elastic = torch.stack([self.elastic.jvp(d_field[:, j])[0]
                                   for j in range(V.shape[1])], dim=-1)
        else:
            elastic = torch.stack([self._elastic_jvp(d_field[:, j]) for j in range(V.shape[1])],
                                  dim=-1)
        damping = torch.sparse.mm(self.system.element_matrix(self.unit_forces),
                                  d_field.contiguous())
        k0_dbv = self.system.stiffness_matmul(self.field, d_bv)
        out = elastic + self.beta * damping \
            + (self.mass * self.velocity)[:, None] * d_alpha[None, :] \
            + self.k0_velocity[:, None] * d_beta[None, :] \
            + self.mass[:, None] * d_ba + self.alpha * self.mass[:, None] * d_bv \
            + self.beta * k0_dbv - d_force
        if d_scale is not None:
            out = out + self.mass_rate[:, None] * d_scale[None, :]
        return out[None]


@dataclasses.dataclass
class _Trajectory:
    """A forward solve: outputs, the states kept (checkpoints) and, with
    ``checkpoint_every = 1``, every step's equilibrium solution (its factors and, once
    built, its parameter derivative)."""

    params: Tensor
    outputs: Tensor                                # (K, n_dofs)
    states: dict[int, tuple[Tensor, Tensor]]       # step -> (x, v), full dofs
    solutions: list[Any] | None                    # every step's equilibrium solution (c = 1)


class ImplicitIntegrator:
    """Backward Euler or BDF2 through the equilibrium core (module docstring).

    Args:
        system: the :class:`DynamicSystem`.
        output_times: ``(K,)`` strictly increasing times ``>= t0`` (s).
        dt: largest step (s); each interval between output times is cut into equal steps
            no longer than ``dt`` (outputs land on steps, no interpolation).
        scheme: ``'bdf2'`` (second order) or ``'backward_euler'`` (first order).
        backend: linear-solve backend of the step equilibria.
        newton: Newton settings of a nonlinear step (tolerances relative to the residual
            at the predictor ``x_n + h v_n``).
        checkpoint_every: ``c`` (module docstring); 0 means ``ceil(sqrt(S))``.
        cache_size: trajectories kept (keyed by the parameters: ``J v`` and ``J^T w`` at
            a point already simulated do not integrate again).
        split: every step of the ``dt`` grid cut into this many equal steps (the step
            halving of :meth:`error_estimate`: ``refined``).
    """

    name = "implicit"

    def __init__(self, system: DynamicSystem, output_times: Tensor | list[float], dt: float,
                 scheme: str = "bdf2", backend: str = "scipy", newton: NewtonOptions | None = None,
                 checkpoint_every: int = 1, cache_size: int = 2, split: int = 1) -> None:
        if scheme not in SCHEMES:
            raise DynamicsInputError(f"unknown implicit scheme {scheme!r}; choose one of "
                                     f"{', '.join(SCHEMES)}")
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise DynamicsInputError(f"the time step dt = {dt!r} must be a positive number (s)")
        if not (isinstance(checkpoint_every, int) and checkpoint_every >= 0):
            raise DynamicsInputError(f"checkpoint_every = {checkpoint_every!r} must be an "
                                     "integer >= 0 (0: ceil(sqrt(steps)))")
        self.system = system
        self.scheme = scheme
        self.dt = float(dt)
        self.backend = backend
        self.split = int(split)
        self.output_times = check_output_times(output_times, system.t0)
        self.model = StepModel(system)
        newton = dataclasses.replace(newton) if newton is not None else NewtonOptions()
        self.newton = dataclasses.replace(newton)
        self._atol = newton.atol
        self.equilibrium = Equilibrium(self.model, system.fixed_dofs, backend=backend,
                                       newton=newton, cache_size=2,
                                       allow_no_dirichlet=True, warm_start=False)
        self._build_grid()
        self.checkpoint_every = checkpoint_every or max(1, math.ceil(math.sqrt(self.n_steps)))
        self.cache_size = int(cache_size)
        self._cache: list[_Trajectory] = []
        self.static_increments = 0      # the loaded solves of the last static_equilibrium

    @property
    def order(self) -> int:
        """The scheme's order of accuracy (BDF2: 2, backward Euler: 1)."""
        return 2 if self.scheme == "bdf2" else 1

    def refined(self, factor: int = 2) -> "ImplicitIntegrator":
        """The same integration (system, output times, scheme, backend, Newton settings) with
        every step cut into ``factor`` equal ones: the reference of an error estimate
        (:meth:`error_estimate`), outputs only (``checkpoint_every=0``: no step's factor is
        kept; with every one kept the 48-frame arm's 376 halved steps would hold gigabytes)."""
        return ImplicitIntegrator(self.system, self.output_times, self.dt,
                                  scheme=self.scheme, backend=self.backend, newton=self.newton,
                                  checkpoint_every=0, cache_size=1, split=self.split * factor)

    def error_estimate(self, params: Tensor) -> dict[str, float]:
        """The integration error of the outputs at ``params``, by step halving: with the
        outputs ``x_h`` and ``x_{h/2}`` of this step and half of it, Richardson's estimate of
        this integration's error is ``|x_h - x_{h/2}| 2^p / (2^p - 1)`` (``p``: :attr:`order`;
        the largest over dofs and outputs). Costs one integration with twice the steps.

        Returns ``{"difference", "estimate", "steps", "reference_steps"}`` (the units of the
        positions)."""
        with torch.no_grad():
            coarse = self(params.detach())
            fine_integrator = self.refined(2)
            fine = fine_integrator(params.detach())
        difference = float((coarse - fine).abs().max())
        p = self.order
        return {"difference": difference, "estimate": difference * 2 ** p / (2 ** p - 1),
                "steps": int(self.n_steps), "reference_steps": int(fine_integrator.n_steps)}

    def static_equilibrium(self, params: Tensor, x_init: Tensor, min_fraction: float = 1 / 1024,
                           max_increments: int = 128) -> Tensor:
        """Positions ``(n_dofs,)`` at rest in equilibrium at ``t0`` under the external force
        (gravity, loads): ``R_el(x; k) = f_ext(t0)``, no inertia, no damping, the prescribed
        dofs at ``x_D(t0)``; Newton from ``x_init`` (no graph: a start is data).

        Where Newton cannot take the whole load from ``x_init`` at once (a soft body whose
        sag is large: its residual stalls on the way), the load is applied in increments,
        each solve starting from the last equilibrium and converged to the tolerance of the
        whole load's (``newton.rtol`` times its residual at ``x_init``): the increment grows
        by half after a success and halves after a failure. Below ``min_fraction`` of the
        load, or after ``max_increments`` solves, the last failure is raised.
        :attr:`static_increments` counts the loaded solves of the last call (1: the whole
        load at once)."""
        t0 = self.step_times[:1].to(x_init)
        fixed = self.system.fixed_positions(t0)
        zeros = x_init.new_zeros(self.system.n_dofs)
        params = params.detach().to(x_init)
        gravity = self.system.gravity.to(x_init)
        loads = self.system.loads_at(t0)[0]

        def loaded(fraction: float) -> Tensor:
            # the step residual without inertia is s M (b_a - g) + R_el - f: b_a = (1 - l) g
            # leaves the weight's fraction l
            return self.model.pack(params, (1.0 - fraction) * gravity, zeros,
                                   fraction * loads, 0.0, 0.0)

        def solve(fraction: float, start: Tensor) -> Tensor:
            self.static_increments += 1
            with torch.no_grad():
                return self.equilibrium(loaded(fraction), fixed, start.reshape(1, -1))[0]

        self.static_increments = 0
        try:
            x = solve(1.0, x_init)
        except NewtonConvergenceError:
            newton = self.equilibrium.newton
            start = x_init.detach().clone().reshape(1, -1)
            start[:, self.system.fixed_dofs.to(start.device)] = fixed
            whole = self.model.residual(start, loaded(1.0))[0][self.system.free_dofs]
            floor = newton.atol
            newton.atol = max(floor, newton.rtol * float(torch.linalg.vector_norm(whole)))
            try:
                x, done, increment = start[0], 0.0, 0.25
                while done < 1.0:
                    target = min(1.0, done + increment)
                    try:
                        x = solve(target, x)
                    except NewtonConvergenceError:
                        if increment <= min_fraction or self.static_increments >= max_increments:
                            raise
                        increment /= 2
                        continue
                    done, increment = target, 1.5 * increment
            finally:
                newton.atol = floor
        self.system.check_state(x, float(t0[0]))
        return x

    # -- the time grid --------------------------------------------------------------------
    def _build_grid(self) -> None:
        t0 = self.system.t0
        nodes = [t0] + [float(t) for t in self.output_times if float(t) > t0]
        times = [t0]
        for start, stop in zip(nodes[:-1], nodes[1:]):
            m = max(1, math.ceil((stop - start) / self.dt - 1e-9)) * self.split
            times.extend(start + (stop - start) * (i + 1) / m for i in range(m))
            times[-1] = stop
        self.step_times = torch.tensor(times, dtype=torch.float64)
        self.n_steps = len(times) - 1
        h = self.step_times[1:] - self.step_times[:-1]
        coefficients = []
        for n in range(self.n_steps):
            hn = float(h[n])
            if self.scheme == "backward_euler" or n == 0:
                coefficients.append((1.0 / hn, -1.0 / hn, 0.0))
            else:
                w = hn / float(h[n - 1])
                coefficients.append(((1 + 2 * w) / ((1 + w) * hn), -(1 + w) / hn,
                                     w * w / ((1 + w) * hn)))
        self.coefficients = coefficients
        self.step_sizes = h
        index = {round(float(t), 12): i for i, t in enumerate(self.step_times)}
        self.output_steps = [index[round(float(t), 12)] if float(t) > t0 else 0
                             for t in self.output_times]
        self._output_of_step: dict[int, list[int]] = {}
        for k, step in enumerate(self.output_steps):
            self._output_of_step.setdefault(step, []).append(k)

    def segments(self) -> list[tuple[int, int]]:
        """Step ranges ``[a, b)`` between checkpoints."""
        c = self.checkpoint_every
        return [(a, min(a + c, self.n_steps)) for a in range(0, self.n_steps, c)]

    @property
    def stored_states(self) -> int:
        """States ``(x, v)`` a forward solve keeps for the gradient (module docstring)."""
        if self.checkpoint_every == 1:
            return self.n_steps + 1
        kept = {a for a, _ in self.segments()} | {a - 1 for a, _ in self.segments() if a > 0}
        return len(kept)

    # -- one step -------------------------------------------------------------------------
    def _inputs(self, n: int, params: Tensor, x: Tensor, v: Tensor, x_prev: Tensor | None,
                v_prev: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        """``(p, fixed values (1, n_fixed), b_v)`` of step ``n`` (state ``n`` -> ``n + 1``)."""
        c0, c1, c2 = self.coefficients[n]
        b_v = c1 * x
        b_a = c1 * v
        if c2:
            b_v = b_v + c2 * x_prev
            b_a = b_a + c2 * v_prev
        b_a = c0 * b_v + b_a
        t_next = self.step_times[n + 1:n + 2].to(x)
        force = self.system.loads_at(t_next)[0]           # the weight is in the residual
        if not bool(torch.isfinite(force).all()):
            dof = int(torch.nonzero(~torch.isfinite(force))[0])
            raise NonFiniteStateError(
                f"the state is not finite at t = {float(t_next):.6g}: the external force on "
                f"vertex {dof // self.system.vertex_dim} (dof {dof}) is {float(force[dof])}")
        # the damping acts on v - v_ref: b_v shifted by v_ref in p (its derivatives are b_v's)
        if self.system.reference_velocity is not None:
            shifted = b_v - self.system.damped_against(t_next)[0]
        else:
            shifted = b_v
        p = self.model.pack(params, b_a, shifted, force, c0 * c0, c0)
        return p, self.system.fixed_positions(t_next), b_v

    def _advance(self, n: int, params: Tensor, state: tuple[Tensor, Tensor],
                 previous: tuple[Tensor, Tensor] | None, keep: bool = False
                 ) -> tuple[Tensor, Tensor, Any]:
        x, v = state
        x_prev, v_prev = previous if previous is not None else (None, None)
        p, fixed, b_v = self._inputs(n, params, x, v, x_prev, v_prev)
        predictor = (x + float(self.step_sizes[n]) * v)[None]
        # Newton's absolute floor follows the inertia term's round-off (M c0^2 x grows as
        # 1/h^2: a fixed floor cannot be met with small steps). 1000 eps of it: at 100 eps
        # the arm's held-out window stalled at 1.4 times the floor (the damping and elastic
        # terms' round-off adds to the inertia's); 1000 eps is still 1e-13 of that term
        inertia = float(torch.linalg.vector_norm(self.system.mass.to(x) * x)) * \
            self.coefficients[n][0] ** 2
        self.equilibrium.newton.atol = max(self._atol, 1000.0 * torch.finfo(x.dtype).eps * inertia)
        with torch.no_grad():
            try:
                x_new = self.equilibrium(p, fixed, predictor)[0]
            except NewtonConvergenceError as error:
                t = float(self.step_times[n + 1])
                raise UnstableStepError(
                    f"the implicit step to t = {t:.6g} s (step {n + 1} of {self.n_steps}, "
                    f"{1e3 * float(self.step_sizes[n]):.3g} ms) did not converge: the step is "
                    f"too long for this motion and material; take shorter steps ("
                    f"{' '.join(str(error).split())})", time=t, step=n + 1) from error
        self.system.check_state(x_new, float(self.step_times[n + 1]))
        v_new = self.coefficients[n][0] * x_new + b_v
        solution = self.equilibrium.solution(p, fixed, None) if keep else None
        return x_new, v_new, solution

    def initial_state(self, like: Tensor) -> tuple[Tensor, Tensor]:
        """``(x0, v0)`` with the Dirichlet dofs on the trajectory at ``t0``."""
        t0 = self.step_times[:1].to(like)
        x0 = self.system.x0.to(like).clone()
        v0 = self.system.v0.to(like).clone()
        fixed = self.system.fixed_dofs.to(like.device)
        if fixed.numel():
            x0[fixed] = self.system.fixed_positions(t0)[0]
            v0[fixed] = self.system.fixed_velocities(t0)[0]
        return x0, v0

    # -- whole trajectories -----------------------------------------------------------------
    def trajectory(self, params: Tensor) -> _Trajectory:
        """The forward solve at ``params`` (cached by value)."""
        params = params.detach()
        for i, traj in enumerate(self._cache):
            if traj.params.shape == params.shape and torch.equal(traj.params, params):
                self._cache.append(self._cache.pop(i))
                return traj
        self.system.check_params(params)
        traj = self._run(params)
        self._cache.append(traj)
        while len(self._cache) > self.cache_size:
            self._cache.pop(0)
        return traj

    def _run(self, params: Tensor) -> _Trajectory:
        keep_all = self.checkpoint_every == 1
        kept = {a for a, _ in self.segments()} | {a - 1 for a, _ in self.segments() if a > 0}
        state = self.initial_state(params)
        previous = None
        states = {0: state}
        solutions: list[Any] | None = [] if keep_all else None
        outputs = params.new_zeros(len(self.output_steps), self.system.n_dofs)
        for k in self._output_of_step.get(0, []):
            outputs[k] = state[0]
        for n in range(self.n_steps):
            x, v, solution = self._advance(n, params, state, previous, keep_all)
            previous, state = state, (x, v)
            if keep_all or (n + 1) in kept:
                states[n + 1] = state
            if solutions is not None:
                solutions.append(solution)
            for k in self._output_of_step.get(n + 1, []):
                outputs[k] = x
        return _Trajectory(params.clone(), outputs, states, solutions)

    def _segment_states(self, traj: _Trajectory, a: int, b: int) -> dict[int, tuple[Tensor, Tensor]]:
        """States ``n = a - 1 .. b`` of segment ``[a, b)`` (recomputed from the checkpoint
        at ``a`` when not kept)."""
        wanted = range(max(a - 1, 0), b + 1)
        if all(n in traj.states for n in wanted):
            return {n: traj.states[n] for n in wanted}
        states = {n: traj.states[n] for n in (a - 1, a) if n in traj.states}
        for n in range(a, b):
            x, v, _ = self._advance(n, traj.params, states[n], states.get(n - 1))
            states[n + 1] = (x, v)
        return states

    def __call__(self, params: Tensor) -> Tensor:
        """Positions ``(K, n_dofs)`` at the output times; differentiable in reverse mode
        (discrete adjoint) and forward mode (tangent propagation)."""
        return TrajectoryFunction.apply(params, self)

    def jacobian(self, params: Tensor, directions: Tensor) -> Tensor:
        """``(d positions / d params) V``: ``(K, n_dofs, k)`` for ``V`` ``(n_params, k)``
        (one solve with ``k`` right-hand sides per step; no graph)."""
        traj = self.trajectory(params)
        return self._tangents(traj, directions.detach().to(traj.params))

    def clear_cache(self) -> None:
        self._cache.clear()
        self.equilibrium.clear_cache()

    # -- the TrajectoryFunction protocol -------------------------------------------------------
    def run(self, params: Tensor) -> _Trajectory:
        return self.trajectory(params)

    def adjoint(self, traj: _Trajectory, grad_outputs: Tensor) -> Tensor:
        return self._adjoint(traj, grad_outputs)

    def tangents(self, traj: _Trajectory, V: Tensor) -> Tensor:
        return self._tangents(traj, V)

    # -- derivatives --------------------------------------------------------------------------
    def _prepare(self, traj: _Trajectory, n: int, p: Tensor, fixed: Tensor, x: Tensor) -> None:
        """Make step ``n``'s solution the equilibrium's cached one: the stored solution
        (``c = 1``: no factorisation) or the state ``x`` adopted (one factorisation)."""
        if traj.solutions is not None:
            self.equilibrium.restore(traj.solutions[n])
        else:
            self.equilibrium.adopt(p, fixed, x[None])

    def _tangents(self, traj: _Trajectory, V: Tensor) -> Tensor:
        n_dofs, k = self.system.n_dofs, V.shape[1]
        zeros = V.new_zeros(n_dofs, k)
        dx, dv, dx_prev, dv_prev = zeros, zeros, zeros, zeros
        out = V.new_zeros(len(self.output_steps), n_dofs, k)
        tail = V.new_zeros(n_dofs + 2, k)
        for a, b in self.segments():
            states = self._segment_states(traj, a, b)
            for n in range(a, b):
                c0, c1, c2 = self.coefficients[n]
                p, fixed, _ = self._inputs(n, traj.params, *states[n],
                                           *(states.get(n - 1) or (None, None)))
                d_bv = c1 * dx + (c2 * dx_prev if c2 else 0.0)
                d_ba = c0 * d_bv + c1 * dv + (c2 * dv_prev if c2 else 0.0)
                directions = torch.cat([V, d_ba, d_bv, tail])
                self._prepare(traj, n, p, fixed, states[n + 1][0])
                dx_new = self.equilibrium.jacobian(p, fixed, directions)[0]
                dv_new = c0 * dx_new + d_bv
                dx_prev, dv_prev, dx, dv = dx, dv, dx_new, dv_new
                for j in self._output_of_step.get(n + 1, []):
                    out[j] = dx
        return out

    def _adjoint(self, traj: _Trajectory, grad_outputs: Tensor) -> Tensor:
        """``(d outputs / d params)^T grad_outputs`` ``(n_params,)``: the reverse sweep."""
        m = self.system.n_params
        n_dofs = self.system.n_dofs
        xbar: dict[int, Tensor] = {}
        vbar: dict[int, Tensor] = {}
        for k, step in enumerate(self.output_steps):
            xbar[step] = xbar.get(step, 0.0) + grad_outputs[k]
        grad = traj.params.new_zeros(m)
        for a, b in reversed(self.segments()):
            if not any(n > a for n in xbar) and not any(n > a for n in vbar):
                continue
            states = self._segment_states(traj, a, b)
            for n in range(b - 1, a - 1, -1):
                xb, vb = xbar.pop(n + 1, None), vbar.pop(n + 1, None)
                if xb is None and vb is None:
                    continue
                xb = torch.zeros(n_dofs, dtype=grad.dtype) if xb is None else xb
                vb = torch.zeros(n_dofs, dtype=grad.dtype) if vb is None else vb
                c0, c1, c2 = self.coefficients[n]
                p, fixed, _ = self._inputs(n, traj.params, *states[n],
                                           *(states.get(n - 1) or (None, None)))
                self._prepare(traj, n, p, fixed, states[n + 1][0])
                with torch.enable_grad():
                    leaf = p.detach().requires_grad_(True)
                    x_solution = self.equilibrium(leaf, fixed)
                    (pbar,) = torch.autograd.grad(x_solution, leaf, (xb + c0 * vb)[None])
                grad = grad + pbar[:m]
                ba_bar = pbar[m:m + n_dofs]
                bv_bar = pbar[m + n_dofs:m + 2 * n_dofs] + c0 * ba_bar + vb
                xbar[n] = xbar.get(n, 0.0) + c1 * bv_bar
                vbar[n] = vbar.get(n, 0.0) + c1 * ba_bar
                if c2:
                    xbar[n - 1] = xbar.get(n - 1, 0.0) + c2 * bv_bar
                    vbar[n - 1] = vbar.get(n - 1, 0.0) + c2 * ba_bar
        return grad
