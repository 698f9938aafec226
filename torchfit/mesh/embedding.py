"""Barycentric embedding of points (a render surface, markers) in a tetrahedral mesh.

Every point gets one tetrahedron and four weights; its position in any deformed state of
the tetrahedral mesh is the weighted sum of that tetrahedron's four vertices. Points in a
tetrahedron use their barycentric coordinates there (all ``>= -tol``); points outside the
mesh (a surface vertex a little outside fTetWild's envelope) use the *extrapolated*
barycentric coordinates in the tetrahedron that owns the nearest boundary face (of faces
equally near, the lowest-numbered: the choice does not depend on the mesh's orientation),
so the rest positions are reproduced exactly and any affine motion of that tetrahedron
moves the point by the same affine map.

Conventions: points ``(n, 3)`` float64, tetrahedral mesh ``tet_points`` ``(V, 3)`` float64
and ``tet_cells`` ``(m, 4)`` int64, positively oriented; lengths in the mesh's unit.
Nothing here solves anything (see docs/architecture.md, layer ``mesh``).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse
import torch
import trimesh
from scipy.spatial import cKDTree

from .simplicial import MeshError

#: Outward faces of a positively oriented tetrahedron (p0, p1, p2, p3): face ``i`` is the one
#: opposite vertex ``i``, counter-clockwise seen from outside.
_OUTWARD_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
#: Candidate tetrahedra (nearest centroids) tried first for every point.
_FIRST_CANDIDATES = 8
#: Point-candidate pairs evaluated at once (bounds the temporary memory).
_PAIRS_PER_CHUNK = 1 << 20


@dataclasses.dataclass(eq=False)
class Embedding:
    """Points embedded in a tetrahedral mesh.

    Attributes:
        cells: ``(n,)`` int64, the tetrahedron containing each point (the nearest one for
            points outside the mesh).
        weights: ``(n, 4)`` float64 barycentric coordinates of each point in its
            tetrahedron (summing to 1; extrapolated, slightly negative, outside the mesh).
        distance: ``(n,)`` float64, 0 inside the mesh, else the distance from the point to
            its tetrahedron (the mesh's length unit).
        n_vertices: number of vertices of the tetrahedral mesh.
        vertices: ``(n, 4)`` int64, the tetrahedral-mesh vertices of each point's
            tetrahedron (``tet_cells[cells]``), the ones :meth:`apply` gathers.
    """

    cells: np.ndarray
    weights: np.ndarray
    distance: np.ndarray
    n_vertices: int
    vertices: np.ndarray
    _tensors: dict = dataclasses.field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        self.cells = np.ascontiguousarray(self.cells, dtype=np.int64).reshape(-1)
        n = len(self.cells)
        self.weights = np.ascontiguousarray(self.weights, dtype=np.float64)
        self.distance = np.ascontiguousarray(self.distance, dtype=np.float64)
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.int64)
        self.n_vertices = int(self.n_vertices)
        if (self.weights.shape != (n, 4) or self.vertices.shape != (n, 4)
                or self.distance.shape != (n,)):
            raise MeshError(f"an embedding of {n} points needs weights and vertices (n, 4) and "
                            f"distance (n,), got {self.weights.shape}, {self.vertices.shape}, "
                            f"{self.distance.shape}")
        if n and (self.vertices.min() < 0 or self.vertices.max() >= self.n_vertices):
            raise MeshError(f"embedding vertex index out of range [0, {self.n_vertices})")

    @property
    def n_points(self) -> int:
        return int(len(self.cells))

    def _index_and_weights(self, device: torch.device,
                           dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        key = (device, dtype)
        if key not in self._tensors:
            index = torch.from_numpy(self.vertices.reshape(-1)).to(device)
            weights = torch.from_numpy(self.weights).to(device=device, dtype=dtype)
            self._tensors[key] = (index, weights)
        return self._tensors[key]

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        """Positions of the embedded points for tetrahedral-mesh positions ``x``.

        Args:
            x: ``(..., n_vertices, 3)`` vertex positions (floating point).

        Returns:
            ``(..., n_points, 3)``: the weighted sums of each point's four vertices. A
            gather and a weighted sum: differentiable (reverse and forward mode) and
            usable under ``torch.func.vmap`` (the batch dimension anywhere).
        """
        if x.dim() < 2 or x.shape[-2] != self.n_vertices or x.shape[-1] != 3:
            raise ValueError(f"apply needs positions (..., {self.n_vertices}, 3) of the "
                             f"tetrahedral mesh's vertices, got {tuple(x.shape)}")
        if not x.is_floating_point():
            raise ValueError(f"apply needs floating-point positions, got {x.dtype}")
        index, weights = self._index_and_weights(x.device, x.dtype)
        corners = x.index_select(-2, index).unflatten(-2, (self.n_points, 4))
        return (corners * weights.unsqueeze(-1)).sum(-2)

    def matrix(self) -> scipy.sparse.csr_matrix:
        """``(n_points, n_vertices)`` sparse interpolation matrix ``W`` (``W @ x`` equals
        :meth:`apply` for ``x`` ``(n_vertices, 3)``); four stored entries per row."""
        rows = np.repeat(np.arange(self.n_points), 4)
        return scipy.sparse.csr_matrix(
            (self.weights.reshape(-1), (rows, self.vertices.reshape(-1))),
            shape=(self.n_points, self.n_vertices))


def dof_matrix(vertices: torch.Tensor, weights: torch.Tensor, n_vertices: int,
               dim: int) -> torch.Tensor:
    """Embedded points on flat dofs: a coalesced sparse COO tensor ``(n dim, n_vertices dim)``
    whose row ``p dim + k`` holds the weights of point ``p``'s corners for coordinate ``k``
    (rows point-major, columns vertex-major, as ``x.reshape(-1)`` of ``(n_vertices, dim)``).

    Args:
        vertices: ``(n, c)`` mesh vertices of each point's cell; weights: ``(n, c)``.
    """
    n, corners = vertices.shape
    rows = (torch.arange(n)[:, None, None] * dim
            + torch.arange(dim)[None, None, :]).expand(n, corners, dim)
    cols = vertices[:, :, None] * dim + torch.arange(dim)[None, None, :]
    values = weights[:, :, None].expand(n, corners, dim)
    return torch.sparse_coo_tensor(
        torch.stack([rows.reshape(-1), cols.reshape(-1)]), values.reshape(-1),
        (n * dim, n_vertices * dim), check_invariants=False).coalesce()


def boundary_faces(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Faces of a tetrahedral mesh that belong to one tetrahedron only.

    Args:
        cells: ``(m, 4)`` positively oriented tetrahedra.

    Returns:
        ``(faces, owners)``: ``faces`` ``(k, 3)`` int64, counter-clockwise seen from outside
        (outward normals), and ``owners`` ``(k,)`` int64, the tetrahedron of each face.
    """
    cells = np.asarray(cells, dtype=np.int64)
    if cells.ndim != 2 or cells.shape[1] != 4:
        raise MeshError(f"tetrahedra must be (m, 4), got {cells.shape}")
    faces = cells[:, _OUTWARD_FACES].reshape(-1, 3)
    owners = np.repeat(np.arange(len(cells), dtype=np.int64), 4)
    if len(faces) == 0:
        return faces, owners
    key = np.sort(faces, axis=1)
    n = int(cells.max()) + 1
    if n < 2 ** 21:                                  # one int64 per face: faster than rows
        key = (key[:, 0] * n + key[:, 1]) * n + key[:, 2]
        _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    else:
        _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    single = counts[inverse.reshape(-1)] == 1
    return faces[single], owners[single]


def _first_tied_face(boundary: trimesh.Trimesh, x: np.ndarray, found: np.ndarray,
                     distance: np.ndarray) -> np.ndarray:
    """``(n,)`` the lowest-numbered boundary face as near to each point ``x`` ``(n, 3)`` as
    the nearest one ``found``, ``distance`` away (relative ``1e-9``).

    A point nearest to an edge or a corner of the boundary is as near to every face there,
    and the owners of those faces extrapolate it differently: which one the search returns
    depends on round-off, so a rotated copy of the same mesh could embed it elsewhere (by
    1e-6 of the body on the capsule). The lowest index among the faces that share a vertex
    with the one found (any tie lies there) does not depend on the orientation.
    """
    faces = np.asarray(boundary.faces, dtype=np.int64)
    around = np.asarray(boundary.vertex_faces, dtype=np.int64)[faces[found]]   # (n, 3, d)
    candidates = around.reshape(len(found), -1)
    valid = candidates >= 0
    rows, cols = np.nonzero(valid)
    near = trimesh.triangles.closest_point(boundary.vertices[faces[candidates[rows, cols]]],
                                           x[rows])
    gap = np.full(candidates.shape, np.inf)
    gap[rows, cols] = np.linalg.norm(x[rows] - near, axis=1)
    tied = (gap <= distance[:, None] * (1 + 1e-9)) | (candidates == found[:, None])
    return np.where(tied, candidates, np.iinfo(np.int64).max).min(axis=1)


def _barycentric(x: np.ndarray, origin: np.ndarray, inverse: np.ndarray) -> np.ndarray:
    """``(..., 4)`` barycentric coordinates of ``x`` ``(..., 3)`` in tetrahedra given by their
    first vertex ``(..., 3)`` and inverse edge matrices ``(..., 3, 3)``."""
    lam = np.einsum("...ij,...j->...i", inverse, x - origin)
    return np.concatenate([1.0 - lam.sum(axis=-1, keepdims=True), lam], axis=-1)


def embed_points(points: np.ndarray, tet_points: np.ndarray, tet_cells: np.ndarray,
                 tol: float = 1e-10, max_distance: float | None = None) -> Embedding:
    """Embed points in a tetrahedral mesh (vectorised point location).

    Each point is located among the tetrahedra whose centroids are nearest (a k-d tree),
    then, for points not found there, among every tetrahedron whose circumscribing ball
    about its centroid holds the point (exact: a point inside a tetrahedron is never
    farther from its centroid than its farthest vertex). A point in no tetrahedron (by more
    than ``tol`` in barycentric terms) is outside the mesh: it gets the tetrahedron owning
    the nearest boundary face (``trimesh.proximity.closest_point`` on
    :func:`boundary_faces`; a tie goes to the lowest-numbered face) and its extrapolated
    barycentric coordinates there.

    Args:
        points: ``(n, 3)`` points to embed.
        tet_points: ``(V, 3)`` vertices of the tetrahedral mesh.
        tet_cells: ``(m, 4)`` positively oriented tetrahedra.
        tol: barycentric tolerance: a point whose smallest coordinate in a tetrahedron is
            ``>= -tol`` is inside it.
        max_distance: if given, a point farther than this outside the mesh raises
            :class:`MeshError` (the mesh's length unit).

    Returns:
        :class:`Embedding` (weights recomputed by a 3x3 solve per point for accuracy).
    """
    x = np.asarray(points, dtype=np.float64)
    P = np.asarray(tet_points, dtype=np.float64)
    C = np.asarray(tet_cells, dtype=np.int64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise MeshError(f"points to embed must be (n, 3), got {x.shape}")
    if P.ndim != 2 or P.shape[1] != 3 or C.ndim != 2 or C.shape[1] != 4 or len(C) == 0:
        raise MeshError(f"embedding needs a tetrahedral mesh with points (V, 3) and at least "
                        f"one cell (m, 4), got {P.shape} and {C.shape}")
    if C.min() < 0 or C.max() >= len(P):
        raise MeshError(f"tetrahedron vertex index out of range [0, {len(P)})")
    bad = np.nonzero(~np.isfinite(x).all(axis=1))[0]
    if bad.size:
        raise MeshError(f"point {int(bad[0])} to embed is not finite {x[bad[0]].tolist()}")
    if not (tol >= 0 and np.isfinite(tol)):
        raise MeshError(f"tol must be a non-negative finite number, got {tol!r}")
    n, m = len(x), len(C)
    corners = P[C]                                   # (m, 4, 3)
    origin = corners[:, 0]
    edges = np.swapaxes(corners[:, 1:] - origin[:, None], 1, 2)   # columns p_i - p_0
    det = np.linalg.det(edges)
    flat = ~(det > 0)
    if flat.any():
        raise MeshError(f"embedding needs positively oriented tetrahedra: {int(flat.sum())} of "
                        f"{m} have non-positive volume (first: cell {int(np.argmax(flat))})")
    inverse = np.linalg.inv(edges)
    centroids = corners.mean(axis=1)
    radius = np.linalg.norm(corners - centroids[:, None], axis=2).max(axis=1)
    tree = cKDTree(centroids)

    cell = np.full(n, -1, dtype=np.int64)
    # 1. the nearest centroids: the tetrahedron where the point is deepest inside
    k = min(_FIRST_CANDIDATES, m)
    chunk = max(1, _PAIRS_PER_CHUNK // k)
    for lo in range(0, n, chunk):
        hi = min(n, lo + chunk)
        cand = tree.query(x[lo:hi], k=k)[1].reshape(hi - lo, k)
        depth = _barycentric(x[lo:hi, None], origin[cand], inverse[cand]).min(axis=-1)
        best = np.argmax(depth, axis=1)
        rows = np.arange(hi - lo)
        found = depth[rows, best] >= -tol
        cell[lo:hi][found] = cand[rows, best][found]
    # 2. the rest: every tetrahedron whose bounding ball holds the point
    rest = np.nonzero(cell < 0)[0]
    if rest.size:
        pairs = cKDTree(x[rest]).sparse_distance_matrix(
            tree, float(radius.max()) * (1 + 1e-9), output_type="ndarray")
        i, j = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
        near = pairs["v"] <= radius[j] * (1 + 1e-9)
        i, j = i[near], j[near]
        depth = _barycentric(x[rest[i]], origin[j], inverse[j]).min(axis=-1)
        inside = depth >= -tol
        i, j, depth = i[inside], j[inside], depth[inside]
        order = np.lexsort((-depth, i))              # per point, the deepest first
        first = np.ones(len(order), dtype=bool)
        first[1:] = i[order][1:] != i[order][:-1]
        cell[rest[i[order][first]]] = j[order][first]
    # 3. outside the mesh: the tetrahedron of the nearest boundary face
    distance = np.zeros(n)
    outside = np.nonzero(cell < 0)[0]
    if outside.size:
        faces, owners = boundary_faces(C)
        boundary = trimesh.Trimesh(P, faces, process=False)
        closest, _, triangle = trimesh.proximity.closest_point(boundary, x[outside])
        distance[outside] = np.linalg.norm(x[outside] - closest, axis=1)
        triangle = _first_tied_face(boundary, x[outside], np.asarray(triangle, np.int64),
                                    distance[outside])
        cell[outside] = owners[triangle]
    if max_distance is not None and outside.size:
        far = distance > max_distance
        if far.any():
            worst = int(np.argmax(distance))
            raise MeshError(f"point {worst} lies {distance[worst]:.4g} outside the "
                            f"tetrahedral mesh, more than max_distance={max_distance:g} "
                            f"({int(far.sum())} point(s) do): the tetrahedralisation does not "
                            "match these points; lower epsilon or check the units")
    # final weights: one 3x3 solve per point (backward stable, so positions reproduce)
    lam = np.linalg.solve(edges[cell], (x - origin[cell])[:, :, None])[:, :, 0]
    weights = np.concatenate([1.0 - lam.sum(axis=1, keepdims=True), lam], axis=1)
    return Embedding(cell, weights, distance, len(P), C[cell])
