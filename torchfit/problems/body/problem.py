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

The body is its template hooks and the collaborators it owns: :attr:`RiggedBody.poses`, its
simulation (:class:`~.poses.FramePoses`, the equilibrium per frame, or with
``problem.dynamic=true`` :class:`~.dynamic.BodyInTime`, the implicit integrator through the
shot, which is then also its :attr:`~torchfit.problems.base.InverseProblem.time`: pascals,
damping, a later validation window); :attr:`RiggedBody.observation`, what it observes
(:class:`~.observation.SurfaceObservation`); :attr:`RiggedBody.comparison`, the model
comparison. One class serves both: the body in time is another simulation, not another
class.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import os
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from ...memory import check_allocation
from ...mesh import MeshError, SimplexMesh, element_adjacency
from ...mesh import (Animation, AnimationError, Embedding, KeptMesh, body_volume, embed_points,
                     joint_cells, read_animation, skeleton_drive, surface_drive)
from ...params import Parameterization, per_element, per_region
from ...physics import NewtonConvergenceError, NewtonOptions
from ...physics.contact import ContactInputError, ElasticityWithContact
from ...physics.dynamics import UnstableStepError
from ...physics.elasticity import QuasistaticElasticity, SimplicialElasticity
from ...steps import count, quiet, step
from ..base import InverseProblem, array_digest
from ..protocols import BodySimulation, WarmStarts
from .grid import blocks_field, body_grid, grid_parameterization
from .motion import most_deformed_frame, most_strained_cells, picture_up, view_axes
from .setup import (animation_summary, check_rig, check_tet_settings, report_rig, tet_mesh,
                    tet_options)
from .report import (BODY_METRICS, body_metrics, describe_body, frame_report,
                     inverted_counts, min_volume_ratios, volume_change)
from ..config import (Backend, ProblemConfigError, check_newton_settings,
                      make_config, require_setting, resolve_backend, setting_error)
from .dynamic import BodyInTime, check_body_dynamics, dynamic_split, in_pascals
from .energy import body_energy, check_contact_settings
from .held_out import NO_VALIDATION, FrameSplit, split_frames
from .model_comparison import ModelComparison
from .bounds import (bounds_warning, check_bounds, damping_theta_bounds, modulus_bounds,
                     region_report, theta_bounds)
from .observation import SurfaceObservation
from .poses import FramePoses
from .repeated_poses import distinct_poses
from .reporter import BodyReport
from .init_field import initial_field_theta
from .config import Layout, ModulusUnit, RiggedBodyConfig, Target, Truth


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
    """Fit Young's modulus so that the simulated body follows a rigged animation, frame by
    frame or through time (``problem.dynamic``; module docstring)."""

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
    #: the error after the best scale is reported in time too (inertia fixes the scale weakly)
    aligned_error = True
    #: what the run reports of a body besides the generic metrics (docs/problems.md)
    extra_metric_names = tuple(BODY_METRICS)

    #: the body's simulation: the equilibrium per frame or the integration through time
    poses: FramePoses | BodyInTime
    #: what it observes: the user's surface vertices in the tetrahedra
    observation: SurfaceObservation

    def __init__(self, cfg: Any = None, *, kept_mesh: KeptMesh | None = None,
                 **overrides: Any) -> None:
        #: the run's own tetrahedral mesh (a resume, ``simulate``), used before the cache
        self.kept_mesh = kept_mesh
        config = make_config(self.config_class, cfg, overrides)
        #: a material layer that states no unit is read in the units of the modulus settings
        #: (pascals in time: ``E_reference`` for relative settings); ``None``: scale-free
        self.unitless_layer_factor: float | None = None
        if config.dynamic:     # inertia fixes the scale: every modulus in pascals
            self.unitless_layer_factor = float(config.E_reference) \
                if config.E0_unit == ModulusUnit.relative else 1.0
            config = in_pascals(config)
            self.scale_free = False
        super().__init__(config)

    # -- hooks of the template --------------------------------------------------------
    def check(self, cfg: RiggedBodyConfig) -> None:
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
        check_contact_settings(cfg)
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
        if cfg.dynamic:
            check_body_dynamics(cfg)

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
            elif message.startswith(f"{where}:"):           # ... on a prim or node of it
                message = message[len(str(where)) + 1:]
            raise ProblemConfigError(f"problem.path={where}: {message}") from err

    def build_model(self, cfg: RiggedBodyConfig) -> None:
        with step(f"reading the animation {cfg.path or self.name}") as progress:
            animation = self.load(cfg)
            # every frame's motion (not the fitted subset's) settles the frame of a round body
            self.motion = animation.frames - animation.rest_vertices
            self.frame_split = dynamic_split(cfg, animation.n_frames) if cfg.dynamic else \
                split_frames(cfg, animation.rest_vertices, animation.frames)
            fitted = cfg.frames if self.frame_split is None else self.frame_split.fitted
            in_file, whole = animation.n_frames, animation
            if fitted is not None:
                try:
                    animation = animation.select([int(f) for f in fitted])
                except AnimationError as err:
                    raise setting_error("frames", cfg.frames, str(err)) from err
            progress.result = animation_summary(animation, in_file)
        self.rig_report = check_rig(cfg, animation)
        # the frames the rig drives: the fitted ones (each an independent equilibrium); in
        # time every frame of the shot (the rig's motion is input, known to the end: the
        # spline through all of it makes the motion at a time the same whichever frames are
        # fitted; the integration stops at the last output frame)
        rigged = whole if cfg.dynamic else animation
        self.animation = animation
        for text in animation.warnings:
            log.warning(f"{animation.path}: rest surface: {text}")
        self.n_frames = animation.n_frames
        if self.kept_mesh is None:     # the count an edge length implies, before fTetWild
            check_tet_count(*edge_count(cfg, animation))
        # the rest surface's tet mesh, built in the body's frame (the same tetrahedra for a
        # rotated body; setup.tet_mesh); a run's own mesh (mesh.npz) first
        self.tet_options = tet_options(cfg)
        self.tet = tet_mesh(cfg, animation, self.motion, self.kept_mesh)
        # per frame: each tetrahedron's F, stress, derivatives (40 values), vertex (9 values)
        cells, points = len(self.tet.cells), len(self.tet.points)
        check_allocation(f"problem.tet_edge_length={cfg.tet_edge_length} with "
                         f"{animation.n_frames} frames", body_bytes(cells, points,
                                                                    animation.n_frames),
                         f"{cells} tetrahedra x {animation.n_frames} frames", ProblemConfigError)
        points, cells = self.tet.points, self.tet.cells
        self.mesh = SimplexMesh(points, cells)
        # the energy every simulation of the body sees (energy.py: where a term joins)
        self.model = body_energy(points, cells, cfg.model.value, cfg.nu, self.dtype, self.device,
                                 contact_dhat=cfg.contact_dhat if cfg.contact else None,
                                 modulus=cfg.E0)
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
        # the attached rig, printed once; the run writes it as rig.json (None: driven vertices)
        self.rig_description = None if rigged.skeleton is None else report_rig(rigged.skeleton, drive)
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
        # warm starts (the last solution, at the solver's next point) keep going rather than
        # fall back to the animated pose: near full bend that cold start needs far more
        # Newton iterations (folds and inverted elements at the inner elbow)
        newton = NewtonOptions(max_iter=cfg.newton_max_iter, rtol=cfg.newton_rtol,
                               atol=cfg.newton_atol, warm_max_iter=cfg.newton_max_iter)
        self.backend = resolve_backend(cfg.backend, self.device, 3)
        if isinstance(self.model, ElasticityWithContact):
            self.start_positions = contact_starts(self.model, cfg, dirichlet,
                                                  self.start_positions, self.frame_numbers(),
                                                  self.backend, newton)
        quasistatic = QuasistaticElasticity(self.model, dirichlet, backend=self.backend,
                                            newton=newton, start="rest", warm_start=cfg.warm_start)
        # frames repeating a pose share one simulation (repeated_poses.py); a pose met again
        # in time is another state (velocity): no frame is shared there
        self.poses = FramePoses(quasistatic, self.dirichlet_positions, self.start_positions,
                                None if cfg.dynamic else distinct_poses(self.dirichlet_positions),
                                cfg.model.value, self.model.n_cells)
        self.comparison = ModelComparison(self.mesh, dirichlet, self.backend, cfg, self.dtype,
                                          self.device, self.dirichlet_positions,
                                          self.start_positions, self.simulate)
        self.tet_regions, self.region_names = self.regions(cfg)
        self.full_bend_frame = self.reference_frame()
        kept_frame = None if self.kept_mesh is None else self.kept_mesh.frame_for(
            animation.rest_vertices, animation.faces, self.tet_options,
            self.tet.canonical)                                   # a run's own (any file)
        self.grid = body_grid(points, cells, self.motion, cfg.grid_nodes, cfg.grid, kept_frame)
        self.grid_shape = self.grid.shape
        up, source = picture_up(animation.up, animation.skeleton, self.grid.axes[2])
        log.info("pictures: up (%s), %s", ", ".join(f"{c:.3g}" for c in up), source)
        self.view_axes = view_axes(animation.rest_vertices, animation.frames, up)
        self.joint_cells = self.joint_region(cfg)
        if cfg.dynamic:
            self.poses = self.time = BodyInTime.build(
                cfg, self.model, self.mesh, self.dirichlet_vertices, self.dirichlet_positions,
                self.start_positions, self.frame_numbers(), self.animation.fps, self.backend,
                lambda: initial_pose(cfg, self.model, self.dirichlet_vertices,
                                     self.dirichlet_positions[0], self.start_positions[0],
                                     quasistatic))
            self.output_times, self.integrator = self.time.output_times, self.time.integrator
        self.warm_starts = self.poses.warm_starts

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
        self.observation = SurfaceObservation(self.animation, self.embedding, self.mesh.cells,
                                              self.model.n_vertices, self.dtype, self.device)
        self.observed_vertices = self.observation.vertices
        self.observed_nodes = self.observed_vertices
        parameters = self.parameterization.field_parameterization if cfg.dynamic else \
            self.parameterization
        self.report = BodyReport(self.mesh, self.joint_cells, self.tet_regions, self.region_names,
                                 parameters.basis, self.parameterization.n_params, cfg,
                                 lambda: homogeneous_surface_error(self))

    def start_settings(self) -> list[str]:
        return [f"problem.{self.initial_setting}", "problem.init_field",
                *self.time.start_settings()]

    def initial_parameters(self, cfg: RiggedBodyConfig) -> Tensor:
        """The constant ``E0``, or the field of ``problem.init_field`` projected on the
        parameters (:func:`.init_field.initial_field_theta`; in time in pascals, the layer's
        stated unit, else that of the modulus settings), the damping at ``alpha0``, ``beta0``."""
        if not cfg.init_field:
            return super().initial_parameters(cfg)
        return initial_field_theta(self, cfg, self.unitless_layer_factor)

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
        return self.observation.measured()

    def unsimulated_truth(self, error: Any) -> ProblemConfigError:
        """A time step the integrator cannot take while simulating the synthetic truth is
        bad input naming ``problem.substeps`` and the true material (at the fit's start the
        solver refuses it likewise)."""
        if not isinstance(error, UnstableStepError):
            return super().unsimulated_truth(error)
        return setting_error("substeps", self.cfg.substeps, "the body cannot be integrated "
                             f"with the synthetic target's true material "
                             f"({', '.join(self.truth_settings())}): {error}")

    # -- the forward model --------------------------------------------------------------
    def simulate(self, physical: Tensor) -> Tensor:
        """Tetrahedron vertex positions ``(F, n_vertices, 3)`` of the fitted frames for ``E``
        ``(n_tets,)`` (in time ``[E, alpha, beta(, density scale)]``): :attr:`poses`."""
        return self.poses.simulate(physical)

    def simulation_accuracy(self) -> float | None:
        """Newton's relative tolerance: 48 nonlinear frames are solved to it, not to round-off."""
        return max(float(self.cfg.newton_rtol), torch.finfo(self.dtype).eps)

    def observe(self, x: Tensor) -> Tensor:
        """The observed surface vertices of every frame, frame-major ``(F * n_obs * 3,)``."""
        return self.observation(x)

    def forward_jacobian(self, theta: Tensor) -> Tensor:
        """``d observe(simulate(map(theta))) / d theta`` ``(m, n_params)``: every frame's
        observed rows, from :attr:`poses` (one factorisation per pose, or tangents forward
        through time)."""
        return self.poses.jacobian(theta, self.parameterization, self.observation.matrix)

    # -- what the metrics and outputs report ---------------------------------------------
    def metrics(self, theta: Tensor, x: Tensor | None = None) -> dict[str, float]:
        with torch.no_grad():
            if x is None:
                x = self.simulate(self.simulation_input(theta))
            out = super().metrics(theta, x)
            errors = self.observation.surface_errors(x, self.x_true)
        out.update(body_metrics(errors, self.report.homogeneous_error(),
                                self.report.joint_volume_change(x), self.report.inverted_tets(x),
                                self.full_bend_frame))
        return out

    def frame_errors(self, x: Tensor) -> dict[str, np.ndarray]:
        """Per frame: mean and max surface error (m), joint-region volume change; in time
        with a synthetic truth also the position errors of every output time (``u_err_inf``,
        ``u_err_2``: the motion pictures')."""
        with torch.no_grad():
            errors = self.observation.surface_errors(x, self.x_true)
        out = frame_report(errors, self.report.joint_volume_change(x),
                           self.report.inverted_tets(x))
        if self.time.in_time and self.x_true is not None:
            out.update(self.poses.frame_errors(x, self.x_true))
        return out

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
            return on_frames(self, split.validation)

    def settings_for_frames(self, numbers: list[int]) -> RiggedBodyConfig:
        """This problem's config with ``frames=numbers`` and no validation (for
        :func:`on_frames`)."""
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
        sub = on_frames(self, numbers)
        if sub.tet.key != self.tet.key or sub.parameterization.n_params != \
                self.parameterization.n_params:
            raise RuntimeError("the problem on a subset of its frames got another tet mesh "
                               f"({sub.tet.key} against {self.tet.key}); check the mesh cache")
        rows = torch.as_tensor([mine.index(n) for n in numbers], device=self.data.device)
        data = self.data.reshape(self.n_frames, -1)[rows].reshape(-1).clone()
        level = None if self.noise_level is None else \
            self.noise_level * math.sqrt(data.numel() / self.data.numel())
        if data.shape != sub.data.shape:
            raise ValueError(f"targets of shape {tuple(data.shape)} for a problem of "
                             f"{tuple(sub.data.shape)}")
        # fit this problem's targets there (a subset of its frames keeps its noise draw)
        sub.data, sub.noise_level = data, level
        return sub

    def theta_bounds(self) -> tuple[Tensor, Tensor] | None:
        """``problem.E_min`` / ``E_max`` on the field's ``theta`` (:mod:`.bounds`); the
        damping in time at most its band's bounds (:func:`.bounds.damping_theta_bounds`)."""
        scalars = self.parameterization.n_scalars if self.time.in_time else 0
        bounds = theta_bounds(self.cfg, self.parameterization.n_params - scalars, self.theta0)
        if bounds is None or not scalars:
            return bounds
        tail = damping_theta_bounds(self.cfg, self.time.band, scalars, self.theta0)
        return torch.cat([bounds[0], tail[0]]), torch.cat([bounds[1], tail[1]])

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), **describe_body(self, modulus_bounds(self.cfg))}


def on_frames(body: RiggedBody, numbers: list[int]) -> RiggedBody:
    """The same body, rig and mesh on the animation frames ``numbers`` (a new body of
    ``body``'s class built from its :meth:`~RiggedBody.settings_for_frames`: ``frames=numbers``
    and no validation; the tet mesh comes from ``body``'s kept mesh or the cache, so the
    parameterisation is the same)."""
    return type(body)(body.settings_for_frames(numbers), kept_mesh=body.kept_mesh)


def homogeneous_surface_error(body: RiggedBody) -> float:
    """Mean surface error of ``body`` with the homogeneous material (any constant:
    scale-free; in time ``E0`` with the starting damping, NaN where it cannot be integrated:
    the fit's start refuses it in one line), simulated cold (:attr:`RiggedBody.report`'s
    baseline, computed once)."""
    homogeneous = body.parameterization.constant(float(getattr(body.cfg, body.initial_setting)),
                                                 body.dtype, body.device)
    try:
        with torch.no_grad(), body.warm_starts.independent():
            x = body.simulate(body.simulation_input(homogeneous))
            return float(body.observation.surface_errors(x, body.x_true).mean())
    except UnstableStepError:
        return math.nan


def initial_pose(cfg: RiggedBodyConfig, model: SimplicialElasticity, driven: Any,
                 drive0: Tensor, skinned0: Tensor, quasistatic: QuasistaticElasticity) -> Tensor:
    """Positions ``(n, 3)`` of the body in time at ``t = 0``: the rest shape where frame 0
    drives the rig (``drive0`` ``(n_driven, 3)`` of the vertices ``driven``) to its rest
    positions, else frame 0's equilibrium for the homogeneous ``E0`` from its skinned pose
    ``skinned0`` ``(n, 3)``."""
    rest = model.rest.points.to(drive0.dtype)
    at_rest = rest[torch.as_tensor(driven, device=drive0.device)]
    scale = float((rest.max(0).values - rest.min(0).values).norm())
    if float((drive0 - at_rest).abs().max()) <= 1e-12 * scale:
        return rest.clone()
    E0 = torch.full((model.n_cells,), float(cfg.E0), dtype=drive0.dtype, device=drive0.device)
    with torch.no_grad(), quasistatic.equilibrium.independent():
        return quasistatic(E0, drive0[None], x_init=skinned0[None])[0]


def contact_starts(model: ElasticityWithContact, cfg: RiggedBodyConfig, dirichlet: Any,
                   start: Tensor, frame_numbers: list[int], backend: Any,
                   newton: NewtonOptions) -> Tensor:
    """Newton's starts ``(F, n, 3)`` without intersections for a body with contact: the
    skinned pose where it is free, else the rest shape with the driven vertices moved and
    carried towards it by CCD, else the equilibrium for ``E0`` reached by adding the
    animated motion from the nearest frame whose start is free in substeps
    (:meth:`~torchfit.physics.contact.ElasticityWithContact.stepped_start`). A frame with
    none of these is one :class:`ProblemConfigError` line naming it."""
    shape = start.shape
    vertices = torch.as_tensor(np.asarray(dirichlet))
    fixed = (vertices[:, None] * 3 + torch.arange(3)).reshape(-1)
    flat = start.reshape(shape[0], -1)
    starts, stuck = model.collision_free_start(flat, fixed)
    if not stuck:
        return starts.reshape(shape)
    free = [f for f in range(shape[0]) if f not in stuck]
    solver = QuasistaticElasticity(model, vertices, backend=backend, newton=newton,
                                   start="rest", warm_start=False)
    E0 = torch.full((model.n_cells,), float(cfg.E0), dtype=flat.dtype, device=flat.device)

    def solve(x: Tensor) -> Tensor:
        positions = x.reshape(1, -1, 3)[:, vertices.to(x.device)]
        return solver(E0, positions, x_init=x.reshape(1, -1, 3)).reshape(1, -1)

    try:
        if not free:
            raise ContactInputError("no frame's animated pose is free of intersections")
        for f in stuck:
            g = min(free, key=lambda k: abs(k - f))
            state = solve(starts[g:g + 1])
            starts[f] = model.stepped_start(solve, state, flat[g:g + 1], flat[f:f + 1],
                                              fixed)[0]
    except (ContactInputError, NewtonConvergenceError) as error:
        names = ", ".join(str(frame_numbers[f]) for f in stuck)
        raise ProblemConfigError(
            f"frame(s) {names}: Newton's start (the animated pose) passes through itself at a "
            f"fold and no start without intersections was found ({str(error).split(';')[0]}); "
            "leave those frames out (problem.frames) or set problem.contact=false") from None
    return starts.reshape(shape)
