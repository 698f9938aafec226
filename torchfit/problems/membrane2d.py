"""``membrane2d``: the elastic sheet spelling IPAM (docs/problems.md, the seed's PhysBAM 2-D test).

Rest rectangle ``[0, width] x [0, height]`` (``2 x 0.5``), structured triangulation of
``nx x ny`` cells (``96 x 24``) each split into two triangles, plane strain. One Young's
modulus per triangle, Poisson ratio ``nu`` fixed; constitutive model ``corotated`` by
default (``linear``, ``stable_neo_hookean`` / ``neo_hookean`` too). Truth: ``E = 1``,
``E = 10`` on the triangles whose centroid lies on the ink of the word IPAM in the 5x7
font of docs/problems.md (:func:`torchfit.mesh.ipam_mask`, box ``[0.10, 0.90) x [0.35, 0.65)``
of the sheet normalised to the unit square).

Animation, 8 frames, each an independent quasistatic equilibrium: the left edge is held
at rest, the right edge (rest ``x = width``) is prescribed:

====  =========================================================================
0, 1  stretch: ``x = width (1 + s)``, ``s = 10 %, 20 %``
2, 3  shear at 20 % stretch: ``x = 1.2 width``, ``y = Y + 0.1, + 0.2``
4, 5  bend: the right edge rotated about its rest centre ``(width, height / 2)``
      by ``10, 20`` degrees (counter-clockwise), no stretch
6, 7  compress: ``x = width (1 + s)``, ``s = -5 %, -10 %``
====  =========================================================================

Every load is a prescribed displacement, so ``x(a E) = x(E)``: scale-free (metrics
report ``k_err_rel_aligned``; solvers get the gauge direction). Data ``dense``: both
coordinates of every free vertex (neither edge) in every frame.

``problem.dynamic=true`` (:class:`DynamicMembrane2D`): the sheet starts at rest; the left
edge stays, the right edge follows a keyed motion (translations ``motion_dx``,
``motion_dy`` at ``motion_times``, eased C2 between keys) and then stops, so the sheet
jiggles and settles under Rayleigh damping ``alpha``, ``beta``; lumped mass from
``density`` (per unit area), optional in-plane ``gravity`` (along ``-y``). Targets: both
coordinates of every free vertex at the output times. Fitted: ``E`` per triangle with
``alpha`` and ``beta`` (:mod:`torchfit.problems.dynamic`). Not scale-free (inertia).
``conf/problem/membrane2d_dynamic.yaml`` is the preset (a 48 x 12 sheet).

``problem.dtype=float32`` with a nonlinear model needs ``problem.newton_atol >= 1e-4``
(checked; docs/notes/membrane2d.md); the ``linear`` model has no such limit.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar, List

import numpy as np
import torch
from torch import Tensor

from ..mesh import normalized_points, rectangle_triangles
from .font import ipam_mask
from ..params import Parameterization, per_element
from ..physics import NewtonOptions
from ..physics.dynamics import DynamicSystem, KeyedMotion
from ..physics.elasticity import QuasistaticElasticity, SimplicialElasticity, get_material
from ..residual import ForwardProducts
from ..settings import Choice
from .base import InverseProblem
from .config import (Backend, DType, ProblemConfig, ProblemConfigError, check_newton_settings,
                     require_setting, resolve_backend)
from .dynamic import (DynamicSettings, TimeIntegration, check_dynamic_flag,
                      check_dynamic_settings, time_steps_allocation)


#: the largest ratio of a cell's width to its height (or the reverse) the sheet accepts
_MAX_CELL_ASPECT = 1e6

class Model(Choice):
    """Constitutive model of the sheet (``MATERIALS`` and ``ALIASES`` of
    :mod:`torchfit.physics.elasticity`)."""

    linear = "linear"
    corotated = "corotated"
    stable_neo_hookean = "stable_neo_hookean"
    neo_hookean = "neo_hookean"              # alias of stable_neo_hookean
    rotated_linear = "rotated_linear"        # alias of corotated


class SheetData(Choice):
    """membrane2d observes every free vertex (docs/problems.md: ``dense`` only)."""

    dense = "dense"


#: smallest Newton ``atol`` accepted with ``dtype=float32`` for the nonlinear models
_FLOAT32_NEWTON_ATOL = 1e-4

#: The animation of docs/problems.md: (kind, value) per frame.
FRAMES: tuple[tuple[str, float], ...] = (
    ("stretch", 0.10), ("stretch", 0.20),
    ("shear", 0.10), ("shear", 0.20),
    ("bend", 10.0), ("bend", 20.0),
    ("stretch", -0.05), ("stretch", -0.10),
)
_SHEAR_STRETCH = 0.20


@dataclasses.dataclass
class Membrane2DConfig(DynamicSettings, ProblemConfig):
    """Settings of ``problem=membrane2d`` (defaults are the canonical values; ``noise``,
    ``seed``, ``transform``, ``device``, ``dtype`` from :class:`ProblemConfig`,
    ``problem.dynamic=true`` and its settings from :class:`DynamicSettings`)."""

    name: str = "membrane2d"
    nx: int = 96                        # cells along x (2 nx ny triangles)
    ny: int = 24                        # cells along y
    width: float = 2.0                  # rest rectangle [0, width] x [0, height]
    height: float = 0.5
    nu: float = 0.3                     # Poisson ratio, fixed (plane strain)
    model: Model = Model.corotated      # linear | corotated | stable_neo_hookean (neo_hookean)
    E_background: float = 1.0
    E_ink: float = 10.0                 # on the letters IPAM
    data: SheetData = SheetData.dense   # dense: every free vertex (neither edge), every frame
    E0: float = 1.0                     # initial guess, constant
    # linear solves: banded (CPU banded Cholesky, SPD; falls back to scipy) | scipy | cg
    backend: Backend = Backend.banded
    newton_rtol: float = 1e-11          # per frame, relative to the residual of the cold start
    newton_atol: float = 1e-13          # absolute floor (force units); float32 with a
                                        # nonlinear model needs >= 1e-4 (checked)
    newton_max_iter: int = 50
    # -- problem.dynamic=true: the sheet's values of DynamicSettings, then its own --
    dt: float = 0.02                    # s
    ode_rtol: float = 1e-6
    ode_atol: float = 1e-8
    duration: float = 2.0               # s
    frames: int = 20
    alpha: float = 0.5                  # true mass damping (1/s)
    beta: float = 0.002                 # true stiffness damping (s)
    alpha0: float = 0.2                 # initial guess
    beta0: float = 0.004
    gravity: float = 0.0                # in-plane, along -y (m/s^2)
    # keyed translation (dx, dy) of the right edge at motion_times (s), eased C2 between keys
    motion_times: List[float] = dataclasses.field(default_factory=lambda: [0.0, 0.3, 0.6])
    motion_dx: List[float] = dataclasses.field(default_factory=lambda: [0.0, 0.2, 0.1])
    motion_dy: List[float] = dataclasses.field(default_factory=lambda: [0.0, 0.15, 0.05])


def animation(right_rest: Tensor, width: float, height: float) -> Tensor:
    """Positions ``(8, n, 2)`` of the right-edge vertices ``right_rest`` ``(n, 2)`` per frame."""
    frames = []
    centre = torch.tensor([width, 0.5 * height], dtype=right_rest.dtype, device=right_rest.device)
    for kind, value in FRAMES:
        p = right_rest.clone()
        if kind == "stretch":
            p[:, 0] = width * (1.0 + value)
        elif kind == "shear":
            p[:, 0] = width * (1.0 + _SHEAR_STRETCH)
            p[:, 1] = right_rest[:, 1] + value
        else:  # bend
            angle = math.radians(value)
            rotation = torch.tensor([[math.cos(angle), -math.sin(angle)],
                                     [math.sin(angle), math.cos(angle)]], dtype=p.dtype,
                                    device=p.device)
            p = centre + (right_rest - centre) @ rotation.T
        frames.append(p)
    return torch.stack(frames)


class Membrane2D(InverseProblem):
    """The IPAM sheet as an inverse problem (fit one Young's modulus per triangle)."""

    config_class = Membrane2DConfig
    name = "membrane2d"
    field_name = "E"
    initial_setting = "E0"
    truth_fields = ("E_background", "E_ink")
    dim = 2
    scale_free = True
    default_sheet_frame = 5            # bend by 20 degrees: the most telling frame to draw
    #: the sheet in motion is another class (:class:`DynamicMembrane2D`)
    in_time: ClassVar[bool] = False

    def check(self, cfg: Membrane2DConfig) -> None:
        check_dynamic_flag(self, cfg, self.in_time)
        for key in ("nx", "ny"):
            require_setting(isinstance(getattr(cfg, key), int) and getattr(cfg, key) >= 1, cfg,
                            key, "must be an integer >= 1 (cells per side)")
        require_setting(cfg.nx >= 2, cfg, "nx", "the sheet needs at least two cells along x "
                        "so that some vertex is free")
        for key in ("width", "height"):
            require_setting(getattr(cfg, key) > 0, cfg, key, "must be positive")
        # a cell far longer than tall (or the reverse) is a degenerate triangle in float64
        aspect = (cfg.width / cfg.nx) / (cfg.height / cfg.ny)
        for key, bad in (("width", aspect > _MAX_CELL_ASPECT),
                         ("height", aspect < 1.0 / _MAX_CELL_ASPECT)):
            require_setting(not bad, cfg, key, f"makes cells {aspect:.3g} times as wide as "
                            f"tall (problem.width / problem.nx over problem.height / "
                            f"problem.ny); keep that ratio within [1e-6, 1e6]")
        require_setting(-1.0 < cfg.nu < 0.5, cfg, "nu", "must lie in (-1, 0.5) (Poisson ratio "
                        "of an isotropic material; 0.5 would be incompressible)")
        for key in ("E_background", "E_ink", "E0"):
            require_setting(getattr(cfg, key) > 0, cfg, key, "must be a positive Young's modulus")
        check_newton_settings(cfg)
        # float32: Newton residuals of the nonlinear models stall near 1e-5 force units on
        # the canonical sheet, so the float64 tolerances can never be met.
        require_setting(cfg.dtype != DType.float32 or cfg.model in (Model.linear,)
                        or cfg.newton_atol >= _FLOAT32_NEWTON_ATOL, cfg, "newton_atol",
                        f"is below what float32 reaches (problem.dtype=float32, "
                        f"problem.model={cfg.model}); set problem.newton_atol="
                        f"{_FLOAT32_NEWTON_ATOL:g} or more, or use problem.dtype=float64")

    def allocation(self, cfg: Membrane2DConfig) -> list[tuple[Any, ...]]:
        # per vertex: two coordinates of rest, position, load, adjoint and work vectors, the
        # triangles' deformation gradients and the factor (about 60 values, a lower bound)
        vertices = (cfg.nx + 1) * (cfg.ny + 1)
        return [(f"problem.nx={cfg.nx} problem.ny={cfg.ny}", vertices * 60 * 8.0,
                 f"{vertices:.3g} vertices")]

    # -- the hooks of the template --------------------------------------------------------
    def build_model(self, cfg: Membrane2DConfig) -> None:
        self.mesh = rectangle_triangles(cfg.nx, cfg.ny, cfg.width, cfg.height)
        self.model = SimplicialElasticity(torch.from_numpy(self.mesh.points),
                                          torch.from_numpy(self.mesh.cells), cfg.model.value,
                                          nu=cfg.nu, dtype=self.dtype, device=self.device)
        left = self.mesh.boundary_vertices("left")
        right = self.mesh.boundary_vertices("right")
        self.left_vertices = torch.as_tensor(left)
        self.right_vertices = torch.as_tensor(right)
        dirichlet = np.concatenate([left, right])
        newton = NewtonOptions(max_iter=cfg.newton_max_iter, rtol=cfg.newton_rtol,
                               atol=cfg.newton_atol)
        self.quasistatic = QuasistaticElasticity(self.model, dirichlet,
                                                 backend=resolve_backend(cfg.backend, self.device, 2),
                                                 newton=newton)
        # warm starts: each frame's Newton starts from its last solution
        self.warm_starts = self.quasistatic.equilibrium
        rest = self.model.rest.points
        right_frames = animation(rest[self.right_vertices], cfg.width, cfg.height)
        n_frames = right_frames.shape[0]
        left_frames = rest[self.left_vertices].expand(n_frames, -1, -1)
        self.dirichlet_positions = torch.cat([left_frames, right_frames], dim=1).contiguous()
        self.n_frames = n_frames

    def build_parameterization(self, cfg: Membrane2DConfig) -> Parameterization:
        return per_element(self.model.n_cells, self.mesh.adjacency(), cfg.transform.value,
                           name="Young's modulus", dtype=self.dtype)

    def build_observation(self, cfg: Membrane2DConfig) -> None:
        self.observed_vertices = self.quasistatic.free_vertices.to(self.device)
        self.observed_nodes = self.observed_vertices

    def true_field(self, cfg: Membrane2DConfig) -> Tensor:
        self.ink = torch.as_tensor(ipam_mask(normalized_points(self.mesh.centroids(),
                                                               self.mesh.extent)),
                                   device=self.device)
        ink = torch.full(self.ink.shape, cfg.E_ink, dtype=self.dtype, device=self.device)
        background = torch.full(self.ink.shape, cfg.E_background, dtype=self.dtype,
                                device=self.device)
        return torch.where(self.ink, ink, background)

    # -- the forward model ------------------------------------------------------------------
    def simulate(self, E: Tensor) -> Tensor:
        """Vertex positions ``(8, n_vertices, 2)`` of every frame for ``E`` ``(n_triangles,)``."""
        if E.shape != (self.model.n_cells,):
            raise ProblemConfigError(f"Young's modulus must have shape ({self.model.n_cells},) "
                                     f"(one per triangle), got {tuple(E.shape)}")
        return self.quasistatic(E, self.dirichlet_positions.to(E))

    def observe(self, x: Tensor) -> Tensor:
        """Both coordinates of every free vertex, frame-major ``(F * n_free * 2,)``."""
        return x[:, self.observed_vertices.to(x.device), :].reshape(-1)

    def forward_products(self, theta: Tensor) -> ForwardProducts:
        """:meth:`forward` at ``theta`` with explicit ``J v`` and ``J^T w``: the map's
        diagonal, the equilibrium's free-dof products (one solve per frame with its stored
        factor, ``dR/dE`` by the model's ``param_derivative``) and the gather of the
        observed dofs. No autograd graph (the static problem only; ``dynamic=true`` keeps
        autograd through its trajectory)."""
        theta = theta.detach()
        E = self.parameterization(theta)
        state = self.quasistatic.linearization(E, self.dirichlet_positions.to(E))
        rows = self._observed_free_rows(state.x.device)
        n_free, n_frames = self.quasistatic.equilibrium.free_dofs.numel(), state.n_frames

        def jvp(v: Tensor) -> Tensor:
            dx = state.free_jvp(self.parameterization.jvp(theta, v))      # (n_free, F)
            return dx.index_select(0, rows).T.reshape(-1)

        def vjp(w: Tensor) -> Tensor:
            grad = w.new_zeros(n_free, n_frames)
            grad.index_copy_(0, rows, w.view(n_frames, -1).T)
            return self.parameterization.vjp(theta, state.free_vjp(grad))

        x = state.x.reshape(n_frames, self.model.n_vertices, -1)
        return ForwardProducts(self.observe(x), jvp, vjp)

    def _observed_free_rows(self, device: torch.device) -> Tensor:
        """Rows of the observed dofs (vertex-major, both coordinates) among the free dofs."""
        if getattr(self, "_free_rows", None) is None:
            dim = self.model.rest.points.shape[1]
            dofs = (dim * self.observed_vertices.cpu()[:, None] + torch.arange(dim)).reshape(-1)
            self._free_rows = self.quasistatic.equilibrium.free_position(dofs)
        return self._free_rows.to(device)

    def simulate_jacobian(self, E: Tensor, directions: Tensor) -> Tensor:
        """``(dx/dE) directions`` ``(8, n_vertices, 2, k)``: one solve with ``k`` right-hand
        sides per frame at the stored solution (gives :meth:`forward_jacobian`; the
        solvers use it only below ``solver.dense_jacobian_max_params`` parameters, far
        fewer than the canonical 4,608)."""
        return self.quasistatic.jacobian(E, self.dirichlet_positions.to(E), directions)

    # -- what the loggers draw -------------------------------------------------------------
    def field_image(self, field: Tensor, pixels_per_cell: int = 4) -> np.ndarray:
        """The per-triangle field as an image ``(ny p, nx p)``, row 0 at the top (max y).

        Each cell is ``p x p`` pixels; a pixel takes the triangle under its centre (on
        the diagonal: the one below it).
        """
        p = int(pixels_per_cell)
        values = field.detach().cpu().numpy().reshape(self.cfg.ny, self.cfg.nx, 2)
        centres = (np.arange(p) + 0.5) / p
        u = np.broadcast_to(centres[None, :], (p, p))          # along x inside the cell
        v = np.broadcast_to(centres[:, None], (p, p))          # along y
        upper = (v > u).astype(np.int64)                       # above the diagonal
        image = values[:, :, upper]                            # (ny, nx, p, p): [j, i, v, u]
        image = image.transpose(0, 2, 1, 3).reshape(self.cfg.ny * p, self.cfg.nx * p)
        return image[::-1].copy()

    def frame_errors(self, x: Tensor) -> dict[str, np.ndarray]:
        """Per-frame position errors against the noise-free truth: ``u_err_inf``, ``u_err_2``."""
        du = (x.detach() - self.x_true).reshape(x.shape[0], -1)
        return {"u_err_inf": du.abs().amax(dim=1).cpu().numpy(),
                "u_err_2": torch.linalg.vector_norm(du, dim=1).cpu().numpy()}

    def frame_names(self) -> list[str]:
        """Short labels of the frames (for plots)."""
        names = []
        for kind, value in FRAMES:
            if kind == "stretch":
                names.append(f"{'stretch' if value > 0 else 'compress'} {abs(value):.0%}")
            elif kind == "shear":
                names.append(f"shear {value:g} at {_SHEAR_STRETCH:.0%}")
            else:
                names.append(f"bend {value:g} deg")
        return names

    def describe(self) -> dict[str, Any]:
        out = super().describe()
        out.update({"model": get_material(self.cfg.model.value).name, "nu": self.model.nu,
                    "n_triangles": self.model.n_cells, "n_vertices": self.model.n_vertices,
                    "n_frames": self.n_frames, "n_ink": int(self.ink.sum())})
        return out


class DynamicMembrane2D(Membrane2D):
    """The sheet in motion (``problem.dynamic=true``; module docstring): fit ``E`` per
    triangle with ``alpha`` and ``beta`` to vertex positions at the output times (its
    :attr:`time` a :class:`~torchfit.problems.dynamic.TimeIntegration`)."""

    # the motion goes through the trajectory's own autograd Function, not the equilibrium
    forward_products = InverseProblem.forward_products

    scale_free = False
    in_time = True
    time: TimeIntegration

    def check(self, cfg: Membrane2DConfig) -> None:
        super().check(cfg)
        check_dynamic_settings(cfg)
        keys = len(cfg.motion_times)
        require_setting(keys >= 1 and len(cfg.motion_dx) == keys == len(cfg.motion_dy), cfg,
                        "motion_dx", f"motion_dx and motion_dy need one value per key time "
                        f"(problem.motion_times has {keys})")
        times = list(cfg.motion_times)
        require_setting(all(b > a for a, b in zip(times[:-1], times[1:])), cfg, "motion_times",
                        "must increase strictly (s)")

    def allocation(self, cfg: Membrane2DConfig) -> list[tuple[Any, ...]]:
        return [*super().allocation(cfg),
                *time_steps_allocation(cfg, 2 * (cfg.nx + 1) * (cfg.ny + 1))]

    def build_model(self, cfg: Membrane2DConfig) -> None:
        dtype, device = self.dtype, self.device
        self.mesh = rectangle_triangles(cfg.nx, cfg.ny, cfg.width, cfg.height)
        self.model = SimplicialElasticity(torch.from_numpy(self.mesh.points),
                                          torch.from_numpy(self.mesh.cells), cfg.model.value,
                                          nu=cfg.nu, dtype=dtype, device=device)
        left = self.mesh.boundary_vertices("left")
        right = self.mesh.boundary_vertices("right")
        self.left_vertices = torch.as_tensor(left)
        self.right_vertices = torch.as_tensor(right)
        dirichlet = np.sort(np.concatenate([left, right]))
        self.free_vertices = torch.as_tensor(np.setdiff1d(np.arange(self.model.n_vertices),
                                                          dirichlet))
        fixed = torch.as_tensor((dirichlet[:, None] * 2 + np.arange(2)).reshape(-1))
        rest = self.model.rest.points.to(dtype)                     # (n_vertices, 2)
        # keyed translation of the right edge; the left edge stays
        key_times = torch.as_tensor(cfg.motion_times, dtype=dtype)
        shift = torch.stack([torch.as_tensor(cfg.motion_dx, dtype=dtype),
                             torch.as_tensor(cfg.motion_dy, dtype=dtype)], dim=1)   # (K, 2)
        moving = torch.as_tensor(np.isin(dirichlet, right), device=device)
        base = rest[torch.as_tensor(dirichlet)]                     # (n_dirichlet, 2)
        keys = base[None] + shift[:, None, :] * moving[None, :, None].to(dtype)
        # lumped mass: a third of each triangle's mass on each of its vertices
        areas = self.model.rest.volumes.to(dtype)
        vertex_mass = torch.zeros(self.model.n_vertices, dtype=dtype, device=device).index_add(
            0, torch.as_tensor(self.mesh.cells.reshape(-1), device=device),
            (cfg.density * areas / 3.0).repeat_interleave(3))
        gravity = torch.zeros(self.model.n_vertices, 2, dtype=dtype, device=device)
        gravity[:, 1] = -cfg.gravity
        self.system = DynamicSystem(
            self.model, self.model.n_cells, vertex_mass.repeat_interleave(2), fixed,
            KeyedMotion(key_times, keys.reshape(len(cfg.motion_times), -1)), None,
            gravity.reshape(-1), rest.reshape(-1), vertex_dim=2)
        newton = NewtonOptions(max_iter=cfg.newton_max_iter, rtol=cfg.newton_rtol,
                               atol=cfg.newton_atol)
        self.time = TimeIntegration.from_settings(
            cfg, self.system, 2, resolve_backend(cfg.backend, self.device, 2), newton,
            start_field=float(cfg.E0))
        self.output_times, self.integrator = self.time.output_times, self.time.integrator
        self.n_frames = int(self.output_times.numel())

    def build_observation(self, cfg: Membrane2DConfig) -> None:
        self.observed_vertices = self.free_vertices.to(self.device)
        self.observed_nodes = self.observed_vertices

    def simulate(self, physical: Tensor) -> Tensor:
        """Vertex positions ``(K, n_vertices, 2)`` at the output times for ``[E, alpha, beta]``."""
        return self.time.positions(physical)

    def simulate_jacobian(self, physical: Tensor, directions: Tensor) -> Tensor:
        """``(d positions / d [E, alpha, beta]) directions`` ``(K, n_vertices, 2, k)``."""
        return self.time.jacobian(physical, directions)

    def frame_names(self) -> list[str]:
        return self.time.frame_names()

    @property
    def default_sheet_frame(self) -> int:
        """The first output time after the motion stops (the sheet jiggles there)."""
        stop = float(self.cfg.motion_times[-1])
        later = torch.nonzero(self.output_times > stop).reshape(-1)
        return int(later[0]) if later.numel() else self.n_frames - 1
