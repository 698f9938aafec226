"""The dynamic variants of the problems (``problem.dynamic=true``): their settings and hooks.

A dynamic problem fits the per-element field together with the Rayleigh damping
coefficients ``alpha`` (1/s) and ``beta`` (s) to positions at output times. Its
parameterisation is a :class:`~torchfit.params.FieldAndScalars` (``theta = [field...,
alpha, beta]``), its simulation input the physical vector ``[k..., alpha, beta]``, its
:meth:`~DynamicMixin.field` the stiffness field alone (what ``k_err_*`` measure, what the
pictures show). Inertia fixes the stiffness scale: never scale-free.

:class:`DynamicSettings` holds the settings every dynamic problem has (mixed into the
problem's config, so the keys are ``problem.dt``, ``problem.scheme``, ...);
:func:`check_dynamic_settings` checks them. ``build_problem`` builds the problem's dynamic
class when ``problem.dynamic=true`` (:func:`check_dynamic_flag`: each class refuses the
other value).
"""
from __future__ import annotations

import contextlib
import dataclasses
import math
from typing import Any, ContextManager, List, Optional

import numpy as np
import torch
from torch import Tensor

from ..params import FieldAndScalars, Parameterization
from ..physics import NewtonOptions
from ..physics.dynamics import (ADAPTIVE_METHODS, DynamicsInputError, DynamicSystem,
                                check_output_times, make_integrator)
from ..settings import Choice
from .config import ProblemConfigError, Transform, require_setting, setting_error


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


_DAMPING = ("alpha", "beta")


@dataclasses.dataclass
class DynamicSettings:
    """Settings of ``problem.dynamic=true``, mixed into a problem's config (put before
    :class:`~torchfit.problems.config.ProblemConfig` in the bases). The defaults are the
    hanging chain's (spring1d); a problem redeclares the ones it changes."""

    dynamic: bool = False               # simulate motion (build_problem: the dynamic class)
    # implicit (backward Euler / BDF2 through the equilibrium core) | torchdiffeq (odeint_adjoint)
    integrator: Integrator = Integrator.implicit
    scheme: Scheme = Scheme.bdf2        # implicit: bdf2 | backward_euler
    # torchdiffeq: dopri5 (adaptive: ode_rtol, ode_atol) | fixed-step rk4 | midpoint | euler (dt)
    ode_method: OdeMethod = OdeMethod.dopri5
    dt: float = 0.01                    # s: implicit step, fixed explicit step
    ode_rtol: float = 1e-8              # torchdiffeq, adaptive methods
    ode_atol: float = 1e-10
    # torchdiffeq, adaptive methods: a solver's trial point may take at most this many times
    # the right-hand sides of the point derivatives were last taken at, else it is a failed
    # trial (a stiffer trial, or a large beta, otherwise integrates for minutes); 0: no limit
    ode_trial_factor: float = 4.0
    duration: float = 6.0               # s
    frames: int = 60                    # output times duration * (1..frames) / frames
    output_times: Optional[List[float]] = None   # or these (s, strictly increasing, > 0)
    density: float = 1.0                # mass per unit length (chain) or area (sheet), > 0
    alpha: float = 1.0                  # true mass damping (1/s): C = alpha M + beta K
    beta: float = 0.001                 # true stiffness damping (s)
    alpha0: float = 0.5                 # initial guess of alpha
    beta0: float = 0.002                # initial guess of beta
    # implicit: 1 keeps every step's state and factor; c > 1 every c-th state (the others
    # recomputed); 0: ceil(sqrt(steps))
    checkpoint_every: int = 1


def check_dynamic_flag(problem: Any, cfg: Any) -> None:
    """``problem.dynamic`` matches the class: the static problem refuses ``true``, its
    dynamic class ``false`` (:func:`torchfit.problems.build_problem` picks the class)."""
    dynamic = isinstance(problem, DynamicMixin)
    require_setting(bool(cfg.dynamic) == dynamic, cfg, "dynamic",
                    f"{type(problem).__name__} is the {'dynamic' if dynamic else 'static'} "
                    "problem; build_problem picks the class that matches problem.dynamic")


#: bytes of one implicit step of the step grid (its time, coefficients and index: Python objects)
IMPLICIT_STEP_BYTES = 256


def stored_states(steps: float, every: float) -> float:
    """States ``(x, v)`` the implicit integrator keeps for the gradient over ``steps`` steps
    with checkpoint interval ``every``: all of them with ``every = 1``, else two per segment
    and one segment recomputed."""
    return steps + 1 if every == 1 else \
        min(steps + 1, 2 * math.ceil(steps / every)) + min(every, steps)


def time_steps_allocation(cfg: Any, n_dofs: int) -> list[tuple[str, float, str, str]]:
    """What the time grid allocates, one entry per cause: the step grid (``steps``: each
    step's time, coefficients and index, Python objects of about 256 bytes, implicit; a float
    tensor, fixed-step torchdiffeq), named by the end time and ``problem.dt``, and the states
    kept for the gradient (implicit: every state with ``c = 1``, else ``2 ceil(steps / c)``
    checkpoints and a segment of ``min(c, steps)`` states ``(x, v)`` of ``n_dofs`` each, ``c`` = ``checkpoint_every`` or
    ``sqrt(steps)``; explicit: 2), named by ``problem.checkpoint_every`` where it is set.
    Adaptive methods choose their steps: nothing known ahead."""
    implicit = cfg.integrator == Integrator.implicit
    if not implicit and str(cfg.ode_method) in ADAPTIVE_METHODS:
        return []
    end = max(cfg.output_times) if cfg.output_times else cfg.duration
    steps = end / cfg.dt + cfg.frames           # inf for a subnormal dt: refused as well
    steps = math.ceil(steps) if math.isfinite(steps) else steps
    horizon = "problem.output_times" if cfg.output_times else \
        f"problem.duration={cfg.duration} at problem.frames={cfg.frames}"
    grid = f"problem.dt={cfg.dt} to {horizon}"
    advice = "choose a larger problem.dt or an earlier end time"
    out = [(grid, steps * (IMPLICIT_STEP_BYTES if implicit else 16) if math.isfinite(steps)
            else math.inf,
            f"{steps:.3g} time steps to t = {end:g} s", advice)]
    if not math.isfinite(steps):
        return out
    every = cfg.checkpoint_every or math.sqrt(steps)
    kept = stored_states(steps, every) if implicit else 2
    out.append((f"problem.checkpoint_every={cfg.checkpoint_every}" if implicit and
                cfg.checkpoint_every else grid, kept * n_dofs * 16,
                f"{kept:.3g} stored states of {n_dofs} degrees of freedom", advice))
    return out


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
    require_setting(math.isfinite(cfg.ode_trial_factor) and cfg.ode_trial_factor >= 0, cfg,
                    "ode_trial_factor", "must be a number >= 0 (0: no limit on a trial's "
                    "right-hand sides)")
    require_setting(isinstance(cfg.checkpoint_every, int) and cfg.checkpoint_every >= 0, cfg,
                    "checkpoint_every", "must be an integer >= 0 (0: ceil(sqrt(steps)))")
    for name in _DAMPING:
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

    def simulation_state(self) -> dict[str, Any]:
        """Nothing carries over between simulations (each integrates from the initial
        state), so a checkpoint needs no simulation state."""
        return {}

    def restore_simulation_state(self, state: dict[str, Any]) -> None:
        """Nothing to restore (:meth:`simulation_state`)."""

    # -- building ---------------------------------------------------------------------------
    def build_integrator(self, cfg: Any, backend: str, newton: NewtonOptions | None = None) -> None:
        self.output_times = output_times(cfg)
        self.n_frames = int(self.output_times.numel())
        self.integrator = make_integrator(
            cfg.integrator.value, self.system, self.output_times, dt=cfg.dt,
            method=cfg.ode_method.value, scheme=cfg.scheme.value, rtol=cfg.ode_rtol,
            atol=cfg.ode_atol, backend=backend, newton=newton,
            checkpoint_every=cfg.checkpoint_every, trial_factor=cfg.ode_trial_factor)

    def damped(self, field: Parameterization, cfg: Any) -> FieldAndScalars:
        return FieldAndScalars(field, _DAMPING, (cfg.alpha0, cfg.beta0), cfg.transform.value)

    def true_damping(self) -> Tensor:
        return torch.tensor([self.cfg.alpha, self.cfg.beta], dtype=self.dtype, device=self.device)

    def truth_settings(self) -> list[str]:
        return [*super().truth_settings(), "problem.alpha", "problem.beta"]  # type: ignore[misc]

    def start_settings(self) -> list[str]:
        return [*super().start_settings(), "problem.alpha0", "problem.beta0"]  # type: ignore[misc]

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

    def product_consistency(self) -> float | None:
        """torchdiffeq with an adaptive method: ``ode_rtol`` (``J^T w`` is the continuous
        adjoint, ``J v`` the forward sensitivities, each accurate to the tolerance: they
        agree to a multiple of it, ``docs/notes/verification.md``). The implicit
        integrator's discrete adjoint is the exact transpose of its tangents: ``None``. A
        fixed-step method (``rk4`` ...) has no tolerance to name: ``None`` (its adjoint
        differs by the method's truncation error; give ``dot_tol``)."""
        if self.cfg.integrator == Integrator.torchdiffeq and \
                self.cfg.ode_method.value in ADAPTIVE_METHODS:
            return float(self.cfg.ode_rtol)
        return None

    def simulation_accuracy(self) -> float | None:
        if self.cfg.integrator == Integrator.torchdiffeq and \
                self.cfg.ode_method.value in ADAPTIVE_METHODS:
            return float(self.cfg.ode_rtol)
        if not self.system.elastic.linear:
            return float(getattr(self.cfg, "newton_rtol", 1e-10))
        return None

    def time_integration(self, theta: Tensor) -> dict[str, Any]:
        """How the motion at ``theta`` is integrated and how accurately: ``integrator``,
        ``scheme`` (implicit) or ``method`` (torchdiffeq), ``steps`` and ``dt`` (s) of the
        implicit step; its error at the outputs estimated by step halving
        (:meth:`~torchfit.physics.dynamics.implicit.ImplicitIntegrator.error_estimate`:
        ``error_estimate`` in the positions' units, ``error_estimate_rel`` of the largest
        displacement from the start, ``reference_steps``); torchdiffeq's adaptive methods
        report their tolerances (``rtol``, ``atol``: the error they control) instead.
        Costs one integration with twice the steps (implicit)."""
        integrator = self.integrator
        physical = self.simulation_input(theta.detach())  # type: ignore[attr-defined]
        out: dict[str, Any] = {"integrator": integrator.name}
        if integrator.name != "implicit":
            out.update({"method": integrator.method, "rtol": float(self.cfg.ode_rtol),
                        "atol": float(self.cfg.ode_atol)})
            return out
        estimate = integrator.error_estimate(physical)
        with torch.no_grad():
            x = integrator(physical.detach())
        start = self.system.x0.to(x)
        moved = (x - start[None]).reshape(x.shape[0], -1, self.system.vertex_dim)
        largest = float(torch.linalg.vector_norm(moved, dim=-1).max())
        out.update({"scheme": integrator.scheme, "steps": estimate["steps"],
                    "dt": float(integrator.dt),
                    "error_estimate": estimate["estimate"],
                    "error_estimate_rel": estimate["estimate"] / largest if largest > 0 else 0.0,
                    "largest_displacement": largest,
                    "reference_steps": estimate["reference_steps"]})
        return out

    def metric_names(self) -> list[str]:
        names = super().metric_names()  # type: ignore[misc]
        return names + ["alpha_damping", "beta_damping", "alpha_damping_err_rel",
                        "beta_damping_err_rel"]

    def metrics(self, theta: Tensor, x: Tensor | None = None) -> dict[str, float]:
        out = super().metrics(theta, x)  # type: ignore[misc]
        damping = self.damping(theta)
        truth = self.true_damping()
        for i, name in enumerate(_DAMPING):
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

