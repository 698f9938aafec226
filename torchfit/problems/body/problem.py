"""``problem=animation``: a rigged body whose Young's modulus is fitted to a user's animation.

The data are an animation folder (:mod:`torchfit.mesh.formats.folder`). The rest surface is
tetrahedralised by pytetwild (cached on disk by a hash of the surface and the options: the
same input gives the same tetrahedra); the user's surface vertices are embedded in the
tetrahedra by barycentric weights, so targets, errors and exports live on them; the rig
prescribes the tetrahedron vertices it drives (:mod:`torchfit.mesh.rig`). Every frame is an
independent quasistatic equilibrium (linear, corotated or stable neo-Hookean elasticity)
started from the animated pose, ``(F, n_vertices, 3)``; ``observe`` is every user surface
vertex but the driven ones in every frame, ``(F * n_obs * 3,)``.

Targets: ``target=rig``, the animated surface (no material reproduces it exactly: the
measure is how far fitting lowers the surface error below the homogeneous material's);
``target=synthetic``, simulated from a known field (``truth=regions`` or ``blocks``).
Parameters: ``grid`` (nodes along the body's principal axes, trilinear to tetrahedra:
:mod:`.grid`), ``region`` or ``tet``. Every load is a prescribed displacement:
scale-free. What the run reports of the body: :mod:`.report`, :mod:`.motion`.
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
from pathlib import Path
from typing import Any, Callable, ContextManager, Protocol

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from ...memory import check_allocation
from ...mesh import MeshError, SimplexMesh, element_adjacency
from ...mesh.formats.folder import Animation, AnimationError
from ...mesh.formats.readers import read_animation
from ...mesh.embedding import Embedding, dof_matrix, embed_points
from ...mesh.rig import joint_cells, skeleton_drive, surface_drive
from ...mesh.tetwild.store import RUN_MESH_FILE, KeptMesh, write_run_mesh
from ...mesh.tetwild.tetrahedralize import TetMesh
from ...params import Parameterization, per_element, per_region
from ...physics import NewtonOptions
from ...physics.elasticity import QuasistaticElasticity, SimplicialElasticity
from ...steps import count, quiet, step
from ..base import InverseProblem, array_digest
from .grid import blocks_field, body_grid, grid_parameterization
from .motion import most_deformed_frame, most_strained_cells, picture_up, view_axes
from .setup import (animation_summary, check_rig, check_tet_settings, first_simulation, tet_mesh,
                    tet_options)
from .report import (BODY_METRICS, body_metrics, describe_body, frame_report,
                          inverted_counts, min_volume_ratios, surface_distances, volume_change)
from ..config import (Backend, ProblemConfigError, check_newton_settings, require_setting,
                     resolve_backend, setting_error)
from ..dynamic import check_dynamic_flag
from .held_out import NO_VALIDATION, FrameSplit, split_frames
from .model_comparison import ModelComparison
from .bounds import bounds_warning, check_bounds, modulus_bounds, region_report, theta_bounds
from .repeated_poses import distinct_poses
from .init_field import initial_field_theta
from .config import Layout, RiggedBodyConfig, Target, Truth


log = logging.getLogger(__name__)

#: largest distance (fraction of the bounding-box diagonal) of a surface vertex outside the
#: tetrahedra before the tetrahedralisation is judged not to match the surface
_MAX_OUTSIDE = 0.02
#: what a body holds per tetrahedron and frame (F, stress, derivatives: 40 values) and per
#: tet vertex and frame (9 values), in float64: the estimate of :func:`body_bytes`
_VALUES_PER_CELL, _VALUES_PER_POINT = 40, 9
#: tet vertices per tetrahedron of fTetWild's meshes (0.30 measured on the short arm)
_POINTS_PER_CELL = 0.3


def edge_count(cfg: RiggedBodyConfig, animation: Animation) -> tuple[str, float, int, str]:
    """The setting, count of tetrahedra, frames and description :func:`check_tet_count`
    checks before fTetWild runs: ``tet_count``, else the count ``tet_edge_length`` implies
    (the body's volume filled with regular tetrahedra of that edge: a lower bound, fTetWild
    makes about :data:`~torchfit.mesh.tetwild.size.TETS_PER_REGULAR` times more)."""
    from ...mesh.tetwild.size import body_volume

    frames = animation.n_frames
    if cfg.tet_count is not None:
        return (f"problem.tet_count={cfg.tet_count}", float(cfg.tet_count), frames,
                f"{float(cfg.tet_count):.3g} tetrahedra x {frames} frames")
    used = animation.rest_vertices[np.unique(animation.faces)]
    edge = cfg.tet_edge_length * float(np.linalg.norm(used.max(axis=0) - used.min(axis=0)))
    regular = edge ** 3 / (6.0 * math.sqrt(2.0))
    cells = body_volume(animation.rest_vertices, animation.faces) / regular \
        if regular > 0 else math.inf
    return (f"problem.tet_edge_length={cfg.tet_edge_length}", cells, frames,
            f"at least {cells:.3g} tetrahedra x {frames} frames")


def body_bytes(cells: float, points: float, frames: int) -> float:
    """Bytes a body of ``cells`` tetrahedra and ``points`` vertices holds over ``frames``
    frames at once (a lower bound of the fit's memory: docs/guide/resume.md)."""
    return frames * (cells * _VALUES_PER_CELL + points * _VALUES_PER_POINT) * 8.0


def check_tet_count(setting: str, cells: float, frames: int, what: str) -> None:
    """Refuse (one line naming ``setting`` and the largest count that fits) a count of
    tetrahedra whose :func:`body_bytes` exceed the memory limit, before fTetWild runs."""
    from ...memory import LIMIT_VARIABLE, memory_limit, size_text

    nbytes = body_bytes(cells, _POINTS_PER_CELL * cells, frames)
    limit = memory_limit()
    if limit is None or nbytes <= limit:
        return
    largest = limit / body_bytes(1.0, _POINTS_PER_CELL, frames)
    source = LIMIT_VARIABLE if os.environ.get(LIMIT_VARIABLE, "").strip() else \
        "available memory"
    change = "a larger value" if "edge_length" in setting else "a smaller value"
    raise ProblemConfigError(f"{setting}: needs about {size_text(nbytes)} for {what}, more than "
                             f"the {size_text(limit)} of {source}, which hold at most about "
                             f"{largest:.2g} tetrahedra over {frames} frame(s); choose {change} "
                             f"(or set {LIMIT_VARIABLE} on a machine with more memory); nothing "
                             "was tetrahedralised")


class RiggedBody(InverseProblem):
    """Fit Young's modulus so that the simulated body follows a rigged animation."""

    config_class = RiggedBodyConfig
    name = "animation"
    field_name = "E"
    initial_setting = "E0"
    truth_fields = ("E_blocks", "E_regions")
    dim = 3
    scale_free = True
    #: the problem wrote its animation folder itself (a run copies it as an example)
    writes_animation = False
    #: arm3d's fitted grid may start a fit of the same arm read as an animation folder
    parameter_family = "rigged body"
    #: where the documentation explains a fold of this body (the arm's; none for yours)
    fold_docs: str | None = None

    #: how the distinct poses are simulated: this process's quasistatic solver, or what a
    #: distributed run plugged in (:meth:`plug`)
    quasistatic: "PoseSimulation"

    def __init__(self, cfg: Any = None, *, kept_mesh: KeptMesh | None = None,
                 **overrides: Any) -> None:
        #: the run's own tetrahedral mesh (a resume, ``simulate``), used before the cache
        self.kept_mesh = kept_mesh
        #: where :meth:`forward_jacobian` comes from when a distributed run gave one
        self.jacobian_provider: Callable[[Tensor], Any] | None = None
        self._simulated = False         # the first simulation's progress lines are shown
        super().__init__(cfg, **overrides)

    def plug(self, simulation: "PoseSimulation",
             jacobian: Callable[[Tensor], Any] | None = None) -> None:
        """The seam a distributed run plugs into: simulate the poses with ``simulation``
        from now on and, where given, take :meth:`forward_jacobian` from ``jacobian``
        (``theta -> (m, n_params)`` rows, or a handle with the products the dense path
        forms: ``torchfit.run.distributed.rows``)."""
        self.quasistatic = simulation
        self.jacobian_provider = jacobian

    # -- hooks of the template --------------------------------------------------------
    def check(self, cfg: RiggedBodyConfig) -> None:
        check_dynamic_flag(self, cfg)
        require_setting(-1.0 < cfg.nu < 0.5, cfg, "nu", "must lie in (-1, 0.5) (Poisson ratio "
                        "of an isotropic material; 0.5 would be incompressible)")
        require_setting(cfg.E0 > 0, cfg, "E0", "must be a positive Young's modulus")
        require_setting(cfg.gravity is None or cfg.dynamic, cfg, "gravity", "is read by the "
                        "body in time only (problem.dynamic=true); the frame-by-frame body "
                        "has none (leave it null)")
        require_setting(cfg.grid is None or (len(cfg.grid) == 3 and all(
            int(n) >= 2 for n in cfg.grid)), cfg, "grid", "must list three node counts >= 2 "
            "(along the body's principal axes, the longest last) or be null (grid_nodes)")
        require_setting(cfg.grid_nodes >= 8, cfg, "grid_nodes", "must be at least 8 (2 per axis)")
        for key in ("E_regions", "E_blocks"):
            values = getattr(cfg, key)
            require_setting(len(values) >= 1 and all(v > 0 for v in values), cfg, key,
                            "must list positive Young's moduli")
        require_setting(len(cfg.E_blocks) == 3, cfg, "E_blocks",
                        "must list three moduli: background, stiff block, soft block")
        require_setting(cfg.rig_tolerance > 0, cfg, "rig_tolerance", "must be positive")
        check_tet_settings(cfg)
        check_newton_settings(cfg)
        check_bounds(cfg)
        require_setting(cfg.frames is None or len(cfg.frames) >= 1, cfg, "frames",
                        "must list at least one frame (or be null for all)")
        require_setting(cfg.frames is None or len(set(cfg.frames)) == len(cfg.frames), cfg,
                        "frames", "lists a frame twice; list each frame once")
        require_setting(cfg.fps >= 0, cfg, "fps", "must be >= 0 (glTF frames per second; 0: "
                        "the animation's keyframes)")
        require_setting(cfg.backend != Backend.banded, cfg, "backend", "banded suits thin 2-D "
                        "sheets, not a 3-D body; use auto, pardiso, scipy or cg")
        self.check_source(cfg)

    def allocation(self, cfg: RiggedBodyConfig) -> list[tuple[str, float, str]]:
        if cfg.tet_count is not None:      # before the animation is read or written
            frames = len(cfg.frames) if cfg.frames else 1       # at least one
            check_tet_count(f"problem.tet_count={cfg.tet_count}", float(cfg.tet_count), frames,
                            f"{float(cfg.tet_count):.3g} tetrahedra x {frames} frame(s)")
        # a grid (the parameters, or the blocks truth): per node theta, its gradient, the
        # search direction, the truth and the blocks' index grids (about 8 values)
        if cfg.parameters != Layout.grid and not (cfg.target == Target.synthetic
                                                  and cfg.truth == Truth.blocks):
            return []
        nodes = float(np.prod([float(n) for n in cfg.grid])) if cfg.grid else 1.5 * cfg.grid_nodes
        setting = f"problem.grid={list(cfg.grid)}" if cfg.grid else \
            f"problem.grid_nodes={cfg.grid_nodes}"
        return [(setting, nodes * 8 * 8.0, f"{nodes:.3g} grid nodes")]

    def check_source(self, cfg: RiggedBodyConfig) -> None:
        require_setting(bool(cfg.path), cfg, "path", "must name the folder of your animation "
                        "(holding animation.yaml), a USD stage or a glTF file; see "
                        "docs/guide/formats.md")

    def load(self, cfg: RiggedBodyConfig) -> Animation:
        """The animation (``problem=arm3d`` makes and writes its own first)."""
        try:
            return read_animation(cfg.path, cfg.prim, cfg.fps)
        except MeshError as err:
            where, message = Path(cfg.path).expanduser().absolute(), str(err)
            if message.startswith(f"{where} "):             # the sniffed file types' lines
                message = message[len(str(where)) + 1:]
            elif message.startswith(f"{where}: "):          # a reader's line on the file itself
                message = message[len(str(where)) + 2:]
            raise ProblemConfigError(f"problem.path={where}: {message}") from err

    def build_model(self, cfg: RiggedBodyConfig) -> None:
        with step(f"reading the animation {cfg.path or self.name}") as progress:
            animation = self.load(cfg)
            # every frame's motion (not the fitted subset's) settles the frame of a round body
            self.motion = animation.frames - animation.rest_vertices
            self.frame_split = self.split_frames(cfg, animation)
            fitted = cfg.frames if self.frame_split is None else self.frame_split.fitted
            in_file, whole = animation.n_frames, animation
            if fitted is not None:
                try:
                    animation = animation.select([int(f) for f in fitted])
                except AnimationError as err:
                    raise setting_error("frames", cfg.frames, str(err)) from err
            progress.result = animation_summary(animation, in_file)
        self.rig_report = check_rig(cfg, animation)
        rigged = self.driving_animation(whole, animation)
        self.animation = animation
        for text in animation.warnings:
            log.warning(f"{animation.path}: rest surface: {text}")
        self.n_frames = animation.n_frames
        if self.kept_mesh is None:     # the count an edge length implies, before fTetWild
            check_tet_count(*edge_count(cfg, animation))
        self.tet = self.tetrahedralize(cfg, animation)
        # per frame: each tetrahedron's F, stress, derivatives (40 values), vertex (9 values)
        cells, points = len(self.tet.cells), len(self.tet.points)
        check_allocation(f"problem.tet_edge_length={cfg.tet_edge_length} with "
                         f"{animation.n_frames} frames", body_bytes(cells, points,
                                                                    animation.n_frames),
                         f"{cells} tetrahedra x {animation.n_frames} frames", ProblemConfigError)
        points, cells = self.tet.points, self.tet.cells
        self.mesh = SimplexMesh(points, cells)
        self.model = SimplicialElasticity(torch.from_numpy(points), torch.from_numpy(cells),
                                          cfg.model.value, nu=cfg.nu, dtype=self.dtype,
                                          device=self.device)
        diagonal = float(np.linalg.norm(points.max(0) - points.min(0)))
        try:
            with step(f"embedding {count(animation.n_vertices)} surface vertices in "
                      f"{count(len(cells))} tetrahedra"):
                self.embedding: Embedding = embed_points(animation.rest_vertices, points, cells,
                                                         max_distance=_MAX_OUTSIDE * diagonal)
            surface = (rigged.rest_vertices, rigged.faces, rigged.frames)
            with step(f"attaching the rig to {count(len(points))} tetrahedron vertices in "
                      f"{count(rigged.n_frames)} frames") as progress:
                drive = skeleton_drive(points, cells, rigged.skeleton, *surface) \
                    if rigged.skeleton is not None else \
                    surface_drive(points, rigged.driven, *surface)
                progress.result = f"{count(len(drive.vertices))} driven (prescribed)"
        except MeshError as err:
            raise ProblemConfigError(f"{animation.path}: {err}") from err
        if drive.idle_bones:
            log.warning(f"{animation.path}: rig check: bone(s) {', '.join(drive.idle_bones)} "
                        f"drive no material (no tetrahedron vertex within attach_radius="
                        f"{animation.skeleton.attach_radius:.3g} m is nearest to them): their "
                        "flesh follows only its neighbours; raise the attach radius "
                        "(torchfit:attachRadius) or give those bones a length")
        dirichlet = drive.vertices
        self.dirichlet_vertices = dirichlet
        self.dirichlet_positions = torch.as_tensor(drive.positions, dtype=self.dtype,
                                                   device=self.device)
        self.start_positions = torch.as_tensor(drive.start, dtype=self.dtype, device=self.device)
        # frames repeating a pose share one simulation (repeated_poses.py)
        self.repeated_poses = self.pose_repeats()
        # warm starts (the last solution, at the solver's next point) keep going rather than
        # fall back to the animated pose: near full bend that cold start needs far more
        # Newton iterations (folds and inverted elements at the inner elbow)
        newton = NewtonOptions(max_iter=cfg.newton_max_iter, rtol=cfg.newton_rtol,
                               atol=cfg.newton_atol, warm_max_iter=cfg.newton_max_iter)
        self.backend = resolve_backend(cfg.backend, self.device, 3)
        self.quasistatic = QuasistaticElasticity(self.model, dirichlet, backend=self.backend,
                                                 newton=newton, start="rest",
                                                 warm_start=cfg.warm_start)
        self.comparison = ModelComparison(self.mesh, dirichlet, self.backend, cfg, self.dtype,
                                          self.device)
        self.tet_regions, self.region_names = self.regions(cfg)
        self.full_bend_frame = self.reference_frame()
        kept_frame = None if self.kept_mesh is None else self.kept_mesh.frame_for(
            animation.rest_vertices, animation.faces, self.tet_options)    # a run's own
        self.grid = body_grid(points, cells, self.motion, cfg.grid_nodes, cfg.grid, kept_frame)
        self.grid_shape = self.grid.shape
        up, source = picture_up(animation.up, animation.skeleton, self.grid.axes[2])
        log.info("pictures: up (%s), %s", ", ".join(f"{c:.3g}" for c in up), source)
        self.view_axes = view_axes(animation.rest_vertices, animation.frames, up)
        self.joint_cells = self.joint_region(cfg)

    def split_frames(self, cfg: RiggedBodyConfig, animation: Animation) -> FrameSplit | None:
        """The fitted and validation frames of ``animation`` (every frame of the file)."""
        return split_frames(cfg, animation.rest_vertices, animation.frames)

    def driving_animation(self, whole: Animation, fitted: Animation) -> Animation:
        """The frames the rig drives the body through: the fitted ones (each an
        independent equilibrium); the dynamic body's are the whole shot up to its last."""
        return fitted

    def pose_repeats(self) -> tuple[Tensor, Tensor] | None:
        """Frames repeating a pose share one simulation (:mod:`.repeated_poses`)."""
        return distinct_poses(self.dirichlet_positions)

    def tetrahedralize(self, cfg: RiggedBodyConfig, animation: Animation) -> TetMesh:
        """The rest surface's tet mesh, built in the body's frame (the same tetrahedra for
        a rotated body; :func:`.setup.tet_mesh`); a run's own mesh (``mesh.npz``)
        first."""
        self.tet_options = tet_options(cfg)
        return tet_mesh(cfg, animation, self.motion, self.kept_mesh)

    # -- regions and the joint ----------------------------------------------------------
    def regions(self, cfg: RiggedBodyConfig) -> tuple[np.ndarray | None, list[str]]:
        """Region label per tetrahedron (carried inward from the nearest labelled surface
        vertex), or ``None`` when the animation has no labels."""
        labels = self.animation.region_labels
        if labels is None:
            return None, []
        _, nearest = cKDTree(self.animation.rest_vertices).query(self.mesh.centroids())
        return labels[nearest], list(self.animation.region_names)

    def joint_region(self, cfg: RiggedBodyConfig) -> np.ndarray:
        """Tetrahedra whose volume change is reported (their name: :attr:`joint_label`): near
        the rig's joints, else the most strained in the reference frame's animated pose."""
        skeleton = self.animation.skeleton
        if skeleton is not None and len(skeleton.joints()):
            self.joint_label = "joint region"
            return joint_cells(self.mesh.centroids(), skeleton)
        self.joint_label = "most strained region"
        pose = self.start_positions[self.full_bend_frame].cpu().numpy()
        return most_strained_cells(self.mesh.points, self.mesh.cells, pose)

    def reference_frame(self) -> int:
        """The frame the pictures compare: the most deformed target surface
        (:func:`.motion.most_deformed_frame`)."""
        return most_deformed_frame(self.animation.rest_vertices, self.animation.frames)

    # -- parameters, observation, truth ----------------------------------------------
    def build_parameterization(self, cfg: RiggedBodyConfig) -> Parameterization:
        centroids = self.mesh.centroids()
        if cfg.parameters == Layout.grid:
            return grid_parameterization(self.grid, centroids, cfg.transform.value, self.dtype)
        if cfg.parameters == Layout.region:
            if self.tet_regions is None:
                raise setting_error("parameters", cfg.parameters.value,
                                    "needs region labels: add a 'regions' entry to the "
                                    "animation's manifest (or use grid or tet)")
            return per_region(self.tet_regions, element_adjacency(self.mesh.cells),
                              cfg.transform.value, name="Young's modulus", dtype=self.dtype)
        return per_element(self.model.n_cells, element_adjacency(self.mesh.cells),
                           cfg.transform.value, name="Young's modulus", dtype=self.dtype)

    def build_observation(self, cfg: RiggedBodyConfig) -> None:
        animation = self.animation
        if animation.driven is not None:
            observed = np.flatnonzero(~animation.driven.mask)
        else:
            observed = np.arange(animation.n_vertices)
        self.observed_vertices = torch.as_tensor(observed)
        self.observed_nodes = self.observed_vertices
        self._observed_weights = torch.as_tensor(self.embedding.weights[observed],
                                                 dtype=self.dtype, device=self.device)
        self._observed_corners = torch.as_tensor(self.mesh.cells[self.embedding.cells[observed]],
                                                 device=self.device)

    def start_settings(self) -> list[str]:
        return [*super().start_settings(), "problem.init_field"]

    def material_density(self, theta: Tensor) -> tuple[float, str] | None:
        """The density (kg/m^3) written with the fitted material and where it comes from;
        ``None``: a quasistatic body does not determine it (the outputs assume one)."""
        return None

    def initial_parameters(self, cfg: RiggedBodyConfig) -> Tensor:
        """The constant ``E0``, or the field of ``problem.init_field`` projected on the
        parameters (:func:`.init_field.initial_field_theta`)."""
        if not cfg.init_field:
            return super().initial_parameters(cfg)
        return initial_field_theta(self, cfg)

    def true_field(self, cfg: RiggedBodyConfig) -> Tensor | None:
        if cfg.target == Target.rig:
            return None
        if cfg.truth == Truth.regions:
            if self.tet_regions is None:
                raise setting_error("truth", cfg.truth.value, "needs region labels in the "
                                    "animation (use truth=blocks)")
            n_regions = int(self.tet_regions.max()) + 1
            require_setting(len(cfg.E_regions) == n_regions, cfg, "E_regions",
                            f"must list one modulus per region ({n_regions}: "
                            f"{', '.join(self.region_names)})")
            values = torch.tensor(cfg.E_regions, dtype=self.dtype, device=self.device)
            return values[torch.as_tensor(self.tet_regions, device=self.device)]
        return blocks_field(self.grid, self.mesh.centroids(), cfg.E_blocks, self.dtype,
                            self.device)

    def measured_data(self, cfg: RiggedBodyConfig) -> Tensor:
        frames = torch.as_tensor(self.animation.frames, dtype=self.dtype, device=self.device)
        return frames[:, self.observed_vertices.to(self.device), :].reshape(-1)

    # -- the forward model --------------------------------------------------------------
    def simulate(self, E: Tensor) -> Tensor:
        """Tetrahedron vertex positions ``(F, n_vertices, 3)`` for ``E`` ``(n_tets,)``."""
        if E.shape != (self.model.n_cells,):
            raise ProblemConfigError(f"Young's modulus must have shape ({self.model.n_cells},) "
                                     f"(one per tetrahedron), got {tuple(E.shape)}")
        poses = self.simulated_poses()      # each distinct pose once, then every frame
        drive, start = self.dirichlet_positions[poses], self.start_positions[poses]
        with contextlib.nullcontext() if self._simulated else \
                first_simulation(len(drive), self.model.n_cells, self.cfg.model.value):
            x = self.quasistatic(E, drive.to(E), x_init=start.to(E))
        self._simulated = True
        return x if self.repeated_poses is None else x[self.repeated_poses[1]]

    def simulated_poses(self) -> Tensor | slice:
        """The frames simulated (the first of each distinct pose, ``repeated_poses.py``):
        an index ``(P,)``, or every frame."""
        return slice(None) if self.repeated_poses is None else self.repeated_poses[0]

    def independent_simulation(self) -> ContextManager[None]:
        """Cold starts from the animated pose that seed no warm start (the synthetic
        target, the homogeneous baseline): :meth:`Equilibrium.independent`."""
        return self.quasistatic.equilibrium.independent()

    def simulation_state(self) -> dict[str, Any]:
        """The solutions Newton's next warm start reads (the anchor, the most recent one)."""
        return self.quasistatic.equilibrium.warm_start_state()

    def restore_simulation_state(self, state: dict[str, Any]) -> None:
        self.quasistatic.equilibrium.restore_warm_start_state(state, self.device)

    def simulation_accuracy(self) -> float | None:
        """Newton's relative tolerance: 48 nonlinear frames are solved to it, not to round-off."""
        return max(float(self.cfg.newton_rtol), torch.finfo(self.dtype).eps)

    def surface(self, x: Tensor) -> Tensor:
        """The user's surface vertices ``(..., V_surface, 3)`` of tet positions ``(..., n, 3)``."""
        return self.embedding.apply(x)

    def observe(self, x: Tensor) -> Tensor:
        """The observed surface vertices of every frame, frame-major ``(F * n_obs * 3,)``."""
        corners = self._observed_corners.to(x.device)
        weights = self._observed_weights.to(x)
        return (x[..., corners, :] * weights[..., None]).sum(-2).reshape(-1)

    def forward_jacobian(self, theta: Tensor) -> Tensor:
        """``d observe(simulate(map(theta))) / d theta`` ``(m, n_params)``: every frame's
        rows of :meth:`pose_jacobian` (or the :attr:`jacobian_provider`'s)."""
        if self.jacobian_provider is not None:
            return self.jacobian_provider(theta)
        observed = self.pose_jacobian(theta)
        if self.repeated_poses is not None:
            observed = observed[self.repeated_poses[1]]
        return observed.reshape(-1, observed.shape[-1])                 # (F n_obs 3, n)

    def pose_jacobian(self, theta: Tensor) -> Tensor:
        """``(P, n_obs 3, n_params)`` of each simulated pose (:meth:`simulated_poses`): every
        parameter direction a right-hand side of the pose's one factorisation, the embedding
        applied to its columns as soon as they are solved (no ``(F, V, 3, n)``)."""
        E = self.parameterization(theta.detach())
        directions = self.parameterization.jacobian(theta.detach())          # (n_cells, n)
        poses = self.simulated_poses()
        return self.quasistatic.jacobian(E, self.dirichlet_positions[poses].to(E), directions,
                                         x_init=self.start_positions[poses].to(E),
                                         observe=self._observation_matrix(E))

    def _observation_matrix(self, like: Tensor) -> Tensor:
        """The observed rows of the embedding on the flat dofs, sparse
        ``(n_obs 3, n_vertices 3)`` (rows and columns point-major, as ``observe``; cached)."""
        key = (like.dtype, like.device)
        if getattr(self, "_observation_key", None) != key:
            self._observation = dof_matrix(self._observed_corners.cpu(),
                                           self._observed_weights.cpu(), self.model.n_vertices,
                                           self.model.dim).to(like)
            self._observation_key = key
        return self._observation

    # -- what the metrics and outputs report ---------------------------------------------
    def clean_targets(self) -> Tensor:
        """Noise-free targets ``(F, n_obs, 3)``: the animation, or the synthetic truth's."""
        if self.x_true is not None:
            return self.observe(self.x_true).reshape(self.n_frames, -1, 3)
        return torch.as_tensor(self.animation.frames, dtype=self.dtype, device=self.device)[
            :, self.observed_vertices.to(self.device)]

    def clean_surface(self) -> Tensor:
        """Noise-free target surface of every user vertex ``(F, V, 3)`` (observed or not)."""
        if self.x_true is not None:
            return self.surface(self.x_true)
        return torch.as_tensor(self.animation.frames, dtype=self.dtype, device=self.device)

    def surface_error_field(self, x: Tensor) -> Tensor:
        """Distance of every user surface vertex to its noise-free target ``(F, V)``."""
        with torch.no_grad():
            return surface_distances(self.surface(x), self.clean_surface())

    def surface_errors(self, x: Tensor) -> Tensor:
        """Distance of every observed surface vertex to its noise-free target ``(F, n_obs)``."""
        return surface_distances(self.observe(x).reshape(self.n_frames, -1, 3),
                                 self.clean_targets())

    def joint_volume_change(self, x: Tensor) -> np.ndarray:
        """Relative volume change of the joint region per frame ``(F,)`` (``V / V_rest - 1``)."""
        return volume_change(_positions(x), self.mesh.points, self.mesh.cells[self.joint_cells])

    def inverted_tets(self, x: Tensor) -> np.ndarray:
        """Tetrahedra turned inside out (signed volume <= 0) per frame ``(F,)``: such a
        frame has several equilibria (docs/notes/arm3d.md#noticed-left-alone: several equilibria near full bend)."""
        return inverted_counts(_positions(x), self.mesh.cells)

    def min_volume_ratio(self, x: Tensor) -> np.ndarray:
        """Per frame ``(F,)``, the smallest volume of a tetrahedron relative to its rest
        volume (``<= 0``: inverted). A frame near a fold has one far below 1 before any
        tetrahedron inverts, so a change of material can fold it (see :meth:`inverted_tets`)."""
        return min_volume_ratios(_positions(x), self.mesh.points, self.mesh.cells)

    def metric_names(self) -> list[str]:
        return super().metric_names() + list(BODY_METRICS)

    def homogeneous_surface_error(self) -> float:
        """Mean surface error of the homogeneous material (any constant: scale-free)."""
        if not hasattr(self, "_homogeneous_error"):
            homogeneous = self.parameterization.constant(self.initial_value(self.cfg),
                                                         self.dtype, self.device)
            with torch.no_grad(), self.independent_simulation():
                x = self.simulate(self.field(homogeneous))
                self._homogeneous_error = float(self.surface_errors(x).mean())
        return self._homogeneous_error

    def metrics(self, theta: Tensor, x: Tensor | None = None) -> dict[str, float]:
        with torch.no_grad():
            if x is None:
                x = self.simulate(self.field(theta))
            out = super().metrics(theta, x)
            errors = self.surface_errors(x)
        out.update(body_metrics(errors, self.homogeneous_surface_error(),
                                self.joint_volume_change(x), self.inverted_tets(x),
                                self.full_bend_frame))
        return out

    def frame_errors(self, x: Tensor) -> dict[str, np.ndarray]:
        """Per frame: mean and max surface error (m), joint-region volume change."""
        with torch.no_grad():
            errors = self.surface_errors(x)
        return frame_report(errors, self.joint_volume_change(x), self.inverted_tets(x))

    def input_digests(self) -> dict[str, str]:
        """The tet mesh (vertices and cells: a cache entry rebuilt into another mesh is
        another mesh) and the animation's fitted surface (rest pose, faces, frames)."""
        a = self.animation
        return {"tet mesh": array_digest(self.mesh.points, self.mesh.cells),
                "animation": array_digest(a.rest_vertices, a.faces, a.frames)}

    def frame_names(self) -> list[str]:
        return list(self.animation.frame_files)

    def frame_numbers(self) -> list[int]:
        """The animation's frame number of every fitted frame (``problem.frames``)."""
        frames = self.cfg.frames if self.frame_split is None else self.frame_split.fitted
        return [int(f) for f in frames] if frames is not None else list(range(self.n_frames))

    def validation_problem(self) -> "RiggedBody | None":
        """The same body on its validation frames (:attr:`frame_split`), on the same mesh,
        with no validation of its own; ``None`` without validation frames."""
        split = self.frame_split
        if split is None:
            return None
        log.info("%s (the same body, rig and mesh: built quietly)", split.describe())
        with quiet():
            return self.on_frames(split.validation)

    def on_frames(self, numbers: list[int]) -> "RiggedBody":
        """The same body, rig and mesh on the animation frames ``numbers`` (a new problem
        built from this one's settings with ``frames=numbers`` and no validation; the tet
        mesh comes from this one's kept mesh or the cache, so the parameterisation is the
        same)."""
        return type(self)(self.settings_for_frames(numbers), kept_mesh=self.kept_mesh)

    def settings_for_frames(self, numbers: list[int]) -> RiggedBodyConfig:
        """This problem's config with ``frames=numbers`` and no validation (for
        :meth:`on_frames`)."""
        return dataclasses.replace(self.cfg, frames=[int(n) for n in numbers], **NO_VALIDATION)

    def with_frames(self, numbers: list[int]) -> "RiggedBody":
        """The same problem on some of its fitted frames (animation frame numbers, in the
        order given), with **its** targets there, noise included: a synthetic truth is
        simulated again on those frames, then the targets are replaced by this problem's
        rows of those frames, so the noise is the same draw, not a new one, and the noise
        level is this problem's for the subset's data count. Raises ``ValueError`` for a
        frame this problem does not fit."""
        mine = self.frame_numbers()
        unknown = [n for n in numbers if n not in mine]
        if not numbers or unknown:
            raise ValueError(f"frames {unknown or numbers} are not fitted frames of this "
                             f"problem ({mine})")
        sub = self.on_frames(numbers)
        if sub.tet.key != self.tet.key or sub.parameterization.n_params != \
                self.parameterization.n_params:
            raise RuntimeError("the problem on a subset of its frames got another tet mesh "
                               f"({sub.tet.key} against {self.tet.key}); check the mesh cache")
        rows = torch.as_tensor([mine.index(n) for n in numbers], device=self.data.device)
        data = self.data.reshape(self.n_frames, -1)[rows].reshape(-1).clone()
        level = None if self.noise_level is None else \
            self.noise_level * math.sqrt(data.numel() / self.data.numel())
        sub.adopt_targets(data, level)
        return sub

    def adopt_targets(self, data: Tensor, noise_level: float | None) -> None:
        """Fit ``data`` ``(m,)`` with noise level ``noise_level`` instead of the targets the
        settings gave (a subset of another problem's frames keeps its noise draw)."""
        if data.shape != self.data.shape:
            raise ValueError(f"targets of shape {tuple(data.shape)} for a problem of "
                             f"{tuple(self.data.shape)}")
        self.data, self.noise_level = data, noise_level

    def simulate_model(self, model: str, E: Tensor, frames: list[int] | None = None) -> Tensor:
        """Positions ``(len(frames), n_vertices, 3)`` of the same body, rig and field with
        another constitutive ``model`` (all frames by default), no gradient; the fit's own
        model returns the fit's simulation (:class:`.model_comparison.ModelComparison`)."""
        frames = list(range(self.n_frames)) if frames is None else list(frames)
        if model == self.cfg.model.value:
            with torch.no_grad():
                return self.simulate(E.detach())[frames]
        index = torch.as_tensor(frames, device=self.device)
        return self.comparison.simulate(model, E, self.dirichlet_positions[index],
                                        self.start_positions[index])

    def keep_mesh(self, run_dir: Path) -> Path | None:
        """The tetrahedral mesh into ``run_dir/mesh.npz`` (with the rest surface it was made
        of, the options, the regions and the grid's frame) so that a resume or ``simulate``
        needs no cache; an existing one is left as it is (a resume passed the checkpoint's
        mesh digest, so it is the same mesh). Returns the path written, or ``None``."""
        path = Path(run_dir) / RUN_MESH_FILE
        if path.exists() or path.is_symlink():
            return None
        a = self.animation
        return write_run_mesh(path, self.tet, self.tet_options, a.rest_vertices, a.faces,
                              self.tet_regions, (self.grid.origin, self.grid.axes))

    def region_summary(self, field: Tensor) -> dict[str, dict[str, float]]:
        """Mean, min, max and volume-weighted mean of ``field`` per region (all tetrahedra
        as one region ``body`` when there are no labels); with bounds, the tetrahedra and
        the parameters on each bound (:mod:`.bounds`)."""
        return region_report(field, self.mesh.signed_volumes(), self.tet_regions,
                             self.region_names, self.parameterization.basis,
                             modulus_bounds(self.cfg))

    def theta_bounds(self) -> tuple[Tensor, Tensor] | None:
        """``problem.E_min`` / ``E_max`` on ``theta`` (:mod:`.bounds`)."""
        return theta_bounds(self.cfg, self.parameterization.n_params, self.theta0)

    def bound_warning(self, at_lower: int, at_upper: int) -> str | None:
        """More than a tenth of the parameters on ``problem.E_min`` / ``E_max``
        (:func:`.bounds.bounds_warning`)."""
        return bounds_warning(self.cfg, self.parameterization.n_params, at_lower, at_upper)

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), **describe_body(self, modulus_bounds(self.cfg))}


class PoseEquilibrium(Protocol):
    """The warm starts of a pose simulation: cold blocks and the state a checkpoint keeps."""

    def independent(self) -> ContextManager[None]:
        ...

    def warm_start_state(self) -> dict[str, Any]:
        ...

    def restore_warm_start_state(self, state: dict[str, Any], device: Any = None) -> None:
        ...


class PoseSimulation(Protocol):
    """What a rigged body simulates its distinct poses with (:meth:`RiggedBody.plug`): a
    :class:`~torchfit.physics.elasticity.QuasistaticElasticity`, or a distributed run's
    split of it over ranks.

    ``simulation(E, positions, x_init)``: positions ``(P, n, 3)`` of the poses whose driven
    vertices are at ``positions`` ``(P, n_driven, 3)``, from ``x_init`` ``(P, n, 3)``;
    ``jacobian(...)``: ``(P, rows, k)`` derivatives of the observed rows along ``k`` field
    directions; ``equilibrium``: cold blocks (``independent()``) and the warm-start state a
    checkpoint saves and a resume restores.
    """

    equilibrium: PoseEquilibrium

    def __call__(self, E: Tensor, positions: Tensor, x_init: Tensor | None = None) -> Tensor:
        ...

    def jacobian(self, E: Tensor, positions: Tensor, directions: Tensor,
                 x_init: Tensor | None = None, observe: Tensor | None = None) -> Tensor:
        ...


def _positions(x: Tensor) -> np.ndarray:
    """Tetrahedron vertex positions ``(F, n, 3)`` as a NumPy array."""
    return x.detach().cpu().numpy()
