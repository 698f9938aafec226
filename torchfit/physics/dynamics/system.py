"""The semi-discrete elastodynamics both integrators solve.

``M a = f_int(x; k) - C v + f_ext(t)`` on the free degrees of freedom, with

* ``f_int = -R_el(x; k)``: the internal force of an elastic model (springs, simplicial
  FEM: anything with ``residual``, ``tangent_pattern`` and ``tangent_values`` whose
  residual is linear in its per-element field ``k``);
* ``M``: a lumped (diagonal) mass, ``(n_dofs,)``, from a positive density;
* ``C = alpha M + beta K0(k)``: Rayleigh damping with fittable ``alpha`` (1/s) and
  ``beta`` (s); ``K0(k)`` is the stiffness at the rest shape (linear Rayleigh damping,
  the same matrix for every state; equal to ``dR_el/dx`` for linear models);
* ``f_ext(t) = M g + loads(t)``: gravity and prescribed time-varying loads;
* optionally a reference velocity ``v_ref(t)`` the damping acts against:
  ``C (v - v_ref(t))`` (a rigged body's flesh damped relative to its rig, so that a rigid
  swing of the limb is not braked as if by air; ``v_ref = 0`` by default);
* Dirichlet dofs whose positions follow a prescribed trajectory ``x_D(t)`` (with its
  velocity ``v_D(t)``).

The parameters of a dynamic simulation are one physical vector
``params = [k (n_field,), alpha, beta]`` (:meth:`DynamicSystem.split`).
"""
from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.linalg import eigsh
from torch import Tensor

from ...linalg import csr_matrix
from .errors import DynamicsInputError, InvalidFieldError, NegativeDampingError, NonFiniteStateError

#: times ``(T,)`` -> values ``(T, n)``
TimeFunction = Callable[[Tensor], Tensor]


def smootherstep(s: Tensor) -> tuple[Tensor, Tensor]:
    """Quintic ``w(s) = 6 s^5 - 15 s^4 + 10 s^3`` on ``[0, 1]`` (clamped) and ``dw/ds``;
    ``w`` is C2 at both ends (zero first and second derivatives)."""
    s = s.clamp(0.0, 1.0)
    w = s * s * s * (s * (6.0 * s - 15.0) + 10.0)
    dw = 30.0 * s * s * (1.0 - s) * (1.0 - s)
    return w, dw


class KeyedMotion:
    """Values keyed at times and eased between keys by :func:`smootherstep` (C2).

    Before the first key the value is the first key's, after the last key the last
    key's (the motion stops): velocity zero there. Vectorised over times.

    Args:
        key_times: ``(K,)`` strictly increasing times (s).
        key_values: ``(K, n)`` values at the keys (positions or forces).
    """

    def __init__(self, key_times: Tensor, key_values: Tensor) -> None:
        key_times = torch.as_tensor(key_times)
        if key_times.dim() != 1 or key_values.dim() != 2 or key_values.shape[0] != key_times.numel():
            raise DynamicsInputError(f"keys need times (K,) and values (K, n), got "
                                     f"{tuple(key_times.shape)} and {tuple(key_values.shape)}")
        if key_times.numel() > 1 and not bool((key_times[1:] > key_times[:-1]).all()):
            raise DynamicsInputError(f"key times must increase strictly, got {key_times.tolist()}")
        self.key_times = key_times.to(key_values)
        self.key_values = key_values

    def _segment(self, t: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        times = self.key_times.to(t)
        k = times.numel()
        if k == 1:
            zero = torch.zeros_like(t)
            index = torch.zeros(t.shape, dtype=torch.long, device=t.device)
            return index, index, zero, zero
        upper = torch.searchsorted(times, t.contiguous(), right=True).clamp(1, k - 1)
        lower = upper - 1
        span = times[upper] - times[lower]
        w, dw = smootherstep((t - times[lower]) / span)
        inside = (t > times[lower]) & (t < times[upper])
        return lower, upper, w, torch.where(inside, dw / span, torch.zeros_like(dw))

    def __call__(self, t: Tensor) -> Tensor:
        """Values ``(T, n)`` at times ``t`` ``(T,)``."""
        values = self.key_values.to(t)
        lower, upper, w, _ = self._segment(t)
        return values[lower] + w[:, None] * (values[upper] - values[lower])

    def velocity(self, t: Tensor) -> Tensor:
        """Time derivative ``(T, n)`` at times ``t`` ``(T,)``."""
        values = self.key_values.to(t)
        lower, upper, _, dw = self._segment(t)
        return dw[:, None] * (values[upper] - values[lower])


class SplineMotion:
    """Values keyed at times and interpolated by the natural cubic spline through the keys
    (C2, passes through every key; a rig's frames played at their frame rate). Before the
    first key the value is the first key's, after the last the last key's (velocity zero
    there). Vectorised over times.

    Unlike :class:`KeyedMotion` the motion does not stop at every key: a rig sampled at
    24 frames per second moves smoothly through its frames instead of halting 24 times a
    second (which would shake the flesh at the frame rate).

    Args:
        key_times: ``(K,)`` strictly increasing times (s).
        key_values: ``(K, n)`` values at the keys.
    """

    def __init__(self, key_times: Tensor, key_values: Tensor) -> None:
        key_times = torch.as_tensor(key_times)
        if key_times.dim() != 1 or key_values.dim() != 2 or key_values.shape[0] != key_times.numel():
            raise DynamicsInputError(f"keys need times (K,) and values (K, n), got "
                                     f"{tuple(key_times.shape)} and {tuple(key_values.shape)}")
        if key_times.numel() > 1 and not bool((key_times[1:] > key_times[:-1]).all()):
            raise DynamicsInputError(f"key times must increase strictly, got {key_times.tolist()}")
        self.key_times = key_times.to(key_values)
        self.key_values = key_values
        self.second = self._second_derivatives()                 # (K, n)

    def _second_derivatives(self) -> Tensor:
        t, y = self.key_times, self.key_values
        k = t.numel()
        out = torch.zeros_like(y)
        if k < 3:
            return out
        h = t[1:] - t[:-1]                                      # (K - 1,)
        slope = (y[1:] - y[:-1]) / h[:, None]
        rhs = 6.0 * (slope[1:] - slope[:-1])                    # (K - 2, n)
        a = torch.diag(2.0 * (h[:-1] + h[1:]))
        if k > 3:
            a = a + torch.diag(h[1:-1], 1) + torch.diag(h[1:-1], -1)
        out[1:-1] = torch.linalg.solve(a, rhs)
        return out

    def _segment(self, t: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        times = self.key_times.to(t)
        k = times.numel()
        upper = torch.searchsorted(times, t.contiguous(), right=True).clamp(1, k - 1)
        lower = upper - 1
        h = times[upper] - times[lower]
        b = ((t - times[lower]) / h).clamp(0.0, 1.0)
        inside = (t >= times[0]) & (t <= times[-1])
        return lower, upper, h, b, inside

    def __call__(self, t: Tensor) -> Tensor:
        """Values ``(T, n)`` at times ``t`` ``(T,)``."""
        y = self.key_values.to(t)
        if y.shape[0] == 1:
            return y.expand(t.numel(), -1)
        m = self.second.to(t)
        lower, upper, h, b, _ = self._segment(t)
        a = 1.0 - b
        hh = (h * h / 6.0)[:, None]
        return a[:, None] * y[lower] + b[:, None] * y[upper] + \
            hh * (((a ** 3 - a)[:, None]) * m[lower] + ((b ** 3 - b)[:, None]) * m[upper])

    def velocity(self, t: Tensor) -> Tensor:
        """Time derivative ``(T, n)`` at times ``t`` ``(T,)`` (zero outside the keys' span)."""
        y = self.key_values.to(t)
        if y.shape[0] == 1:
            return torch.zeros(t.numel(), y.shape[1], dtype=t.dtype, device=t.device)
        m = self.second.to(t)
        lower, upper, h, b, inside = self._segment(t)
        a = 1.0 - b
        out = (y[upper] - y[lower]) / h[:, None] + (h / 6.0)[:, None] * (
            -((3.0 * a * a - 1.0)[:, None]) * m[lower] + ((3.0 * b * b - 1.0)[:, None]) * m[upper])
        return torch.where(inside[:, None], out, torch.zeros_like(out))


def check_output_times(times: Tensor | list[float], t0: float = 0.0) -> Tensor:
    """``times`` as a float64 tensor if they are finite, increase strictly and start at or
    after ``t0``; else a one-line :class:`DynamicsInputError`."""
    t = torch.as_tensor(times, dtype=torch.float64).reshape(-1)
    if t.numel() == 0:
        raise DynamicsInputError("no output time given; give at least one time > 0")
    if not bool(torch.isfinite(t).all()):
        raise DynamicsInputError(f"output times must be finite, got {t.tolist()}")
    if float(t[0]) < t0:
        raise DynamicsInputError(f"output time {float(t[0]):g} is before the start t0 = {t0:g}")
    steps = t[1:] - t[:-1]
    if t.numel() > 1 and not bool((steps > 0).all()):
        i = int(torch.nonzero(steps <= 0)[0]) + 1
        raise DynamicsInputError(f"output times must increase strictly: t[{i}] = "
                                 f"{float(t[i]):g} is not after t[{i - 1}] = {float(t[i - 1]):g}")
    return t


class DynamicSystem:
    """Elastodynamics of an elastic model with lumped mass, Rayleigh damping, gravity,
    loads and moving Dirichlet dofs (module docstring).

    Args:
        elastic: the elastic model: ``n_dofs``, ``linear``, ``residual(x (B, n_dofs), k)``
            (``dEnergy/dx``, no external force), ``tangent_pattern``,
            ``tangent_values(x, k)`` (element-major contributions of ``dR/dx``, the same
            number per element), optionally ``param_derivative`` and ``check_modulus``.
        n_field: number of per-element field values ``k`` (springs, triangles).
        mass: ``(n_dofs,)`` lumped mass of every dof (> 0).
        fixed_dofs: ``(n_fixed,)`` sorted Dirichlet dofs.
        dirichlet: ``t (T,) -> (T, n_fixed)`` prescribed positions of the fixed dofs, with
            ``dirichlet.velocity(t)``: a :class:`KeyedMotion` (or anything with both).
        loads: ``t (T,) -> (T, n_dofs)`` prescribed external forces besides gravity, or
            ``None``.
        gravity: ``(n_dofs,)`` gravitational acceleration of every dof (force ``M g``).
        x0, v0: ``(n_dofs,)`` initial positions and velocities (Dirichlet dofs are
            overwritten by the trajectory at ``t0``).
        vertex_dim: dofs per vertex (for messages naming a vertex).
        t0: start time.
        rest: ``(n_dofs,)`` rest positions, where ``K0`` is taken (default ``x0``).
        reference_velocity: ``t (T,) -> (T, n_dofs)`` the velocity the damping acts
            against (``C (v - v_ref)``), or ``None`` (``v_ref = 0``).
        density_scaled: the parameters end with a density scale ``s`` (> 0): the mass is
            ``s M`` (inertia, the mass damping ``alpha s M`` and the weight ``s M g``),
            ``params = [k, alpha, beta, s]``; without it ``s = 1``.
    """

    def __init__(self, elastic, n_field: int, mass: Tensor, fixed_dofs: Tensor, dirichlet,
                 loads: TimeFunction | None, gravity: Tensor, x0: Tensor, v0: Tensor | None = None,
                 vertex_dim: int = 1, t0: float = 0.0, rest: Tensor | None = None,
                 reference_velocity: TimeFunction | None = None,
                 density_scaled: bool = False) -> None:
        self.elastic = elastic
        self.density_scaled = bool(density_scaled)
        self.reference_velocity = reference_velocity
        self.n_dofs = int(elastic.n_dofs)
        self.n_field = int(n_field)
        self.vertex_dim = int(vertex_dim)
        self.t0 = float(t0)
        mass = torch.as_tensor(mass)
        if mass.shape != (self.n_dofs,):
            raise DynamicsInputError(f"mass must have one value per dof ({self.n_dofs},), got "
                                     f"{tuple(mass.shape)}")
        if not bool((torch.isfinite(mass) & (mass > 0)).all()):
            raise DynamicsInputError("the lumped mass must be positive and finite at every "
                                     "dof: the density must be > 0")
        self.mass = mass
        dtype, device = mass.dtype, mass.device
        self.fixed_dofs = torch.sort(torch.as_tensor(fixed_dofs, dtype=torch.long).reshape(-1)).values
        free = torch.ones(self.n_dofs, dtype=torch.bool)
        free[self.fixed_dofs] = False
        self.free_dofs = torch.nonzero(free).reshape(-1)
        self.dirichlet = dirichlet
        self.loads = loads
        self.gravity = torch.as_tensor(gravity, dtype=dtype, device=device).reshape(self.n_dofs)
        self.x0 = torch.as_tensor(x0, dtype=dtype, device=device).reshape(self.n_dofs)
        self.v0 = torch.zeros_like(self.x0) if v0 is None else \
            torch.as_tensor(v0, dtype=dtype, device=device).reshape(self.n_dofs)
        # rest stiffness per unit field: element blocks (n_field, d_el, d_el), element dofs
        pattern = elastic.tangent_pattern
        rows = pattern.row_indices[pattern.scatter]
        cols = pattern.col_indices[pattern.scatter]
        self.element_rows, self.element_cols = rows, cols
        per_element = rows.numel() // self.n_field
        d_el = int(round(math.sqrt(per_element)))
        if d_el * d_el * self.n_field != rows.numel():
            raise ValueError("the elastic model's tangent contributions are not square "
                             "element blocks, one per field value")
        self.element_dofs = rows.reshape(self.n_field, d_el, d_el)[:, :, 0].to(device)
        with torch.no_grad():
            at = self.x0 if rest is None else torch.as_tensor(rest).to(self.x0).reshape(-1)
            unit = elastic.tangent_values(at[None].clone(),
                                          torch.ones(self.n_field, dtype=dtype, device=device))
        self.unit_stiffness = unit.reshape(self.n_field, d_el, d_el).to(dtype).contiguous()
        self._rest_stiffness: tuple[Tensor, Tensor] | None = None   # (field, K0 CSR)
        self._element_csr: tuple[Tensor, Tensor, Tensor] | None = None
        self._check_initial_state()

    # -- parameters ---------------------------------------------------------------------
    @property
    def n_params(self) -> int:
        """Length of the physical parameter vector ``[k, alpha, beta]`` (``[k, alpha, beta,
        s]`` with a density scale)."""
        return self.n_field + 2 + int(self.density_scaled)

    def mass_scale(self, params: Tensor) -> Tensor:
        """The density scale ``s`` of ``params`` (a scalar tensor; 1 without one)."""
        if self.density_scaled:
            return params[self.n_field + 2]
        return params.new_ones(())

    def split(self, params: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(k (n_field,), alpha (), beta ())`` of ``params``."""
        return params[:self.n_field], params[self.n_field], params[self.n_field + 1]

    def check_params(self, params: Tensor) -> None:
        """Raise naming the bad entry: shape, a field value that is not positive and finite
        (:class:`InvalidFieldError` or the model's own error), a damping coefficient that is
        negative or not finite (:class:`NegativeDampingError`)."""
        if params.shape != (self.n_params,):
            raise ValueError(f"dynamics parameters must have shape ({self.n_params},) "
                             f"(field of {self.n_field}, alpha, beta"
                             f"{', density scale' if self.density_scaled else ''}), got "
                             f"{tuple(params.shape)}")
        field, alpha, beta = (p.detach() for p in self.split(params))
        scale = float(self.mass_scale(params.detach()))
        if not (math.isfinite(scale) and scale > 0):
            raise InvalidFieldError(f"the density scale = {scale:g} must be positive and "
                                    "finite (the mass is the scale times the density's)")
        for name, value, unit in (("alpha", alpha, "1/s"), ("beta", beta, "s")):
            if not (math.isfinite(float(value)) and float(value) >= 0):
                raise NegativeDampingError(
                    f"Rayleigh damping coefficient {name} = {float(value):g} {unit} is negative "
                    f"or not finite (C = alpha M + beta K must not feed energy in); with "
                    f"problem.transform=identity keep {name} >= 0, or use problem.transform=exp")
        check = getattr(self.elastic, "check_modulus", None)
        if check is not None:
            check(field)
            return
        bad = ~(torch.isfinite(field) & (field > 0))
        if bool(bad.any()):
            e = int(torch.nonzero(bad)[0])
            raise InvalidFieldError(f"stiffness must be positive and finite: element {e} has "
                                    f"{float(field[e]):g}; with problem.transform=identity keep it "
                                    "> 0, or use problem.transform=exp")

    # -- forces ---------------------------------------------------------------------------
    def stiffness_matvec(self, field: Tensor, u: Tensor) -> Tensor:
        """``K0(k) u`` ``(..., n_dofs)`` for ``u`` ``(..., n_dofs)`` (differentiable in both)."""
        dofs = self.element_dofs.to(u.device)
        local = u[..., dofs]                                          # (..., n_field, d_el)
        forces = torch.einsum("eab,...eb->...ea", self.unit_stiffness.to(u), local)
        forces = forces * field.to(u)[:, None]
        out = u.new_zeros(*u.shape[:-1], self.n_dofs)
        return out.index_add(-1, dofs.reshape(-1), forces.reshape(*u.shape[:-1], -1))

    def stiffness_matmul(self, field: Tensor, U: Tensor) -> Tensor:
        """``K0(k) U`` ``(n_dofs, k)`` for ``U`` ``(n_dofs, k)`` (no graph): one sparse product
        with :meth:`rest_stiffness_matrix`."""
        return torch.sparse.mm(self.rest_stiffness_matrix(field.detach().to(U)), U.contiguous())

    def rest_stiffness_matrix(self, field: Tensor) -> Tensor:
        """``K0(k)`` as a sparse CSR matrix ``(n_dofs, n_dofs)`` on the elastic tangent's
        pattern (no graph). The last one is kept: every step of a trajectory, and every
        column block of its tangents, has the same field."""
        field = field.detach()
        kept = self._rest_stiffness
        if kept is not None and kept[0].shape == field.shape and kept[0].dtype == field.dtype \
                and kept[0].device == field.device and torch.equal(kept[0], field):
            return kept[1]
        pattern = self.elastic.tangent_pattern
        values = pattern.assemble(self.rest_stiffness_contributions(field))
        matrix = csr_matrix(pattern.crow_indices.to(field.device),
                            pattern.col_indices.to(field.device), values, pattern.shape)
        self._rest_stiffness = (field.clone(), matrix)
        return matrix

    def element_matrix(self, forces: Tensor) -> Tensor:
        """Element vectors ``(n_field, d_el)`` as the sparse CSR matrix ``(n_dofs, n_field)``
        whose column ``e`` is element ``e``'s vector summed into its dofs: ``B @ V`` is
        :meth:`scatter_elements` of ``forces[:, :, None] * V[:, None, :]`` without the
        ``(n_field, d_el, k)`` intermediate."""
        if self._element_csr is None or self._element_csr[0].device != forces.device:
            dofs = self.element_dofs.reshape(-1).to(forces.device)
            order = torch.argsort(dofs, stable=True)
            cells = torch.arange(self.n_field, device=forces.device).repeat_interleave(
                self.element_dofs.shape[1])[order]
            counts = torch.bincount(dofs, minlength=self.n_dofs)
            crow = torch.cat([counts.new_zeros(1), torch.cumsum(counts, 0)])
            self._element_csr = (order, crow, cells.contiguous())
        order, crow, cells = self._element_csr
        return csr_matrix(crow, cells, forces.reshape(-1)[order], (self.n_dofs, self.n_field))

    def unit_element_forces(self, u: Tensor) -> Tensor:
        """``K0_e u`` per element at unit field, ``(..., n_field, d_el)`` (``dK0 u / dk``)."""
        local = u[..., self.element_dofs.to(u.device)]
        return torch.einsum("eab,...eb->...ea", self.unit_stiffness.to(u), local)

    def scatter_elements(self, forces: Tensor) -> Tensor:
        """Element vectors ``(n_field, d_el)`` or ``(n_field, d_el, k)`` summed into dofs,
        ``(n_dofs,)`` or ``(n_dofs, k)``.

        An ``index_add`` along the last (contiguous) dimension: the same along the first
        one, or a sparse product, runs into torch's intra-op thread pool and was 100 times
        slower with two threads on a loaded machine.
        """
        flat = forces.reshape(forces.shape[0] * forces.shape[1], -1).T.contiguous()
        dofs = self.element_dofs.reshape(-1).to(flat.device)
        out = flat.new_zeros(flat.shape[0], self.n_dofs).index_add_(1, dofs, flat)
        return out.T.reshape(self.n_dofs, *forces.shape[2:])

    def rest_stiffness_contributions(self, field: Tensor) -> Tensor:
        """Contributions of ``K0(k)`` on the elastic tangent pattern, ``(n_contrib,)``."""
        return (self.unit_stiffness.to(field) * field[:, None, None]).reshape(-1)

    def external_force(self, t: Tensor, scale: Tensor | float = 1.0) -> Tensor:
        """``s M g + loads(t)``, ``(T, n_dofs)`` at times ``t`` ``(T,)`` (``s``: the
        density scale)."""
        force = (scale * (self.mass * self.gravity).to(t))[None, :].expand(t.numel(), -1)
        return force + self.loads_at(t)

    def loads_at(self, t: Tensor) -> Tensor:
        """``loads(t)`` ``(T, n_dofs)`` (zeros without loads): the external force besides
        the weight."""
        if self.loads is None:
            return t.new_zeros(t.numel(), self.n_dofs)
        return self.loads(t).to(t)

    def fixed_positions(self, t: Tensor) -> Tensor:
        """Dirichlet positions ``(T, n_fixed)`` at times ``t``."""
        return self.dirichlet(t).to(t)

    def fixed_velocities(self, t: Tensor) -> Tensor:
        """Dirichlet velocities ``(T, n_fixed)`` at times ``t``."""
        return self.dirichlet.velocity(t).to(t)

    def acceleration(self, t: Tensor, x: Tensor, v: Tensor, params: Tensor) -> Tensor:
        """``M^-1 (f_int - C v + f_ext)`` ``(B, n_dofs)`` for full states ``x, v`` ``(B, n_dofs)``
        at one time ``t`` (a scalar tensor); differentiable in ``x``, ``v``, ``params``."""
        field, alpha, beta = self.split(params)
        mass = self.mass_scale(params) * self.mass.to(x)
        v = v - self.damped_against(t.reshape(1)).to(v)
        force = -self.elastic.residual(x, field) - alpha * mass * v \
            - beta * self.stiffness_matvec(field, v) + \
            self.external_force(t.reshape(1), self.mass_scale(params))
        return force / mass

    def damped_against(self, t: Tensor) -> Tensor:
        """``v_ref(t)`` ``(T, n_dofs)`` (zeros without a reference velocity)."""
        if self.reference_velocity is None:
            return self.mass.new_zeros(t.numel(), self.n_dofs).to(t)
        return self.reference_velocity(t).to(t)

    # -- scales and checks ------------------------------------------------------------------
    def max_frequency(self, field: Tensor, iterations: int = 60) -> float:
        """Largest angular frequency (rad/s) of ``M^-1 K0(k)`` on the free dofs, by power
        iteration (the stiffest mode that an explicit step must resolve)."""
        with torch.no_grad():
            free = self.free_dofs.to(field.device)
            inv_sqrt_m = self.mass.to(field).rsqrt()
            generator = torch.Generator().manual_seed(0)
            u = torch.randn(self.n_dofs, generator=generator, dtype=torch.float64).to(field)
            mask = torch.zeros_like(u)
            mask[free] = 1.0
            u = u * mask
            value = 0.0
            for _ in range(iterations):
                u = u / torch.linalg.vector_norm(u)
                w = inv_sqrt_m * self.stiffness_matvec(field.detach(), inv_sqrt_m * u) * mask
                value = float(torch.dot(u, w))
                u = w
            return math.sqrt(max(value, 0.0))

    def lowest_frequency(self, field: Tensor) -> float | None:
        """The lowest angular frequency ``w1`` (rad/s) of ``K0(k) u = w^2 M u`` on the free
        dofs (the Dirichlet dofs held: the body's slowest free oscillation about its rest
        shape, at the mass of ``problem.density``, a density scale of 1): shift-invert
        Lanczos at 0 (one sparse LU of ``K0_ff``, a few solves with it). ``None`` where
        ``K0_ff`` is singular (nothing holds the body: a rigid mode at ``w = 0``) or there
        is no free dof. Costs about one factorisation of the stiffness; no graph."""
        free = self.free_dofs.cpu().numpy()
        if free.size == 0:
            return None
        with torch.no_grad():
            field = field.detach().to(torch.float64).cpu()
            pattern = self.elastic.tangent_pattern
            values = pattern.assemble(self.rest_stiffness_contributions(field))
            stiffness = pattern.to_scipy(values).tocsc()[free][:, free]
            stiffness = (0.5 * (stiffness + stiffness.T)).tocsc()
            mass = self.mass.detach().to(torch.float64).cpu().numpy()[free]
        if free.size <= 3:     # eigsh needs more rows than modes: the dense problem
            dense = stiffness.toarray() / np.sqrt(np.outer(mass, mass))
            lowest = float(np.linalg.eigvalsh(dense)[0])
        else:
            try:
                lowest = float(eigsh(stiffness, k=1, M=sp.diags(mass).tocsc(), sigma=0.0,
                                     which="LM", return_eigenvectors=False)[0])
            except (RuntimeError, ValueError):   # a singular K0_ff: a rigid mode
                return None
        if not math.isfinite(lowest) or lowest <= 0:
            return None
        return math.sqrt(lowest)

    def start_at(self, x0: Tensor) -> None:
        """Start from positions ``x0`` ``(n_dofs,)`` (a state computed after the system, as
        a static equilibrium under gravity); integrators built on it read it at their next
        integration (clear their caches)."""
        self.x0 = torch.as_tensor(x0, dtype=self.x0.dtype, device=self.x0.device).reshape(
            self.n_dofs).clone()
        self._check_initial_state()

    def _check_initial_state(self) -> None:
        for name, state in (("position", self.x0), ("velocity", self.v0)):
            bad = ~torch.isfinite(state)
            if bool(bad.any()):
                dof = int(torch.nonzero(bad)[0])
                raise NonFiniteStateError(
                    f"the state is not finite at t = {self.t0:g}: initial {name} of vertex "
                    f"{dof // self.vertex_dim} (dof {dof}) is {float(state[dof])}")

    def check_state(self, x: Tensor, t: float, what: str = "position") -> None:
        """Raise :class:`NonFiniteStateError` naming time and vertex if ``x`` ``(n_dofs,)``
        is not finite."""
        bad = ~torch.isfinite(x.detach())
        if bool(bad.any()):
            dof = int(torch.nonzero(bad.reshape(-1))[0]) % self.n_dofs
            raise NonFiniteStateError(
                f"the state is not finite at t = {t:.6g}: {what} of vertex "
                f"{dof // self.vertex_dim} (dof {dof}) is {float(x.reshape(-1)[dof])}; check the "
                "loads, the prescribed motion and the parameters")

    def full(self, free_values: Tensor, fixed_values: Tensor) -> Tensor:
        """Full vectors ``(B, n_dofs)`` from free ``(B, n_free)`` and fixed ``(B, n_fixed)``."""
        out = free_values.new_zeros(free_values.shape[0], self.n_dofs)
        out = out.index_copy(1, self.free_dofs.to(out.device), free_values)
        return out.index_copy(1, self.fixed_dofs.to(out.device), fixed_values.to(out))


class TrajectoryFunction(torch.autograd.Function):
    """Positions at the output times as one autograd node, for either integrator.

    The integrator provides ``run(params)`` (its cached solve, with ``outputs``
    ``(K, n_dofs)`` and ``params``), ``adjoint(run, grad_outputs)`` (reverse mode) and
    ``tangents(run, V)`` (forward mode, ``V`` ``(n_params, k)``).
    """

    @staticmethod
    def forward(params: Tensor, integrator: Any) -> Tensor:  # type: ignore[override]
        return integrator.run(params).outputs.clone()

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple, output: Tensor) -> None:
        params, integrator = inputs
        ctx.integrator = integrator
        ctx.run = integrator.run(params)          # cache hit
        ctx.set_materialize_grads(False)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad_outputs: Tensor | None) -> tuple:  # type: ignore[override]
        if grad_outputs is None:
            return None, None
        return ctx.integrator.adjoint(ctx.run, grad_outputs.detach()), None

    @staticmethod
    def jvp(ctx: Any, d_params: Tensor | None, *_: Any) -> Tensor:  # type: ignore[override]
        run = ctx.run
        if d_params is None:
            return torch.zeros_like(run.outputs)
        return ctx.integrator.tangents(run, d_params.detach().to(run.params)[:, None])[..., 0]

