"""Problems in motion (``problem.dynamic=true``): their settings and their time model.

A problem in motion fits the per-element field together with the Rayleigh damping
coefficients ``alpha`` (1/s) and ``beta`` (s) to positions at output times. It is another
problem (its own class, built by ``build_problem`` when ``problem.dynamic=true``) whose
:attr:`~torchfit.problems.base.InverseProblem.time` is a :class:`TimeIntegration`: the
parameterisation a :class:`~torchfit.params.FieldAndScalars` (``theta = [field..., alpha,
beta]``), the simulation input the physical vector ``[k..., alpha, beta]``, the problem's
``field`` the stiffness field alone (what ``k_err_*`` measure, what the pictures show), the
damping's truth, metrics and description added to the problem's. Inertia fixes the
stiffness scale: never scale-free. Problems whose frames are independent have
:data:`QUASISTATIC`.

The damping's physical bounds (:class:`DampingBand`): the damping ratio ``zeta(w) = alpha /
(2 w) + beta w / 2`` at most :data:`ZETA_MAX` at the lowest mode ``w1`` (at the start's
material) and at ``pi x`` the frame rate; a start outside them is refused, the fitted
damping reported against them (:meth:`TimeIntegration.damping_report`).

:class:`DynamicSettings` holds the settings every dynamic problem has (mixed into the
problem's config, so the keys are ``problem.dt``, ``problem.scheme``, ...);
:func:`check_dynamic_settings` checks them (:func:`check_dynamic_flag`: each class refuses
the other value of ``problem.dynamic``).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, List, Optional

import numpy as np
import torch
from torch import Tensor

from ..params import FieldAndScalars, Parameterization
from ..physics import NewtonOptions
from ..physics.dynamics import (ADAPTIVE_METHODS, DynamicsInputError, DynamicSystem,
                                check_output_times, make_integrator)
from ..settings import Choice
from .config import ProblemConfigError, Transform, require_setting, setting_error
from .damping import ZETA_MAX, DampingBand


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


def check_dynamic_flag(problem: Any, cfg: Any, dynamic: bool) -> None:
    """``problem.dynamic`` matches the class (``dynamic``: the class is the problem in
    motion): the static problem refuses ``true``, its dynamic class ``false``
    (:func:`torchfit.problems.build_problem` picks the class)."""
    require_setting(bool(cfg.dynamic) == dynamic, cfg, "dynamic",
                    f"{type(problem).__name__} is the {'dynamic' if dynamic else 'static'} "
                    "problem; build_problem picks the class that matches problem.dynamic")


#: a fitted coefficient within this fraction of its bound is on it
ON_BOUND_RTOL = 1e-3

#: the integration error above which, as a fraction of the fitted error, a fit warns: the
#: misfit then holds as much of the step's error as of the material's
INTEGRATION_ERROR_FRACTION = 0.5


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


class Quasistatic:
    """The :class:`~.protocols.TimeModel` of independent frames (load cases, poses): the
    simulation input is the field itself, nothing is added to the problem's settings,
    metrics or description, and a simulation is as accurate as the problem says."""

    in_time = False

    def parameterization(self, field: Parameterization) -> Parameterization:
        return field

    def field(self, physical: Tensor) -> Tensor:
        return physical

    def scalars(self, physical: Tensor) -> Tensor:
        return physical[:0]

    def true_input(self, field_true: Tensor) -> Tensor:
        return field_true

    def truth_settings(self) -> list[str]:
        return []

    def start_settings(self) -> list[str]:
        return []

    def metric_names(self) -> list[str]:
        return []

    def metrics(self, physical: Tensor) -> dict[str, float]:
        return {}

    def describe(self) -> dict[str, Any]:
        return {}

    def accuracy(self, static: float | None) -> float | None:
        return static

    def product_consistency(self) -> float | None:
        return None


#: the time model of every problem whose frames are independent (the default)
QUASISTATIC = Quasistatic()


@dataclasses.dataclass(frozen=True)
class Scalars:
    """The scalars a problem in motion fits beside its field: their names (``alpha``,
    ``beta``, the body's ``density_scale``), starts, true values and transform (``exp`` or
    ``identity``, as the field's)."""

    names: tuple[str, ...]
    starts: tuple[float, ...]
    truths: tuple[float, ...]
    transform: str

    @classmethod
    def damping(cls, cfg: Any) -> "Scalars":
        """Rayleigh damping: ``alpha``, ``beta`` from ``alpha0``, ``beta0`` (truth
        ``alpha``, ``beta``)."""
        return cls(_DAMPING, (cfg.alpha0, cfg.beta0), (cfg.alpha, cfg.beta),
                   cfg.transform.value)


class TimeIntegration:
    """The :class:`~.protocols.TimeModel` of a problem in motion: its frames are output
    times of one integration of a :class:`~torchfit.physics.dynamics.DynamicSystem`.

    The simulation input is ``[field..., scalars...]`` (:class:`Scalars`: the Rayleigh
    damping, for the body also a density scale) through a
    :class:`~torchfit.params.FieldAndScalars`; :meth:`positions` integrates it to the output
    times ``(K, n_nodes, dim)`` and :meth:`jacobian` gives its tangents. Inertia fixes the
    stiffness scale: a problem in motion is never scale-free. Nothing carries over from one
    simulation to the next (each integrates from the initial state): its problem keeps the
    default :data:`~torchfit.problems.base.NO_WARM_STARTS`.

    Args:
        cfg: the problem's settings (``integrator``, ``ode_method``, ``ode_rtol``,
            ``ode_atol``; ``newton_rtol`` where the model is nonlinear).
        system: the dynamic system integrated.
        integrator: its integrator (:func:`~torchfit.physics.dynamics.make_integrator`).
        output_times: ``(K,)`` seconds.
        dim: components per node of the state.
        scalars: the scalars beside the field.
        band: the frequencies the damping is judged at (:class:`DampingBand`), or ``None``.
        has_truth: the target is simulated from a known truth (the ``*_err_rel`` metrics
            exist only then).
    """

    in_time = True

    def __init__(self, cfg: Any, system: DynamicSystem, integrator: Any, output_times: Tensor,
                 dim: int, scalars: Scalars, band: DampingBand | None = None,
                 has_truth: bool = True) -> None:
        self.cfg, self.system, self.integrator = cfg, system, integrator
        self.output_times, self.dim, self.scalar_spec = output_times, int(dim), scalars
        self.band, self.has_truth = band, bool(has_truth)

    @classmethod
    def from_settings(cls, cfg: Any, system: DynamicSystem, dim: int, backend: str,
                      newton: NewtonOptions | None = None,
                      start_field: float | None = None) -> "TimeIntegration":
        """The integration :class:`DynamicSettings` describe (``problem.integrator``,
        ``scheme``, ``ode_method``, ``dt``, tolerances, output times), damping fitted.
        With ``start_field`` (the start's homogeneous field) the damping's
        :class:`DampingBand` at it, the frames the output times (``pi / dt`` of their
        shortest interval): a start ``alpha0``, ``beta0`` outside its bounds is refused."""
        times = output_times(cfg)
        band = None
        if start_field is not None:
            interval = float(torch.diff(torch.cat([times.new_zeros(1), times])).min())
            band = DampingBand.of(system, start_field, interval)
            band.check_start(cfg, float(cfg.alpha0), float(cfg.beta0),
                             frames=f"the output times (their shortest interval {interval:.4g} s)")
        integrator = make_integrator(
            cfg.integrator.value, system, times, dt=cfg.dt, method=cfg.ode_method.value,
            scheme=cfg.scheme.value, rtol=cfg.ode_rtol, atol=cfg.ode_atol, backend=backend,
            newton=newton, checkpoint_every=cfg.checkpoint_every,
            trial_factor=cfg.ode_trial_factor)
        return cls(cfg, system, integrator, times, dim, Scalars.damping(cfg), band,
                   getattr(cfg, "targets", None) is None)

    # -- the time model ------------------------------------------------------------------
    def parameterization(self, field: Parameterization) -> FieldAndScalars:
        spec = self.scalar_spec
        return FieldAndScalars(field, spec.names, spec.starts, spec.transform)

    def field(self, physical: Tensor) -> Tensor:
        return physical[:self.system.n_field]

    def scalars(self, physical: Tensor) -> Tensor:
        """The scalars ``(alpha, beta[, density scale])`` of a simulation input."""
        return physical[self.system.n_field:]

    def true_input(self, field_true: Tensor) -> Tensor:
        truths = torch.tensor(self.scalar_spec.truths, dtype=field_true.dtype,
                              device=field_true.device)
        return torch.cat([field_true, truths])

    def truth_settings(self) -> list[str]:
        return [f"problem.{name}" for name in self.scalar_spec.names]

    def start_settings(self) -> list[str]:
        return [f"problem.{name}0" for name in _DAMPING]

    def metric_names(self) -> list[str]:
        names = ["alpha_damping", "beta_damping"]
        if self.band is not None:
            names += ["damping_ratio_w_high"] + \
                (["damping_ratio_w1"] if self.band.w1 is not None else [])
        if self.has_truth:
            names += ["alpha_damping_err_rel", "beta_damping_err_rel"]
        if "density_scale" in self.scalar_spec.names:
            names += ["density_scale"] + (["density_scale_err_rel"] if self.has_truth else [])
        return names

    def metrics(self, physical: Tensor) -> dict[str, float]:
        """The fitted damping (``alpha_damping`` 1/s, ``beta_damping`` s), the damping ratios
        it gives (``damping_ratio_w1``, ``damping_ratio_w_high``: :class:`DampingBand`) and,
        where a truth exists (a synthetic target), its relative error to it (the absolute
        value where the truth is 0); a fitted density scale and its relative error."""
        fitted, truths = self.scalars(physical.detach()), self.scalar_spec.truths
        out: dict[str, float] = {}
        for i, name in enumerate(_DAMPING):
            truth = torch.tensor(truths[i], dtype=fitted.dtype, device=fitted.device)
            out[f"{name}_damping"] = float(fitted[i])
            if self.has_truth:
                out[f"{name}_damping_err_rel"] = float(abs(fitted[i] - truth) / abs(truth)) \
                    if float(truth) != 0 else float(abs(fitted[i]))
        if self.band is not None:
            ratios = self.band.ratios(float(fitted[0]), float(fitted[1]))
            out["damping_ratio_w_high"] = ratios["zeta_w_high"]
            if "zeta_w1" in ratios:
                out["damping_ratio_w1"] = ratios["zeta_w1"]
        if "density_scale" in self.scalar_spec.names:
            scale = float(fitted[self.scalar_spec.names.index("density_scale")])
            out["density_scale"] = scale
            if self.has_truth:
                out["density_scale_err_rel"] = abs(
                    scale / float(truths[self.scalar_spec.names.index("density_scale")]) - 1)
        return out

    def damping_report(self, physical: Tensor) -> dict[str, Any] | None:
        """The fitted damping against its band (``None`` without a band): ``alpha`` (1/s),
        ``beta`` (s), the band (:meth:`DampingBand.describe`), the ratios ``zeta_w1``,
        ``zeta_w_high``, ``on_bound`` (the coefficients within :data:`ON_BOUND_RTOL` of
        their bound) and ``explains_motion``: a coefficient on its bound or ``zeta_w1``
        above 1 (the lowest mode overdamped), where the damping rather than the material
        explains the motion; ``note``: the summary line then."""
        if self.band is None:
            return None
        fitted = self.scalars(physical.detach())
        alpha, beta = float(fitted[0]), float(fitted[1])
        band = self.band
        on_bound = [name for name, value, bound in (("alpha", alpha, band.alpha_max),
                                                    ("beta", beta, band.beta_max))
                    if math.isfinite(bound) and value >= bound * (1 - ON_BOUND_RTOL)]
        ratios = band.ratios(alpha, beta)
        overdamped = ratios.get("zeta_w1", 0.0) > 1.0
        out: dict[str, Any] = {"alpha": alpha, "beta": beta, **band.describe(), **ratios,
                               "on_bound": on_bound,
                               "explains_motion": bool(on_bound) or overdamped}
        if out["explains_motion"]:
            why = " and ".join(
                ([f"{', '.join(on_bound)} on {'its' if len(on_bound) == 1 else 'their'} "
                  f"bound{'s' if len(on_bound) > 1 else ''} (alpha <= {band.alpha_max:.3g} 1/s, "
                  f"beta <= {band.beta_max:.3g} s: zeta <= {ZETA_MAX:g} at w1 and the frame "
                  "rate)"] if on_bound else []) +
                ([f"zeta = {ratios['zeta_w1']:.3g} at the lowest mode (overdamped)"]
                 if overdamped else []))
            out["note"] = (f"the damping rather than the material explains the motion: the "
                           f"fitted damping alpha = {alpha:.3g} 1/s, beta = {beta:.3g} s has "
                           f"{why}; the frames show no oscillation the damping must match, so "
                           "the material is better fitted quasistatically (problem.dynamic="
                           "false)")
        return out

    def describe(self) -> dict[str, Any]:
        integrator = self.integrator
        out: dict[str, Any] = {"dynamic": True, "integrator": integrator.name,
                               "output_times": int(self.output_times.numel()),
                               "stored_states": int(integrator.stored_states)}
        if self.band is not None:
            out["damping_band"] = self.band.describe()
        if integrator.name == "implicit":
            out.update({"scheme": integrator.scheme, "steps": int(integrator.n_steps),
                        "checkpoint_every": int(integrator.checkpoint_every)})
        else:
            out.update({"method": integrator.method})
        return out

    def accuracy(self, static: float | None) -> float | None:
        """torchdiffeq's adaptive methods: ``ode_rtol``; a nonlinear model: Newton's
        ``newton_rtol`` per step; else machine precision (``None``)."""
        if self.cfg.integrator == Integrator.torchdiffeq and \
                self.cfg.ode_method.value in ADAPTIVE_METHODS:
            return float(self.cfg.ode_rtol)
        if not self.system.elastic.linear:
            return float(getattr(self.cfg, "newton_rtol", 1e-10))
        return None

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

    # -- the motion ----------------------------------------------------------------------
    def positions(self, physical: Tensor) -> Tensor:
        """Positions ``(K, n_nodes, dim)`` at the output times for ``[field..., scalars...]``."""
        if physical.shape != (self.system.n_params,):
            raise ProblemConfigError(
                f"the dynamic simulation takes [field ({self.system.n_field}), "
                f"{', '.join(self.scalar_spec.names)}], shape ({self.system.n_params},), got "
                f"{tuple(physical.shape)}")
        x = self.integrator(physical)
        return x.reshape(x.shape[0], -1, self.dim)

    def jacobian(self, physical: Tensor, directions: Tensor) -> Tensor:
        """``(d positions / d physical) directions``: ``(K, n_nodes, dim, k)``."""
        dx = self.integrator.jacobian(physical, directions)
        return dx.reshape(dx.shape[0], -1, self.dim, dx.shape[-1])

    def frame_errors(self, x: Tensor, x_true: Tensor) -> dict[str, np.ndarray]:
        """Position errors per output time against the noise-free truth ``x_true``."""
        du = (x.detach() - x_true).reshape(x.shape[0], -1)
        return {"u_err_inf": du.abs().amax(dim=1).cpu().numpy(),
                "u_err_2": torch.linalg.vector_norm(du, dim=1).cpu().numpy()}

    def frame_names(self) -> list[str]:
        return [f"t = {float(t):.3g} s" for t in self.output_times]

    def report(self, physical: Tensor, metrics: dict[str, Any] | None = None
               ) -> dict[str, Any]:
        """How the motion at ``physical`` is integrated and how accurately: ``integrator``,
        ``scheme`` (implicit) or ``method`` (torchdiffeq), ``steps`` and ``dt`` (s) of the
        implicit step; its error at the outputs estimated by step halving
        (:meth:`~torchfit.physics.dynamics.implicit.ImplicitIntegrator.error_estimate`:
        ``error_estimate`` in the positions' units, ``error_estimate_rel`` of the largest
        displacement from the start, ``reference_steps``); torchdiffeq's adaptive methods
        report their tolerances (``rtol``, ``atol``: the error they control) instead.
        Costs one integration with twice the steps (implicit). ``result.json``'s
        ``time_integration``. Also the fitted damping against its band (``damping``:
        :meth:`damping_report`) and ``warnings``: summary lines where the damping explains
        the motion, or where the integration error is not small against the fitted error
        (``metrics``' ``surface_err_mean``: above :data:`INTEGRATION_ERROR_FRACTION` of it)."""
        integrator = self.integrator
        physical = physical.detach()
        out: dict[str, Any] = {"integrator": integrator.name}
        warnings: list[str] = []
        damping = self.damping_report(physical)
        if damping is not None:
            out["damping"] = damping
            if damping["explains_motion"]:
                warnings.append(damping["note"])
        if warnings:
            out["warnings"] = warnings
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
        fitted = None if metrics is None else metrics.get("surface_err_mean")
        if fitted is not None and math.isfinite(float(fitted)) and \
                estimate["estimate"] > INTEGRATION_ERROR_FRACTION * float(fitted):
            warnings.append(
                f"the integration error (about {1e3 * estimate['estimate']:.3g} mm, estimated "
                f"against {estimate['reference_steps']} steps) is not small against the fitted "
                f"error ({1e3 * float(fitted):.3g} mm mean): the fitted material partly fits the "
                "time step's error; raise problem.substeps")
            out["warnings"] = warnings
        return out
