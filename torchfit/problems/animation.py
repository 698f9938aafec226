"""``animation``: fit the Young's modulus of a body to a rigged animation a user brings.

The data are a folder in the format of :mod:`torchfit.mesh.animation` (a manifest naming
the rest surface, the frames, and the skeleton or driven surface vertices that move the
body). The problem

1. tetrahedralises the rest surface with pytetwild (cached on disk by a hash of the surface
   and the options: the same input gives the same tetrahedra, hence the same fit);
2. embeds the user's surface vertices in the tetrahedra by barycentric weights, so targets,
   errors and exports live on the user's own vertices;
3. prescribes (Dirichlet) the tetrahedron vertices the rig drives: within
   ``attach_radius`` of a bone (moved by linear blend skinning), or within ``tolerance`` of
   the driven surface region (moved with it);
4. simulates every frame as an independent quasistatic equilibrium (linear, corotated or
   stable neo-Hookean elasticity) starting from the animated pose: tetrahedron vertices on
   the surface from the frame, interior ones from the rig;
5. observes the user's surface vertices (all of them; without the driven ones in the
   driven mode), in every frame.

Targets: ``target=rig``: the animated surface itself (no material reproduces it exactly;
the measure is how far fitting lowers the surface error below the homogeneous material's);
``target=synthetic``: the surface simulated from a known piecewise-constant field
(``truth=regions``: one value per region; ``truth=blocks``: blocks of grid nodes).

Parameters (``parameters=``): ``grid`` (default: Young's modulus on a coarse regular grid of
``grid`` nodes over the bounding box, trilinear to tetrahedra, with the grid's difference
operator for split Bregman), ``region`` (one value per region label) or ``tet`` (one per
tetrahedron). Every load is a prescribed displacement: scale-free (aligned errors).
"""
from __future__ import annotations

import dataclasses
import math
import os
import warnings
from pathlib import Path
from typing import Any, ContextManager, List, Optional

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from ..mesh import MeshError, SimplexMesh, element_adjacency, signed_volumes
from ..mesh.animation import Animation, AnimationError, load_animation
from ..mesh.embedding import Embedding, boundary_faces, embed_points
from ..mesh.rig import blend, distance_weights, segment_distances
from ..mesh.tetrahedralize import TetMesh, TetOptions, default_cache_dir, tetrahedralize
from ..params import Parameterization, per_element, per_grid_node, per_region
from ..physics import NewtonOptions
from ..physics.elasticity import QuasistaticElasticity, SimplicialElasticity, get_material
from ..settings import Choice
from .base import InverseProblem
from .config import (Backend, ProblemConfig, ProblemConfigError, check_newton_settings,
                     require_setting, resolve_backend, setting_error)


class ElasticModel(Choice):
    """Constitutive model of the body."""

    linear = "linear"
    corotated = "corotated"
    stable_neo_hookean = "stable_neo_hookean"


class Target(Choice):
    """``rig``: the animated surface; ``synthetic``: simulated from a known field."""

    rig = "rig"
    synthetic = "synthetic"


class Truth(Choice):
    """The known field of ``target=synthetic``."""

    regions = "regions"     # one value per region (E_regions)
    blocks = "blocks"       # blocks of grid nodes (E_blocks), trilinear between nodes


class Layout(Choice):
    """Where the fitted parameters live."""

    grid = "grid"           # nodes of a coarse regular grid, trilinear to tetrahedra
    region = "region"       # one per region label
    tet = "tet"             # one per tetrahedron


@dataclasses.dataclass
class AnimationConfig(ProblemConfig):
    """Settings of ``problem=animation`` (lengths in metres; ``noise`` in metres too)."""

    name: str = "animation"
    path: str = ""                         # folder holding animation.yaml
    frames: Optional[List[int]] = None     # a subset of the frames (numbers); null: all
    model: ElasticModel = ElasticModel.corotated   # linear | corotated | stable_neo_hookean
    nu: float = 0.45                       # Poisson ratio, fixed
    # rig (the animated surface) | synthetic (simulated from a known field)
    target: Target = Target.rig
    truth: Truth = Truth.blocks            # synthetic only: blocks | regions (needs labels)
    # truth=regions: one modulus per label (arm: bone, muscle, fat; the bone core is attached to
    # the rig, so its modulus is unobservable: it gets the muscle's value by default)
    E_regions: List[float] = dataclasses.field(default_factory=lambda: [4.0, 4.0, 1.0])
    # truth=blocks: background, stiff block, soft block
    E_blocks: List[float] = dataclasses.field(default_factory=lambda: [1.0, 4.0, 0.4])
    # grid (coarse nodes, trilinear) | region (one per label; needs labels) | tet
    parameters: Layout = Layout.grid
    grid: List[int] = dataclasses.field(default_factory=lambda: [4, 4, 12])   # nodes x, y, z
    E0: float = 1.0                        # initial guess, constant (the homogeneous material)
    # auto (pardiso where installed, else scipy) | pardiso | scipy | cg
    backend: Backend = Backend.auto
    # tetrahedralisation (pytetwild): target edge length as a fraction of the bounding-box
    # diagonal, envelope (fraction of the diagonal), quality (stop energy), optimisation
    tet_edge_length: float = 0.05
    tet_epsilon: float = 1e-3
    tet_stop_energy: float = 10.0
    tet_optimize: bool = True
    # tet meshes (and the arm's animation): "" is $TORCHFIT_CACHE_DIR or ~/.cache/torchfit
    cache_dir: str = ""
    newton_rtol: float = 1e-10
    newton_atol: float = 1e-12
    newton_max_iter: int = 300
    # Newton's start at a new parameter vector: an earlier solution (true; the solver's current
    # point where it is known) or the animated pose (false, the definition in PROBLEMS.md; see
    # docs/problems/arm3d.md, "Several equilibria near full bend", for when it matters)
    warm_start: bool = True


#: largest distance (fraction of the bounding-box diagonal) of a surface vertex outside the
#: tetrahedra before the tetrahedralisation is judged not to match the surface
MAX_OUTSIDE = 0.02


class AnimationProblem(InverseProblem):
    """Fit Young's modulus so that the simulated body follows a rigged animation."""

    config_class = AnimationConfig
    name = "animation"
    field_name = "E"
    initial_setting = "E0"
    dim = 3
    scale_free = True
    #: the problem wrote its animation folder itself (a run copies it as an example)
    writes_animation = False

    # -- hooks of the template --------------------------------------------------------
    def check(self, cfg: AnimationConfig) -> None:
        require_setting(-1.0 < cfg.nu < 0.5, cfg, "nu", "must lie in (-1, 0.5) (Poisson ratio "
                        "of an isotropic material; 0.5 would be incompressible)")
        require_setting(cfg.E0 > 0, cfg, "E0", "must be a positive Young's modulus")
        require_setting(len(cfg.grid) == 3 and all(int(n) >= 2 for n in cfg.grid), cfg, "grid",
                        "must list three node counts >= 2 (x, y, z)")
        for key in ("E_regions", "E_blocks"):
            values = getattr(cfg, key)
            require_setting(len(values) >= 1 and all(v > 0 for v in values), cfg, key,
                            "must list positive Young's moduli")
        require_setting(len(cfg.E_blocks) == 3, cfg, "E_blocks",
                        "must list three moduli: background, stiff block, soft block")
        for key in ("tet_edge_length", "tet_epsilon", "tet_stop_energy"):
            require_setting(getattr(cfg, key) > 0, cfg, key, "must be positive")
        check_newton_settings(cfg)
        require_setting(cfg.frames is None or len(cfg.frames) >= 1, cfg, "frames",
                        "must list at least one frame (or be null for all)")
        require_setting(cfg.backend != Backend.banded, cfg, "backend", "banded suits thin 2-D "
                        "sheets, not a 3-D body; use auto, pardiso, scipy or cg")
        self.check_source(cfg)

    def check_source(self, cfg: AnimationConfig) -> None:
        require_setting(bool(cfg.path), cfg, "path", "must name the folder of your animation "
                        "(holding animation.yaml; see README, 'Bring your own animation')")

    def load(self, cfg: AnimationConfig) -> Animation:
        """The animation (``problem=arm3d`` makes and writes its own first)."""
        try:
            return load_animation(cfg.path)
        except MeshError as err:
            raise ProblemConfigError(f"problem.path={cfg.path}: {err}") from err

    def build_model(self, cfg: AnimationConfig) -> None:
        animation = self.load(cfg)
        if cfg.frames is not None:
            try:
                animation = animation.select([int(f) for f in cfg.frames])
            except AnimationError as err:
                raise setting_error("frames", cfg.frames, str(err)) from err
        self.animation = animation
        for text in animation.warnings:
            warnings.warn(f"{animation.path}: rest surface: {text}", UserWarning, stacklevel=2)
        self.n_frames = animation.n_frames
        self.tet = self.tetrahedralize(cfg, animation)
        points, cells = self.tet.points, self.tet.cells
        self.mesh = SimplexMesh(points, cells)
        self.model = SimplicialElasticity(torch.from_numpy(points), torch.from_numpy(cells),
                                          cfg.model.value, nu=cfg.nu, dtype=self.dtype,
                                          device=self.device)
        diagonal = float(np.linalg.norm(points.max(0) - points.min(0)))
        try:
            self.embedding: Embedding = embed_points(animation.rest_vertices, points, cells,
                                                     max_distance=MAX_OUTSIDE * diagonal)
        except MeshError as err:
            raise ProblemConfigError(f"{animation.path}: {err}") from err
        if animation.skeleton is not None:
            dirichlet, positions, start = self._skeleton_drive(animation)
        else:
            dirichlet, positions, start = self._surface_drive(animation)
        self.dirichlet_vertices = dirichlet
        self.dirichlet_positions = torch.as_tensor(positions, dtype=self.dtype,
                                                   device=self.device)
        start[:, dirichlet] = positions
        self.start_positions = torch.as_tensor(start, dtype=self.dtype, device=self.device)
        # warm starts (the last solution, at the solver's next point) keep going rather than
        # fall back to the animated pose: near full bend that cold start needs far more
        # Newton iterations (folds and inverted elements at the inner elbow)
        newton = NewtonOptions(max_iter=cfg.newton_max_iter, rtol=cfg.newton_rtol,
                               atol=cfg.newton_atol, warm_max_iter=cfg.newton_max_iter)
        self.backend = resolve_backend(cfg.backend, self.device, 3)
        self.quasistatic = QuasistaticElasticity(self.model, dirichlet, backend=self.backend,
                                                 newton=newton, start="rest",
                                                 warm_start=cfg.warm_start)
        self.tet_regions, self.region_names = self.regions(cfg)
        self.joint_cells = self.joint_region(cfg)
        self.full_bend_frame = self.reference_frame()
        self._other_models: dict[str, QuasistaticElasticity] = {}

    def tetrahedralize(self, cfg: AnimationConfig, animation: Animation) -> TetMesh:
        options = TetOptions(edge_length_fac=cfg.tet_edge_length, epsilon=cfg.tet_epsilon,
                             stop_energy=cfg.tet_stop_energy, optimize=cfg.tet_optimize)
        cache = Path(cfg.cache_dir).expanduser() / "tetmesh" if cfg.cache_dir else \
            default_cache_dir()
        try:
            # the surface's warnings were given once above, with the animation's name
            return tetrahedralize(animation.rest_vertices, animation.faces, options,
                                  cache_dir=cache, warn=False)
        except MeshError as err:
            raise ProblemConfigError(f"{animation.path}: {err}") from err

    # -- what drives the body ---------------------------------------------------------
    def _surface_start(self, animation: Animation, points: np.ndarray) -> np.ndarray:
        """Positions ``(F, n, 3)`` of ``points`` moved with the displacement of the closest
        point of the rest surface (barycentric in its triangle)."""
        import trimesh

        surface = trimesh.Trimesh(animation.rest_vertices, animation.faces, process=False)
        closest, _, triangle = trimesh.proximity.closest_point(surface, points)
        corners = animation.rest_vertices[animation.faces[triangle]]          # (n, 3, 3)
        bary = trimesh.triangles.points_to_barycentric(corners, closest)       # (n, 3)
        displacement = animation.frames - animation.rest_vertices[None]       # (F, V, 3)
        moved = np.einsum("nk,fnkd->fnd", bary, displacement[:, animation.faces[triangle]])
        return points[None] + moved

    def _skeleton_drive(self, animation: Animation
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        skeleton = animation.skeleton
        points = self.tet.points
        distances = segment_distances(points, skeleton.heads, skeleton.tails)   # (n, B)
        attached = distances.min(axis=1) <= skeleton.attach_radius
        if not attached.any():
            raise ProblemConfigError(
                f"{animation.path}: no material point lies within attach_radius="
                f"{skeleton.attach_radius:.4g} m of any bone (nearest: "
                f"{distances.min():.4g} m); put the bones inside the body or raise "
                "skeleton.attach_radius")
        if attached.all():
            raise ProblemConfigError(
                f"{animation.path}: every material point lies within attach_radius="
                f"{skeleton.attach_radius:.4g} m of a bone, so nothing is left to simulate; "
                "lower skeleton.attach_radius")
        if skeleton.weights is not None:
            # weights given per rest-surface vertex: carried inward from the nearest one
            _, nearest = cKDTree(animation.rest_vertices).query(points)
            weights = skeleton.weights[nearest]
        else:
            weights = distance_weights(distances, skeleton.attach_radius)
        rigged = blend(points, weights, skeleton.transforms)                    # (F, n, 3)
        dirichlet = np.flatnonzero(attached)
        start = rigged.copy()
        boundary = np.unique(boundary_faces(self.tet.cells)[0])
        start[:, boundary] = self._surface_start(animation, points[boundary])
        return dirichlet, rigged[:, dirichlet], start

    def _surface_drive(self, animation: Animation
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        import trimesh

        driven = animation.driven
        points = self.tet.points
        faces = animation.faces
        full = driven.mask[faces].all(axis=1)
        if full.any():
            region = trimesh.Trimesh(animation.rest_vertices, faces[full], process=False)
            _, distance, _ = trimesh.proximity.closest_point(region, points)
        else:
            distance, _ = cKDTree(animation.rest_vertices[driven.mask]).query(points)
        near = distance <= driven.tolerance
        if not near.any():
            raise ProblemConfigError(
                f"{animation.path}: no tetrahedron vertex lies within driven.tolerance="
                f"{driven.tolerance:.4g} m of the driven surface (nearest: {distance.min():.4g} "
                "m); raise driven.tolerance")
        if near.all():
            raise ProblemConfigError(
                f"{animation.path}: every tetrahedron vertex lies within driven.tolerance of "
                "the driven surface, so nothing is left to simulate; lower driven.tolerance")
        start = self._surface_start(animation, points)
        dirichlet = np.flatnonzero(near)
        return dirichlet, start[:, dirichlet], start

    # -- regions and the joint ----------------------------------------------------------
    def regions(self, cfg: AnimationConfig) -> tuple[np.ndarray | None, list[str]]:
        """Region label per tetrahedron (carried inward from the nearest labelled surface
        vertex), or ``None`` when the animation has no labels."""
        labels = self.animation.region_labels
        if labels is None:
            return None, []
        _, nearest = cKDTree(self.animation.rest_vertices).query(self.mesh.centroids())
        return labels[nearest], list(self.animation.region_names)

    def joint_region(self, cfg: AnimationConfig) -> np.ndarray:
        """Tetrahedra whose volume change is reported: those within ``3 attach_radius`` of a
        joint of the skeleton (every tetrahedron without a skeleton or joint)."""
        skeleton = self.animation.skeleton
        centroids = self.mesh.centroids()
        if skeleton is None or not len(skeleton.joints()):
            return np.arange(len(centroids))
        joints = skeleton.joints()
        distance = np.linalg.norm(centroids[:, None, :] - joints[None], axis=-1).min(axis=1)
        cells = np.flatnonzero(distance <= 3.0 * skeleton.attach_radius)
        return cells if cells.size else np.arange(len(centroids))

    def reference_frame(self) -> int:
        """The frame of largest bone rotation (the full bend), 0 without a skeleton."""
        skeleton = self.animation.skeleton
        if skeleton is None:
            return 0
        A = skeleton.transforms[..., :3]
        cosine = np.clip((np.trace(A, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
        return int(np.argmax(np.arccos(cosine).max(axis=1)))

    # -- parameters, observation, truth ----------------------------------------------
    def build_parameterization(self, cfg: AnimationConfig) -> Parameterization:
        centroids = self.mesh.centroids()
        lower, upper = self.tet.points.min(0), self.tet.points.max(0)
        self.grid_shape = tuple(int(n) for n in cfg.grid)
        if cfg.parameters == Layout.grid:
            return per_grid_node(self.grid_shape, centroids, lower, upper,
                                 cfg.transform.value, name="Young's modulus", dtype=self.dtype)
        if cfg.parameters == Layout.region:
            if self.tet_regions is None:
                raise setting_error("parameters", cfg.parameters.value,
                                    "needs region labels: add a 'regions' entry to the "
                                    "animation's manifest (or use grid or tet)")
            return per_region(self.tet_regions, element_adjacency(self.mesh.cells),
                              cfg.transform.value, name="Young's modulus", dtype=self.dtype)
        return per_element(self.model.n_cells, element_adjacency(self.mesh.cells),
                           cfg.transform.value, name="Young's modulus", dtype=self.dtype)

    def build_observation(self, cfg: AnimationConfig) -> None:
        animation = self.animation
        if animation.driven is not None:
            observed = np.flatnonzero(~animation.driven.mask)
        else:
            observed = np.arange(animation.n_vertices)
        self.observed_vertices = torch.as_tensor(observed)
        self.observed_nodes = self.observed_vertices
        self._observed_weights = torch.as_tensor(self.embedding.weights[observed],
                                                 dtype=self.dtype, device=self.device)
        self._observed_corners = torch.as_tensor(self.embedding_cells()[observed],
                                                 device=self.device)

    def embedding_cells(self) -> np.ndarray:
        """Tetrahedron vertex indices ``(V_surface, 4)`` of each user surface vertex."""
        return self.mesh.cells[self.embedding.cells]

    def true_field(self, cfg: AnimationConfig) -> Tensor | None:
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
        return self.blocks_field(cfg)

    def block_nodes(self) -> np.ndarray:
        """Label per grid node of the ``blocks`` truth: 0 background, 1 stiff, 2 soft.

        In grid index space: the stiff block is the nodes with ``ix >= nx/2`` (the front
        half) and ``iz`` in the second quarter of the length; the soft block ``iy < ny/2``
        and ``iz`` in the third quarter. Both span several nodes in every direction.
        """
        nx, ny, nz = self.grid_shape
        ix, iy, iz = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
        labels = np.zeros((nx, ny, nz), dtype=np.int64)
        stiff = (ix >= nx // 2) & (iz >= nz // 4) & (iz < nz // 2)
        soft = (iy < ny // 2) & (iz >= nz // 2) & (iz < (3 * nz) // 4)
        labels[stiff] = 1
        labels[soft] = 2
        return labels.reshape(-1)

    def blocks_field(self, cfg: AnimationConfig) -> Tensor:
        """The ``blocks`` truth per tetrahedron: grid-node values, trilinear to tetrahedra."""
        grid = per_grid_node(self.grid_shape, self.mesh.centroids(), self.tet.points.min(0),
                             self.tet.points.max(0), "identity", dtype=self.dtype)
        values = torch.tensor(cfg.E_blocks, dtype=self.dtype)[torch.as_tensor(self.block_nodes())]
        return grid(values.to(self.device))

    def measured_data(self, cfg: AnimationConfig) -> Tensor:
        frames = torch.as_tensor(self.animation.frames, dtype=self.dtype, device=self.device)
        return frames[:, self.observed_vertices.to(self.device), :].reshape(-1)

    # -- the forward model --------------------------------------------------------------
    def simulate(self, E: Tensor) -> Tensor:
        """Tetrahedron vertex positions ``(F, n_vertices, 3)`` for ``E`` ``(n_tets,)``."""
        if E.shape != (self.model.n_cells,):
            raise ProblemConfigError(f"Young's modulus must have shape ({self.model.n_cells},) "
                                     f"(one per tetrahedron), got {tuple(E.shape)}")
        return self.quasistatic(E, self.dirichlet_positions.to(E),
                                x_init=self.start_positions.to(E))

    def independent_simulation(self) -> ContextManager[None]:
        """Cold starts from the animated pose that seed no warm start (the synthetic
        target, the homogeneous baseline): :meth:`Equilibrium.independent`."""
        return self.quasistatic.equilibrium.independent()

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
        """``d observe(simulate(map(theta))) / d theta`` ``(m, n_params)``: every parameter
        direction as a right-hand side of the one factorisation per frame."""
        E = self.parameterization(theta.detach())
        directions = self.parameterization.jacobian(theta.detach())          # (n_cells, n)
        # the embedding applied to each frame's columns as soon as they are solved: the
        # (F, V, 3, n) derivative of every vertex is never formed
        observed = self.quasistatic.jacobian(E, self.dirichlet_positions.to(E), directions,
                                             x_init=self.start_positions.to(E),
                                             observe=self._observation_matrix(E))
        return observed.reshape(-1, observed.shape[-1])                 # (F n_obs 3, n)

    def _observation_matrix(self, like: Tensor) -> Tensor:
        """The observed rows of the embedding on the flat dofs, sparse
        ``(n_obs 3, n_vertices 3)`` (rows and columns point-major, as ``observe``; cached)."""
        key = (like.dtype, like.device)
        if getattr(self, "_observation_key", None) != key:
            corners = self._observed_corners.cpu()                       # (n_obs, 4)
            n_obs, n_corners = corners.shape
            d = self.model.dim
            rows = (torch.arange(n_obs)[:, None, None] * d
                    + torch.arange(d)[None, None, :]).expand(n_obs, n_corners, d)
            cols = corners[:, :, None] * d + torch.arange(d)[None, None, :]
            values = self._observed_weights.cpu()[:, :, None].expand(n_obs, n_corners, d)
            self._observation = torch.sparse_coo_tensor(
                torch.stack([rows.reshape(-1), cols.reshape(-1)]), values.reshape(-1),
                (n_obs * d, self.model.n_vertices * d), check_invariants=False
            ).coalesce().to(like)
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
            return torch.linalg.vector_norm(self.surface(x) - self.clean_surface(), dim=-1)

    def surface_errors(self, x: Tensor) -> Tensor:
        """Distance of every observed surface vertex to its noise-free target ``(F, n_obs)``."""
        sim = self.observe(x).reshape(self.n_frames, -1, 3)
        return torch.linalg.vector_norm(sim - self.clean_targets(), dim=-1)

    def joint_volume_change(self, x: Tensor) -> np.ndarray:
        """Relative volume change of the joint region per frame ``(F,)`` (``V / V_rest - 1``)."""
        cells = self.mesh.cells[self.joint_cells]
        rest = float(signed_volumes(self.mesh.points, cells).sum())
        return _frame_volumes(x, cells).sum(axis=1) / rest - 1.0

    def inverted_tets(self, x: Tensor) -> np.ndarray:
        """Tetrahedra turned inside out (signed volume <= 0) per frame ``(F,)``.

        Where a frame's equilibrium has inverted tetrahedra (the inner elbow folding at full
        bend), Newton can reach several equilibria depending on where it starts, so that
        frame's simulation is not a unique function of the material: see
        docs/problems/arm3d.md, "Several equilibria near full bend".
        """
        return (_frame_volumes(x, self.mesh.cells) <= 0).sum(axis=1)

    def min_volume_ratio(self, x: Tensor) -> np.ndarray:
        """Per frame ``(F,)``, the smallest volume of a tetrahedron relative to its rest
        volume (``<= 0``: inverted). A frame near a fold has one far below 1 before any
        tetrahedron inverts, so a change of material can fold it (see :meth:`inverted_tets`)."""
        rest = signed_volumes(self.mesh.points, self.mesh.cells)
        return (_frame_volumes(x, self.mesh.cells) / rest[None]).min(axis=1)

    def metric_names(self) -> list[str]:
        return super().metric_names() + ["surface_err_mean", "surface_err_max",
                                         "surface_err_reduction", "joint_volume_change",
                                         "inverted_tets"]

    def homogeneous_surface_error(self) -> float:
        """Mean surface error of the homogeneous material (any constant: scale-free)."""
        if not hasattr(self, "_homogeneous_error"):
            with torch.no_grad(), self.independent_simulation():
                x = self.simulate(self.field(self.theta0))
                self._homogeneous_error = float(self.surface_errors(x).mean())
        return self._homogeneous_error

    def metrics(self, theta: Tensor, x: Tensor | None = None) -> dict[str, float]:
        with torch.no_grad():
            if x is None:
                x = self.simulate(self.field(theta))
            out = super().metrics(theta, x)
            errors = self.surface_errors(x)
        out["surface_err_mean"] = float(errors.mean())
        out["surface_err_max"] = float(errors.max())
        mean = out["surface_err_mean"]
        out["surface_err_reduction"] = self.homogeneous_surface_error() / mean if mean > 0 \
            else math.inf
        out["joint_volume_change"] = float(self.joint_volume_change(x)[self.full_bend_frame])
        out["inverted_tets"] = float(self.inverted_tets(x).max())
        return out

    def frame_errors(self, x: Tensor) -> dict[str, np.ndarray]:
        """Per frame: mean and max surface error (m), joint-region volume change."""
        with torch.no_grad():
            errors = self.surface_errors(x)
        return {"surface_err_mean": errors.mean(dim=1).cpu().numpy(),
                "surface_err_max": errors.amax(dim=1).cpu().numpy(),
                "joint_volume_change": self.joint_volume_change(x),
                "inverted_tets": self.inverted_tets(x)}

    def frame_names(self) -> list[str]:
        return list(self.animation.frame_files)

    def frame_numbers(self) -> list[int]:
        """The animation's frame number of every fitted frame (``problem.frames``)."""
        frames = self.cfg.frames
        return [int(f) for f in frames] if frames is not None else list(range(self.n_frames))

    def with_frames(self, numbers: list[int]) -> "AnimationProblem":
        """The same problem on some of its fitted frames (animation frame numbers, in the
        order given), with **this** problem's targets on them, noise included.

        Built again from the settings with ``frames=numbers``: the tet mesh and the
        animation come from their caches (the same mesh, so the same parameterisation);
        a synthetic truth is simulated again on those frames (cold, as here). The targets
        are then replaced by this problem's rows of those frames, so the noise is the same
        draw, not a new one, and the noise level ``delta`` is this one's for the subset's
        data count. Raises ``ValueError`` for a frame this problem does not fit.
        """
        mine = self.frame_numbers()
        unknown = [n for n in numbers if n not in mine]
        if not numbers or unknown:
            raise ValueError(f"frames {unknown or numbers} are not fitted frames of this "
                             f"problem ({mine})")
        sub = type(self)(self.settings_for_frames([int(n) for n in numbers]))
        if sub.tet.key != self.tet.key or sub.parameterization.n_params != \
                self.parameterization.n_params:
            raise RuntimeError("the problem on a subset of its frames got another tet mesh "
                               f"({sub.tet.key} against {self.tet.key}); check the mesh cache")
        rows = torch.as_tensor([mine.index(n) for n in numbers], device=self.data.device)
        sub.data = self.data.reshape(self.n_frames, -1)[rows].reshape(-1).clone()
        if self.noise_level is not None:
            sub.noise_level = self.noise_level * math.sqrt(sub.data.numel() / self.data.numel())
        return sub

    def settings_for_frames(self, numbers: list[int]) -> AnimationConfig:
        """This problem's config with ``frames=numbers`` (for :meth:`with_frames`)."""
        return dataclasses.replace(self.cfg, frames=list(numbers))

    def simulate_model(self, model: str, E: Tensor, frames: list[int] | None = None) -> Tensor:
        """Positions ``(len(frames), n_vertices, 3)`` of the same body, rig and field with
        another constitutive ``model`` (for the model comparison), no gradient."""
        frames = list(range(self.n_frames)) if frames is None else list(frames)
        if model == self.cfg.model.value:
            with torch.no_grad():
                return self.simulate(E.detach())[frames]   # the fit's own model: its state
        if model not in self._other_models:
            other = SimplicialElasticity(torch.from_numpy(self.mesh.points),
                                         torch.from_numpy(self.mesh.cells), model, nu=self.cfg.nu,
                                         dtype=self.dtype, device=self.device)
            newton = NewtonOptions(max_iter=self.cfg.newton_max_iter, rtol=self.cfg.newton_rtol,
                                   atol=self.cfg.newton_atol)
            self._other_models[model] = QuasistaticElasticity(
                other, self.dirichlet_vertices, backend=self.backend, newton=newton, start="rest")
        index = torch.as_tensor(frames, device=self.device)
        with torch.no_grad():
            return self._other_models[model](E.detach(), self.dirichlet_positions[index].to(E),
                                             x_init=self.start_positions[index].to(E))

    def region_summary(self, field: Tensor) -> dict[str, dict[str, float]]:
        """Mean, min, max and volume-weighted mean of ``field`` per region (all tetrahedra
        as one region ``body`` when there are no labels)."""
        values = field.detach().cpu().numpy()
        volumes = self.mesh.signed_volumes()
        labels = self.tet_regions if self.tet_regions is not None else \
            np.zeros(len(values), dtype=np.int64)
        names = self.region_names or ["body"]
        out = {}
        for r, name in enumerate(names):
            mask = labels == r
            if not mask.any():
                continue
            out[name] = {"tets": int(mask.sum()), "volume": float(volumes[mask].sum()),
                         "mean": float(values[mask].mean()), "min": float(values[mask].min()),
                         "max": float(values[mask].max()),
                         "volume_mean": float((values[mask] * volumes[mask]).sum()
                                              / volumes[mask].sum())}
        return out

    def describe(self) -> dict[str, Any]:
        out = super().describe()
        out.update({"model": get_material(self.cfg.model.value).name, "nu": self.model.nu,
                    "animation": str(self.animation.path), "n_frames": self.n_frames,
                    "n_tets": self.model.n_cells, "n_vertices": self.model.n_vertices,
                    "n_surface_vertices": self.animation.n_vertices,
                    "n_dirichlet": int(len(self.dirichlet_vertices)),
                    "n_free_dofs": 3 * (self.model.n_vertices - len(self.dirichlet_vertices)),
                    "tet_cache_hit": bool(self.tet.from_cache), "tet_key": self.tet.key,
                    "tetrahedralize_s": float(self.tet.build_seconds),
                    "backend": self.backend, "full_bend_frame": self.full_bend_frame,
                    "joint_tets": int(len(self.joint_cells)),
                    "surface_err_mean_homogeneous": self.homogeneous_surface_error()})
        if os.environ.get("TORCHFIT_CACHE_DIR"):
            out["cache_dir"] = os.environ["TORCHFIT_CACHE_DIR"]
        return out


def _frame_volumes(x: Tensor, cells: np.ndarray) -> np.ndarray:
    """Signed volumes ``(F, len(cells))`` of ``cells`` at positions ``x`` ``(F, n, 3)``
    (frame by frame: the corner array of 48 frames of 10k tetrahedra would be 110 MB)."""
    positions = x.detach().cpu().numpy()
    return np.stack([signed_volumes(frame, cells) for frame in positions])
