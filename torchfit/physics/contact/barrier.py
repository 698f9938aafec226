"""The IPC self-contact barrier of a tetrahedral body's boundary surface, through ipctk.

:class:`SelfContact` is the incremental potential contact term (Li et al. 2020) on the
boundary triangles of the simulation's tetrahedra: for positions ``x`` ``(F, n_vertices * 3)``
(vertex-major dofs, the elastic model's) it gives per frame the barrier energy
``kappa * sum_k b(d_k; dhat)`` over the surface's primitive pairs closer than ``dhat``, its
gradient ``(F, n_dofs)`` and its Hessian (exact, or projected to PSD per pair as IPC's Newton
does), and the largest step along ``x0 -> x1`` that is free of collisions (continuous
collision detection). Everything (candidates, distances, barrier and its derivatives, CCD) is
ipctk's; this module only maps the surface's vertices to the body's dofs.

Why the tetrahedral boundary rather than the embedded render surface: the barrier's forces
must act on the unknowns, and the boundary's vertices *are* mesh nodes (no mapping to carry
into the Hessian), while an embedded surface's vertices move by interpolation inside cells,
so a render surface that is coarser or finer than the cells could pass through itself
between the tet boundary's contacts; the render surface follows the tet boundary to within
the embedding's distance (a small fraction of ``dhat`` at the default mesh sizes).

The barrier depends on positions only: ``kappa`` and ``dhat`` are constants of the term
while a solve runs (no parameter derivative; the adjoint and the tangents see contact only
through the tangent stiffness).
"""
from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
import torch
from torch import Tensor

from ...mesh import boundary_faces


class ContactInputError(ValueError):
    """A contact setting out of range or a rest shape that already passes through itself."""


def _ipctk():
    import ipctk  # imported here: only bodies with contact need the IPC Toolkit
    return ipctk


def surface_edges(faces: np.ndarray) -> np.ndarray:
    """The distinct edges ``(m, 2)`` int32 of triangles ``faces`` ``(k, 3)``."""
    pairs = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(pairs, axis=0).astype(np.int32)


class SelfContact:
    """IPC self-contact of the boundary surface of tetrahedra ``cells`` at rest ``points``.

    Args:
        points: ``(n_vertices, 3)`` rest positions (metres).
        cells: ``(n_tets, 4)`` positively oriented tetrahedra.
        dhat_fraction: the barrier's activation distance as a fraction of the rest bounding
            box's diagonal, in ``(0, 0.1]``.
        stiffness: the barrier stiffness ``kappa`` (J per unit barrier); set it from the
            problem's scale with :meth:`initial_stiffness`.

    Raises :class:`ContactInputError` for ``dhat_fraction`` out of range and for a rest
    shape whose surface intersects itself (naming a vertex near the intersection).
    """

    def __init__(self, points: np.ndarray, cells: np.ndarray, dhat_fraction: float = 1e-3,
                 stiffness: float = 1.0) -> None:
        ipctk = _ipctk()
        if not (0.0 < float(dhat_fraction) <= 0.1):
            raise ContactInputError(
                f"problem.contact_dhat = {dhat_fraction:g} is out of range: the contact "
                "distance is a fraction of the body's diagonal in (0, 0.1] (default 1e-3)")
        points = np.asarray(points, dtype=np.float64)
        self.n_vertices, self.dim = points.shape
        self.n_dofs = self.n_vertices * self.dim
        faces, _ = boundary_faces(np.asarray(cells))
        on_surface = np.unique(faces)
        #: body vertex of every surface vertex ``(n_surface,)``
        self.surface_vertices = on_surface
        local = np.full(self.n_vertices, -1, dtype=np.int64)
        local[on_surface] = np.arange(on_surface.size)
        self.faces = local[faces].astype(np.int32)
        self.edges = surface_edges(self.faces)
        rest = np.asfortranarray(points[on_surface])
        self.mesh = ipctk.CollisionMesh(rest, np.asfortranarray(self.edges),
                                        np.asfortranarray(self.faces))
        self.diagonal = float(ipctk.world_bbox_diagonal_length(rest))
        self.dhat = float(dhat_fraction) * self.diagonal
        self.stiffness = float(stiffness)
        self.max_stiffness = math.inf
        self._previous_min_distance: float | None = None
        if ipctk.has_intersections(self.mesh, rest):
            raise ContactInputError(self._intersection_message(rest, "the rest shape"))
        # surface dofs (vertex-major) among the body's dofs
        self.surface_dofs = (on_surface[:, None] * self.dim + np.arange(self.dim)).reshape(-1)

    def _intersection_message(self, V: np.ndarray, what: str) -> str:
        ipctk = _ipctk()
        collisions = ipctk.NormalCollisions()
        collisions.build(self.mesh, V, 1e-9 * self.diagonal)
        where = ""
        if len(collisions):
            local = collisions[0].vertex_ids(self.mesh.edges, self.mesh.faces)[0]
            where = (f" near vertex {int(self.surface_vertices[local])} at "
                     f"{np.round(V[local], 4).tolist()}")
        return (f"{what}'s surface passes through itself{where}: fix the mesh (remesh the "
                "fold so no triangles cross) or set problem.contact=false")

    # -- positions ------------------------------------------------------------------------
    def surface_positions(self, x: Tensor) -> np.ndarray:
        """Surface vertex positions ``(F, n_surface, 3)`` float64 of body dofs ``(F, n_dofs)``."""
        X = x.detach().cpu().to(torch.float64).numpy().reshape(x.shape[0], self.n_vertices,
                                                                 self.dim)
        return np.ascontiguousarray(X[:, self.surface_vertices])

    def _collisions(self, V: np.ndarray):
        ipctk = _ipctk()
        collisions = ipctk.NormalCollisions()
        collisions.build(self.mesh, np.asfortranarray(V), self.dhat)
        return collisions

    def _potential(self):
        return _ipctk().BarrierPotential(self.dhat, self.stiffness)

    # -- energy, gradient, Hessian ---------------------------------------------------------
    def energy(self, x: Tensor) -> Tensor:
        """Barrier energy per frame ``(F,)`` (J); ``inf`` where the surface intersects."""
        potential = self._potential()
        out = []
        for V in self.surface_positions(x):
            out.append(potential(self._collisions(V), self.mesh, np.asfortranarray(V)))
        return torch.tensor(out, dtype=x.dtype, device=x.device)

    def gradient(self, x: Tensor) -> Tensor:
        """``dEnergy/dx`` ``(F, n_dofs)`` (zero off the surface)."""
        potential = self._potential()
        out = x.new_zeros(x.shape[0], self.n_dofs)
        dofs = torch.from_numpy(self.surface_dofs).to(x.device)
        for f, V in enumerate(self.surface_positions(x)):
            g = potential.gradient(self._collisions(V), self.mesh, np.asfortranarray(V))
            out[f, dofs] = torch.from_numpy(np.asarray(g).reshape(-1)).to(x)
        return out

    def hessian_and_pairs(self, V: np.ndarray, projected: bool = False
                          ) -> tuple[sp.coo_matrix, np.ndarray]:
        """One frame's Hessian in the surface's dofs (coo; exact, or each pair's block
        projected to PSD) at surface positions ``V`` ``(n_surface, 3)``, and the body vertex
        pairs ``(p, 2)`` its active collisions couple (every stencil vertex with every one,
        itself included): the blocks the Hessian can fill, the same whether projected or not."""
        ipctk = _ipctk()
        method = ipctk.PSDProjectionMethod.CLAMP if projected else ipctk.PSDProjectionMethod.NONE
        V = np.asfortranarray(V)
        collisions = self._collisions(V)
        if len(collisions) == 0:
            empty = sp.coo_matrix((V.size, V.size))
            return empty, np.zeros((0, 2), dtype=np.int64)
        H = self._potential().hessian(collisions, self.mesh, V, method).tocoo()
        E, F = self.mesh.edges, self.mesh.faces
        stencils = np.array([c.vertex_ids(E, F) for c in collisions], dtype=np.int64)
        stencils = self.surface_vertices[np.where(stencils < 0, stencils[:, :1], stencils)]
        k = stencils.shape[1]
        a = np.repeat(stencils, k, axis=1).reshape(-1)
        b = np.tile(stencils, (1, k)).reshape(-1)
        return H, np.unique(np.stack([a, b], axis=1), axis=0)

    # -- step size and stiffness -----------------------------------------------------------
    def collision_free_step(self, x0: Tensor, x1: Tensor) -> Tensor:
        """The largest ``alpha`` in ``[0, 1]`` per frame ``(F,)`` such that the straight path
        from ``x0`` to ``x0 + alpha (x1 - x0)`` has no contact (ipctk's CCD)."""
        ipctk = _ipctk()
        V0, V1 = self.surface_positions(x0), self.surface_positions(x1)
        steps = [ipctk.compute_collision_free_stepsize(self.mesh, np.asfortranarray(a),
                                                       np.asfortranarray(b))
                 for a, b in zip(V0, V1)]
        return torch.tensor(steps, dtype=x0.dtype, device=x0.device)

    def minimum_distance(self, x: Tensor) -> float:
        """The smallest distance between surface primitives closer than ``dhat`` in any
        frame (``dhat`` when no pair is that close)."""
        return math.sqrt(self._minimum_squared_distance(x))

    def _minimum_squared_distance(self, x: Tensor) -> float:
        # ipctk's compute_minimum_distance (and update_barrier_stiffness) work in squared
        # distances
        smallest = self.dhat ** 2
        for V in self.surface_positions(x):
            collisions = self._collisions(V)
            if len(collisions):
                smallest = min(smallest, float(collisions.compute_minimum_distance(
                    self.mesh, np.asfortranarray(V))))
        return smallest

    def initial_stiffness(self, elastic_gradient: np.ndarray, x: Tensor,
                          scale: float) -> float:
        """Set ``kappa`` from the problem's scale as IPC does (ipctk's
        ``initial_barrier_stiffness``): ``elastic_gradient`` ``(n_dofs,)`` the elastic
        energy's gradient at the one-frame state ``x`` ``(1, n_dofs)``, and ``scale`` the
        stiffness per dof that bounds ``kappa`` (IPC's average mass; here the mean diagonal
        of the elastic tangent). Returns and keeps ``kappa``; keeps its maximum for
        :meth:`adapt_stiffness`."""
        ipctk = _ipctk()
        self.stiffness = 1.0
        barrier_gradient = self.gradient(x)[0].cpu().numpy()
        kappa, max_kappa = ipctk.initial_barrier_stiffness(
            self.diagonal, ipctk.ClampedLogBarrier(), self.dhat, float(scale),
            np.asarray(elastic_gradient, dtype=np.float64)[self.surface_dofs].reshape(-1, 1),
            barrier_gradient[self.surface_dofs].reshape(-1, 1))
        self.stiffness, self.max_stiffness = float(kappa), float(max_kappa)
        return self.stiffness

    def adapt_stiffness(self, x: Tensor) -> float:
        """IPC's update (ipctk's ``update_barrier_stiffness``): double ``kappa`` (up to its
        maximum) when the smallest distance keeps shrinking below ``1e-9`` of the diagonal."""
        ipctk = _ipctk()
        current = self._minimum_squared_distance(x)
        if self._previous_min_distance is not None and math.isfinite(self.max_stiffness):
            self.stiffness = float(ipctk.update_barrier_stiffness(
                self._previous_min_distance, current, self.max_stiffness, self.stiffness,
                self.diagonal))
        self._previous_min_distance = current
        return self.stiffness

    def intersecting_frames(self, x: Tensor) -> list[int]:
        """Frames of ``x`` ``(F, n_dofs)`` whose surface passes through itself."""
        ipctk = _ipctk()
        return [f for f, V in enumerate(self.surface_positions(x))
                if ipctk.has_intersections(self.mesh, np.asfortranarray(V))]
