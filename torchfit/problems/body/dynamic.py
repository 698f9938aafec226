"""The rigged body in time (``problem.dynamic=true`` for ``animation`` and ``arm3d``).

The rig drives its tetrahedron vertices through the shot: the driven positions of every
frame of the shot at times ``f / fps`` (the animation's frame
rate: the folder's ``fps``, a USD stage's time codes per second, a glTF's sampling or key
rate; 24 by default), a natural cubic spline in time between frames
(:class:`~torchfit.physics.dynamics.SplineMotion`). The other vertices integrate

    ``M a = f_int(x; E) - (alpha M + beta K0(E)) (v - v_rig(t)) + M g``

with the implicit integrator (BDF2 by default; ``problem.substeps`` steps per frame, so
``dt = 1 / (fps substeps)``), lumped mass from ``problem.density`` (kg/m^3: a quarter of each
tetrahedron's mass on each of its vertices), Rayleigh damping ``alpha`` (1/s), ``beta`` (s)
(:mod:`torchfit.physics.dynamics`), damping the velocity relative to the rig's (``v_rig``:
the skinned pose of every tetrahedron vertex, the same spline in time; a limb swung rigidly
is not braked as by air, and slow motion is the quasistatic body). The same constitutive models (their residual is linear
in ``E``), parameterisations (grid, region, tet), bounds and outputs as the quasistatic body.

``g`` is ``problem.gravity`` (m/s^2 in the animation's axes; none by default: the animated
shapes already show the body as it hangs).

Start: at ``t = 0`` (frame 0) the body moves with the rig (``v = v_rig(0)``) in the quasistatic
equilibrium of frame 0 for the homogeneous starting material ``E0`` (the rest shape when
frame 0 is the rest pose, as the arm's), under gravity where it is given (the static
equilibrium ``f_int(x; E0) + M g = 0`` with the driven vertices at frame 0); that state is
data, not differentiated.

Moduli are pascals (inertia fixes the scale: not scale-free): with ``problem.E0_unit=relative``
(the default) ``E0``, ``E_blocks``, ``E_regions`` (and absolute bounds) are factors of
``problem.E_reference``, with ``E0_unit=Pa`` pascals. Parameters: the body's field
parameterisation and the two damping coefficients (:class:`~torchfit.params.FieldAndScalars`,
``theta = [field..., alpha, beta]``), the damping within its physical bounds
(:class:`~torchfit.problems.damping.DampingBand` at ``E0`` and ``pi x fps``: a start outside
them refused, the solver kept inside them where ``problem.bounds`` holds). Data: the observed surface at the fitted frames.
``problem.init_field`` starts the field from a material layer in pascals (its stated unit,
:mod:`.init_field`). Validation: ``problem.validation_frames`` must be a later window than every fitted frame (the
held-out future; :func:`dynamic_split`); ``validation_every`` is refused.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import numpy as np
import torch
from torch import Tensor

from ...memory import check_allocation
from ...params import Parameterization
from ...physics import NewtonConvergenceError, NewtonOptions
from ...physics.dynamics import DynamicSystem, SplineMotion, UnstableStepError, make_integrator
from ..base import NO_WARM_STARTS
from ..config import ProblemConfigError, Transform, require_setting, setting_error
from ..damping import DampingBand
from ..dynamic import IMPLICIT_STEP_BYTES, Integrator, Scalars, TimeIntegration, stored_states
from ..protocols import WarmStarts
from .config import ModulusUnit, RiggedBodyConfig, Target
from .held_out import FrameSplit

_DAMPING = ("alpha", "beta")


#: the densities a body may have (kg/m^3): from a foam's to beyond the densest metal's
DENSITY_RANGE = (1.0, 1.0e5)

def in_pascals(cfg: RiggedBodyConfig) -> RiggedBodyConfig:
    """``cfg`` with its moduli in pascals (``E0_unit=Pa``): with ``E0_unit=relative`` every
    modulus setting times ``E_reference``; with ``Pa`` as it is."""
    require_setting(math.isfinite(cfg.E_reference) and cfg.E_reference > 0, cfg,
                    "E_reference", "must be a positive Young's modulus in pascals (soft "
                    "tissue: 1e4)")
    if cfg.E0_unit == ModulusUnit.Pa:
        return cfg
    s = float(cfg.E_reference)
    changes: dict[str, Any] = {
        "E0": cfg.E0 * s, "E_blocks": [v * s for v in cfg.E_blocks],
        "E_regions": [v * s for v in cfg.E_regions], "E0_unit": ModulusUnit.Pa}
    if not cfg.E_bounds_relative:
        changes.update(E_min=cfg.E_min * s, E_max=cfg.E_max * s)
    return dataclasses.replace(cfg, **changes)


def check_body_dynamics(cfg: RiggedBodyConfig) -> None:
    """The dynamic settings of a body (one-line :class:`ProblemConfigError` each)."""
    require_setting(cfg.integrator == Integrator.implicit, cfg, "integrator",
                    "torchdiffeq does not apply to a body: its stiffest tetrahedron's period "
                    "is far below a frame, an explicit step must resolve it; use "
                    "problem.integrator=implicit")
    require_setting(isinstance(cfg.substeps, int) and not isinstance(cfg.substeps, bool)
                    and cfg.substeps >= 1, cfg, "substeps", "must be an integer >= 1 "
                    "(implicit steps per frame: dt = 1 / (fps substeps))")
    require_setting(math.isfinite(cfg.density) and cfg.density > 0, cfg, "density",
                    "must be > 0 (kg/m^3; soft tissue 1000): every vertex needs a positive "
                    "lumped mass")
    # a density no solid has (1e12 was accepted, and a poor fit called determined): below
    # aerogel's, above osmium's (22,590) by a margin
    low, high = DENSITY_RANGE
    require_setting(low <= cfg.density <= high, cfg, "density", f"is not a density a body "
                    f"has: give kg/m^3 within [{low:g}, {high:g}] (soft tissue about 1000, "
                    "bone about 1900)")
    require_setting(isinstance(cfg.fit_density, bool), cfg, "fit_density", "must be true or "
                    "false (a density scale among the parameters)")
    require_setting(isinstance(cfg.density_scale, (int, float))
                    and not isinstance(cfg.density_scale, bool)
                    and math.isfinite(cfg.density_scale) and cfg.density_scale > 0, cfg,
                    "density_scale", "must be > 0 (the synthetic truth's density is "
                    "problem.density times it)")
    gravity = cfg.gravity
    require_setting(gravity is None or (len(gravity) == 3 and all(
        isinstance(g, (int, float)) and not isinstance(g, bool) and math.isfinite(g)
        for g in gravity)), cfg, "gravity", "must be null or three finite numbers: the "
        "acceleration in m/s^2 in the animation's axes ([0, 0, -9.81] Z-up, [0, -9.81, 0] Y-up)")
    require_setting(isinstance(cfg.checkpoint_every, int) and cfg.checkpoint_every >= 0, cfg,
                    "checkpoint_every", "must be an integer >= 0 (0: ceil(sqrt(steps)))")
    for name in _DAMPING:
        for key in (name, f"{name}0"):
            value = getattr(cfg, key)
            if cfg.transform == Transform.exp:
                require_setting(math.isfinite(value) and value > 0, cfg, key,
                                f"must be > 0 with problem.transform=exp ({name} = "
                                "exp(theta)); use problem.transform=identity for 0")
            else:
                require_setting(math.isfinite(value) and value >= 0, cfg, key,
                                f"is a negative damping coefficient: Rayleigh damping "
                                f"C = alpha M + beta K needs {name} >= 0")
    require_setting(not cfg.validation_every, cfg, "validation_every",
                    "holds out every k-th pose, which a motion in time cannot skip; hold out "
                    "a later window with problem.validation_frames=[...] (frames after every "
                    "fitted frame)")


def dynamic_split(cfg: RiggedBodyConfig, n_frames: int) -> FrameSplit | None:
    """Fitted and held-out frames of the dynamic body: ``validation_frames`` a window later
    than every fitted frame; with ``problem.frames=null`` the fit takes every frame before
    it. ``None`` without validation."""
    named = cfg.validation_frames
    if named is None:
        return None
    validation = [int(f) for f in named]
    bad = [f for f in validation if not 0 <= f < n_frames]
    if not validation or bad:
        raise setting_error("validation_frames", named, f"frame {bad[0]} is not a frame of the "
                            f"animation (0..{n_frames - 1})" if bad else "lists no frame "
                            "(null: no validation)")
    if len(set(validation)) != len(validation):
        raise setting_error("validation_frames", named, "lists a frame twice; list each frame "
                            "once")
    first = min(validation)
    fitted = list(range(first)) if cfg.frames is None else [int(f) for f in cfg.frames]
    late = [f for f in fitted if f >= first]
    if late:
        raise setting_error("validation_frames", named, f"is not a later window: fitted frame "
                            f"{late[0]} is not before validation frame {first} (problem.dynamic"
                            "=true holds out the future); fit earlier frames only")
    if not fitted:
        raise setting_error("validation_frames", named, "leaves no frame to fit before it "
                            "(the fit takes the frames before the held-out window)")
    return FrameSplit(fitted, sorted(validation), [], len(fitted) + len(validation))


class BodyInTime(TimeIntegration):
    """The rigged body's simulation in time (module docstring): the
    :class:`~torchfit.problems.protocols.BodySimulation` and the
    :class:`~torchfit.problems.protocols.TimeModel` of ``problem.dynamic=true``.

    Built by :meth:`build` from the body's pieces; its simulation input is ``[E (n_tets,),
    alpha, beta(, density scale)]`` (pascals, 1/s, s, a factor of ``problem.density``);
    :meth:`simulate` gives the fitted frames' positions ``(F, n, 3)`` at their times ``f /
    fps``, :meth:`jacobian` the observed rows' tangents forward through time. Nothing
    carries over between simulations (each integrates from the start):
    :attr:`warm_starts` is :data:`~torchfit.problems.base.NO_WARM_STARTS`.
    """

    warm_starts: WarmStarts = NO_WARM_STARTS

    def __init__(self, cfg: RiggedBodyConfig, system: DynamicSystem, integrator: Any,
                 output_times: Tensor, fps: float, dt: float, shot_frames: int,
                 band: DampingBand | None = None) -> None:
        super().__init__(cfg, system, integrator, output_times, 3, Scalars(
            scalar_names(cfg), scalar_starts(cfg), (cfg.alpha, cfg.beta, *(
                (cfg.density_scale,) if cfg.fit_density else ())), cfg.transform.value),
            band, cfg.target == Target.synthetic)
        self.fps, self.dt, self.shot_frames = fps, dt, int(shot_frames)

    @classmethod
    def build(cls, cfg: RiggedBodyConfig, model: Any, mesh: Any, dirichlet_vertices: Any,
              drive: Tensor, skinned: Tensor, frame_numbers: list[int], fps: float,
              backend: str, initial_pose: Callable[[], Tensor]) -> "BodyInTime":
        """The body in time from the body's model (elasticity on its tetrahedra), mesh,
        driven vertices and their positions in every frame of the shot ``drive`` ``(S,
        n_driven, 3)``, the skinned pose of every tetrahedron vertex ``skinned`` ``(S, n,
        3)``, the fitted frames' numbers, the frame rate and the linear-solve backend;
        ``initial_pose()``: the positions at ``t = 0`` (the rest shape, or frame 0's
        equilibrium for ``E0``). Refuses (naming the setting) a frame rate, step or step
        grid the integrator cannot take and a start under gravity with no equilibrium."""
        fps = float(fps)
        require_setting(math.isfinite(fps) and fps > 0, cfg, "path", f"the animation's frame "
                        f"rate is {fps:g}; give it a positive fps (the folder's 'fps')")
        dt = 1.0 / (fps * cfg.substeps)
        require_setting(math.isfinite(dt) and dt > 0, cfg, "substeps", f"gives the time step "
                        f"{dt!r} s at {fps:g} fps, which the integrator cannot take; use fewer "
                        "substeps")
        check_time_steps(cfg, frame_numbers, 3 * model.n_vertices)
        dtype, device = drive.dtype, drive.device
        n = model.n_vertices
        cells = torch.as_tensor(mesh.cells, device=device)
        volumes = torch.as_tensor(np.abs(mesh.signed_volumes()), dtype=dtype, device=device)
        vertex_mass = torch.zeros(n, dtype=dtype, device=device).index_add(
            0, cells.reshape(-1), (cfg.density * volumes / 4.0).repeat_interleave(4))
        vertices = np.asarray(dirichlet_vertices, dtype=np.int64)
        order = np.argsort(vertices, kind="stable")
        keys = drive[:, torch.as_tensor(order, device=device)]               # (S, nd, 3)
        fixed = torch.as_tensor((vertices[order][:, None] * 3 + np.arange(3)).reshape(-1))
        key_times = torch.arange(keys.shape[0], dtype=dtype, device=device) / fps
        rest = model.rest.points.to(dtype)
        # the rig's motion of every tetrahedron vertex (the skinned pose): the damping acts
        # on the velocity relative to it, and the body starts moving with it
        rig = SplineMotion(key_times, skinned.reshape(keys.shape[0], -1))
        gravity = torch.zeros(3, dtype=dtype, device=device) if cfg.gravity is None else \
            torch.tensor([float(g) for g in cfg.gravity], dtype=dtype, device=device)
        system = DynamicSystem(
            model, model.n_cells, vertex_mass.repeat_interleave(3), fixed,
            SplineMotion(key_times, keys.reshape(keys.shape[0], -1)), None,
            gravity.repeat(n), initial_pose().reshape(-1),
            rig.velocity(key_times[:1])[0], vertex_dim=3, rest=rest.reshape(-1),
            reference_velocity=rig.velocity, density_scaled=cfg.fit_density)
        # the damping's bounds: zeta <= ZETA_MAX at the lowest mode at E0 and at pi fps; a
        # start outside them refused before anything is integrated
        band = DampingBand.of(system, float(cfg.E0), 1.0 / fps)
        band.check_start(cfg, float(cfg.alpha0), float(cfg.beta0),
                         frames="the animation")
        output_times = torch.as_tensor(frame_numbers, dtype=torch.float64) / fps
        newton = NewtonOptions(max_iter=cfg.newton_max_iter, rtol=cfg.newton_rtol,
                               atol=cfg.newton_atol)
        integrator = make_integrator(
            "implicit", system, output_times, dt=dt, scheme=cfg.scheme.value,
            backend=backend, newton=newton, checkpoint_every=cfg.checkpoint_every)
        if cfg.gravity is not None and bool(gravity.any()):
            # at rest under gravity at t = 0 for E0: the body does not drop at the start
            start = torch.cat([torch.full((model.n_cells,), float(cfg.E0), dtype=dtype,
                                          device=device),
                               torch.tensor(scalar_starts(cfg), dtype=dtype, device=device)])
            try:
                rest_under_gravity = integrator.static_equilibrium(start, system.x0)
            except NewtonConvergenceError as error:
                # Seen on a capsule held by 4 tetrahedron vertices near its axis with gravity
                # across it: the centre of mass above the held line, the body would swing
                # round it; no equilibrium near the rest shape for Newton to find.
                raise ProblemConfigError(
                    f"problem.gravity={list(cfg.gravity)}: the body has no equilibrium at rest "
                    f"under gravity at the first frame for the start E0 = {cfg.E0:g} Pa (Newton "
                    f"from the rest shape, the load in up to "
                    f"{integrator.static_increments} increments: "
                    f"{' '.join(str(error).split(': ', 1)[-1].split(';')[0].split())}); the rig "
                    f"holds it by {len(dirichlet_vertices)} tetrahedron vertices, so it "
                    "may sag or swing far from its rest shape: raise problem.E0, drive more of "
                    "the body (a larger attach radius, torchfit:attachRadius) or set "
                    "problem.gravity=null") from error
            system.start_at(rest_under_gravity)
        return cls(cfg, system, integrator, output_times, fps, dt, drive.shape[0], band)

    # -- the body's simulation -----------------------------------------------------------
    def simulate(self, physical: Tensor) -> Tensor:
        """Tetrahedron vertex positions ``(F, n, 3)`` at the fitted frames' times for
        ``[E (n_tets,), alpha, beta]``. A step whose Newton does not converge raises
        :class:`UnstableStepError` naming the setting to raise (a failed trial inside a fit;
        at its start a refusal)."""
        try:
            return self.positions(physical)
        except UnstableStepError as error:
            raise UnstableStepError(f"{error}; at {self.fps:g} fps x {self.cfg.substeps} "
                                    "substeps: raise problem.substeps", error.time,
                                    error.step) from error

    def jacobian(self, theta: Tensor, parameterization: Parameterization,
                 observe: Callable[[Tensor], Tensor]) -> Tensor:
        """``d observe(simulate(map(theta))) / d theta`` ``(m, n_params)``: tangents forward
        through time (one solve with ``n_params`` right-hand sides per step), the observed
        rows (``observe(like)``: sparse ``(n_obs 3, n 3)``) of every output frame."""
        with torch.no_grad():
            theta = theta.detach()
            physical = parameterization(theta)
            directions = parameterization.jacobian(theta)              # (n_tets + 2, n)
            dx = self.integrator.jacobian(physical, directions)       # (F, 3 n, n)
            rows = observe(physical)
            return torch.cat([torch.sparse.mm(rows, dx[f]) for f in range(dx.shape[0])])

    def material_density(self, physical: Tensor) -> tuple[float, str] | None:
        """``problem.density`` (kg/m^3), times the fitted density scale where it is fitted."""
        if not self.cfg.fit_density:
            return float(self.cfg.density), "problem.density (the body in time's mass)"
        scale = float(self.scalars(physical)[2])
        return float(self.cfg.density) * scale, (f"fitted: problem.density x the fitted density "
                                                 f"scale {scale:.6g}")

    # -- what it adds to the body's reports ------------------------------------------------
    def report(self, physical: Tensor, metrics: dict[str, Any] | None = None
               ) -> dict[str, Any]:
        """The dynamic problems' report (positions in metres) with the frame rate and the
        substeps."""
        out = super().report(physical, metrics)
        out.update({"fps": self.fps, "substeps": int(self.cfg.substeps)})
        return out

    def describe(self) -> dict[str, Any]:
        out = super().describe()
        out.update({"fps": self.fps, "substeps": int(self.cfg.substeps), "dt": self.dt,
                    "density": float(self.cfg.density), "fit_density": bool(self.cfg.fit_density),
                    "shot_frames": self.shot_frames,
                    "mass": float(self.system.mass.sum()) / 3.0})
        return out


def scalar_names(cfg: RiggedBodyConfig) -> tuple[str, ...]:
    """The scalars beside the field: the damping, and the density scale where fitted."""
    return (*_DAMPING, *(("density_scale",) if cfg.fit_density else ()))


def scalar_starts(cfg: RiggedBodyConfig) -> tuple[float, ...]:
    """Their starts: ``alpha0``, ``beta0`` (and the density scale 1: ``problem.density``)."""
    return (cfg.alpha0, cfg.beta0, *((1.0,) if cfg.fit_density else ()))


def check_time_steps(cfg: RiggedBodyConfig, frame_numbers: list[int], n_dofs: int) -> None:
    """Refuse, naming ``problem.substeps``, a step grid whose size exceeds the memory
    limit: ``substeps`` steps per frame up to the last fitted frame, each a Python object
    of about 256 bytes, and the states ``(x, v)`` the gradient keeps (every one with
    ``checkpoint_every = 1``, else two per segment and one segment); a lower bound, since
    each kept step's factorisation comes on top."""
    last = max(frame_numbers)
    steps = last * cfg.substeps
    kept = stored_states(steps, cfg.checkpoint_every or max(1.0, math.sqrt(steps)))
    check_allocation(f"problem.substeps={cfg.substeps}",
                     steps * float(IMPLICIT_STEP_BYTES) + kept * n_dofs * 16.0,
                     f"{steps:.3g} implicit steps to frame {last} and {kept:.3g} stored "
                     f"states of {n_dofs} degrees of freedom", ProblemConfigError,
                     "choose fewer problem.substeps (for the stored states, a larger "
                     "problem.checkpoint_every also helps)")
