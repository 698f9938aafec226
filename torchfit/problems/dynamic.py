"""What the dynamic variants of the problems share (``problem.dynamic=true``).

A dynamic problem fits the per-element field together with the Rayleigh damping
coefficients ``alpha`` (1/s) and ``beta`` (s) to positions at output times. Its
parameterisation is a :class:`~torchfit.params.FieldAndScalars` (``theta = [field...,
alpha, beta]``), its simulation input the physical vector ``[k..., alpha, beta]``, its
:meth:`~DynamicMixin.field` the stiffness field alone (what ``k_err_*`` measure, what the
pictures show). Inertia fixes the stiffness scale: never scale-free.

The settings every dynamic problem has (checked by :func:`check_dynamic_settings`):

``integrator``      ``implicit`` (backward Euler / BDF2 through the equilibrium core) or
                    ``torchdiffeq`` (``odeint_adjoint``)
``scheme``          implicit: ``bdf2`` | ``backward_euler``
``ode_method``      torchdiffeq: ``dopri5`` (adaptive, ``ode_rtol``, ``ode_atol``) or a
                    fixed-step ``rk4`` | ``midpoint`` | ``euler`` (step ``dt``)
``dt``              implicit step, fixed explicit step (s)
``duration``, ``frames``  output times ``duration * (1..frames) / frames`` unless
                    ``output_times`` lists them (strictly increasing, > 0)
``density``         mass per unit length (springs) or area (sheet), > 0
``alpha``, ``beta`` true damping; ``alpha0``, ``beta0`` the initial guess
``checkpoint_every`` implicit: 1 keeps every step's state and factor; ``c > 1`` keeps
                    every ``c``-th state and recomputes; 0 is ``ceil(sqrt(steps))``
"""
from __future__ import annotations

import contextlib
from typing import Any, ContextManager

import numpy as np
import torch
from torch import Tensor

from ..params import FieldAndScalars, Parameterization
from ..physics.dynamics import (ADAPTIVE_METHODS, FIXED_METHODS, DynamicSystem,
                                check_output_times, make_integrator)
from ..physics.dynamics.errors import DynamicsInputError
from ..physics.equilibrium import NewtonOptions
from .base import Choice, ProblemConfigError, Transform, require_setting, setting_error


class Integrator(Choice):
    """Time integrator of a dynamic problem."""

    implicit = "implicit"
    torchdiffeq = "torchdiffeq"


class Scheme(Choice):
    """Implicit scheme."""

    bdf2 = "bdf2"
    backward_euler = "backward_euler"


class OdeMethod(Choice):
    """torchdiffeq method (adaptive or fixed-step)."""

    dopri5 = "dopri5"
    dopri8 = "dopri8"
    bosh3 = "bosh3"
    adaptive_heun = "adaptive_heun"
    rk4 = "rk4"
    midpoint = "midpoint"
    euler = "euler"


DAMPING = ("alpha", "beta")


def check_dynamic_settings(cfg: Any) -> None:
    """The dynamic settings of ``cfg`` (one-line :class:`ProblemConfigError` each)."""
    require_setting(cfg.density > 0, cfg, "density", "must be > 0 (mass per unit length or "
                    "area; the lumped mass of every node must be positive)")
    require_setting(cfg.dt > 0, cfg, "dt", "must be > 0 (s)")
    require_setting(cfg.duration > 0, cfg, "duration", "must be > 0 (s)")
    require_setting(isinstance(cfg.frames, int) and cfg.frames >= 1, cfg, "frames",
                    "must be an integer >= 1 (output times)")
    require_setting(cfg.ode_rtol > 0, cfg, "ode_rtol", "must be > 0")
    require_setting(cfg.ode_atol > 0, cfg, "ode_atol", "must be > 0")
    require_setting(isinstance(cfg.checkpoint_every, int) and cfg.checkpoint_every >= 0, cfg,
                    "checkpoint_every", "must be an integer >= 0 (0: ceil(sqrt(steps)))")
    for name in DAMPING:
        for key in (name, f"{name}0"):
            value = getattr(cfg, key)
            if cfg.transform == Transform.exp:
                require_setting(value > 0, cfg, key, f"must be > 0 with problem.transform=exp "
                                f"({name} = exp(theta)); use problem.transform=identity for 0")
            else:
                require_setting(value >= 0, cfg, key, f"is a negative damping coefficient: "
                                f"Rayleigh damping C = alpha M + beta K needs {name} >= 0")
    if cfg.output_times is not None:
        try:
            times = check_output_times(cfg.output_times, 0.0)
        except DynamicsInputError as error:
            raise setting_error("output_times", cfg.output_times, str(error)) from None
        require_setting(float(times[0]) > 0, cfg, "output_times", "must be > 0 (the state at "
                        "t = 0 is the initial state, not data)")


def output_times(cfg: Any) -> Tensor:
    """The output times of ``cfg`` ``(K,)`` (float64)."""
    if cfg.output_times is not None:
        return torch.as_tensor(cfg.output_times, dtype=torch.float64)
    return torch.arange(1, cfg.frames + 1, dtype=torch.float64) * (cfg.duration / cfg.frames)


class DynamicMixin:
    """Hooks shared by the dynamic problems (put before the problem class in the bases).

    The problem sets ``self.system`` (a :class:`DynamicSystem`) in ``build_model`` and calls
    :meth:`build_integrator`; :meth:`build_parameterization` wraps its field
    parameterisation with the damping scalars.
    """

    scale_free = False
    cfg: Any
    system: DynamicSystem

    def independent_simulation(self) -> ContextManager[None]:
        """Nothing to isolate: every simulation integrates from the initial state (each
        step's Newton starts from the step before, within that simulation)."""
        return contextlib.nullcontext()

    # -- building ---------------------------------------------------------------------------
    def build_integrator(self, cfg: Any, backend: str, newton: NewtonOptions | None = None) -> None:
        self.output_times = output_times(cfg)
        self.n_frames = int(self.output_times.numel())
        self.integrator = make_integrator(
            cfg.integrator.value, self.system, self.output_times, dt=cfg.dt,
            method=cfg.ode_method.value, scheme=cfg.scheme.value, rtol=cfg.ode_rtol,
            atol=cfg.ode_atol, backend=backend, newton=newton,
            checkpoint_every=cfg.checkpoint_every)

    def damped(self, field: Parameterization, cfg: Any) -> FieldAndScalars:
        return FieldAndScalars(field, DAMPING, (cfg.alpha0, cfg.beta0), cfg.transform.value)

    def true_damping(self) -> Tensor:
        return torch.tensor([self.cfg.alpha, self.cfg.beta], dtype=self.dtype, device=self.device)

    # -- the contract -------------------------------------------------------------------------
    def field(self, theta: Tensor) -> Tensor:
        return self.parameterization.split(self.parameterization(theta.detach()))[0]

    def damping(self, theta: Tensor) -> Tensor:
        """``(alpha, beta)`` at ``theta``."""
        return self.parameterization.split(self.parameterization(theta.detach()))[1]

    def true_simulation_input(self) -> Tensor:
        return torch.cat([self.field_true, self.true_damping()])

    def positions(self, physical: Tensor) -> Tensor:
        """Positions ``(K, n_nodes, dim)`` at the output times for ``[k..., alpha, beta]``."""
        if physical.shape != (self.system.n_params,):
            raise ProblemConfigError(
                f"the dynamic simulation takes [field ({self.system.n_field}), alpha, beta], shape "
                f"({self.system.n_params},), got {tuple(physical.shape)}")
        x = self.integrator(physical)
        return x.reshape(x.shape[0], -1, self.dim)

    def simulate_jacobian(self, physical: Tensor, directions: Tensor) -> Tensor:
        """``(d positions / d [k, alpha, beta]) V``: ``(K, n_nodes, dim, k)``."""
        dx = self.integrator.jacobian(physical, directions)
        return dx.reshape(dx.shape[0], -1, self.dim, dx.shape[-1])

    def simulation_accuracy(self) -> float | None:
        if self.cfg.integrator == Integrator.torchdiffeq and \
                self.cfg.ode_method.value in ADAPTIVE_METHODS:
            return float(self.cfg.ode_rtol)
        if not self.system.elastic.linear:
            return float(getattr(self.cfg, "newton_rtol", 1e-10))
        return None

    def metric_names(self) -> list[str]:
        names = super().metric_names()  # type: ignore[misc]
        return names + ["alpha_damping", "beta_damping", "alpha_damping_err_rel",
                        "beta_damping_err_rel"]

    def metrics(self, theta: Tensor, x: Tensor | None = None) -> dict[str, float]:
        out = super().metrics(theta, x)  # type: ignore[misc]
        damping = self.damping(theta)
        truth = self.true_damping()
        for i, name in enumerate(DAMPING):
            out[f"{name}_damping"] = float(damping[i])
            out[f"{name}_damping_err_rel"] = float(abs(damping[i] - truth[i]) / abs(truth[i])) \
                if float(truth[i]) != 0 else float(abs(damping[i]))
        return out

    # -- frames are output times ----------------------------------------------------------------
    def frame_errors(self, x: Tensor) -> dict[str, np.ndarray]:
        """Position errors per output time against the noise-free truth."""
        du = (x.detach() - self.x_true).reshape(x.shape[0], -1)
        return {"u_err_inf": du.abs().amax(dim=1).cpu().numpy(),
                "u_err_2": torch.linalg.vector_norm(du, dim=1).cpu().numpy()}

    def frame_names(self) -> list[str]:
        return [f"t = {float(t):.3g} s" for t in self.output_times]

    def describe(self) -> dict[str, Any]:
        out = super().describe()  # type: ignore[misc]
        integrator = self.integrator
        out.update({"dynamic": True, "integrator": integrator.name,
                    "output_times": int(self.n_frames),
                    "stored_states": int(integrator.stored_states)})
        if integrator.name == "implicit":
            out.update({"scheme": integrator.scheme, "steps": int(integrator.n_steps),
                        "checkpoint_every": int(integrator.checkpoint_every)})
        else:
            out.update({"method": integrator.method})
        return out


__all__ = ["DAMPING", "DynamicMixin", "FIXED_METHODS", "Integrator", "OdeMethod", "Scheme",
           "check_dynamic_settings", "output_times"]
