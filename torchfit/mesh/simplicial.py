"""Simplicial meshes: structured grids, boundary sets, adjacency and rest-shape checks.

Structured triangle grids of a rectangle, tetrahedral boxes, boundary sets, element
adjacency by shared facets, rest-shape checks.

Conventions (every function here):

* ``points`` is ``(n_vertices, d)`` float64, ``cells`` is ``(n_cells, d + 1)`` int64;
* cells are positively oriented (counter-clockwise triangles, right-handed tetrahedra:
  ``det([p1 - p0, ..., pd - p0]) > 0``);
* a structured rectangle numbers vertex ``(i, j)`` (``i`` along x, ``j`` along y) as
  ``j * (nx + 1) + i`` and splits cell ``(i, j)`` (number ``c = j * nx + i``) along its
  diagonal from ``(i, j)`` to ``(i + 1, j + 1)`` into triangles ``2c`` (below the
  diagonal) and ``2c + 1`` (above it).

Nothing here solves anything (see docs/architecture.md, layer ``mesh``).
"""
from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np


class MeshError(ValueError):
    """A mesh is unusable (inverted or degenerate elements, bad indices); names them."""


@dataclasses.dataclass
class SimplexMesh:
    """Points and simplices of one mesh (triangles in 2-D, tetrahedra in 3-D).

    Attributes:
        points: ``(n_vertices, d)`` rest positions.
        cells: ``(n_cells, d + 1)`` vertex indices per simplex.
        shape: ``(nx, ny[, nz])`` cells per side for structured meshes, else ``None``.
        extent: ``((lo, hi), ...)`` the box of a structured mesh, else the bounding box.
    """

    points: np.ndarray
    cells: np.ndarray
    shape: tuple[int, ...] | None = None
    extent: tuple[tuple[float, float], ...] | None = None

    def __post_init__(self) -> None:
        self.points = np.ascontiguousarray(self.points, dtype=np.float64)
        self.cells = np.ascontiguousarray(self.cells, dtype=np.int64)
        if self.points.ndim != 2 or self.points.shape[1] not in (2, 3):
            raise MeshError(f"points must be (n, 2) or (n, 3), got {self.points.shape}")
        d = self.points.shape[1]
        if self.cells.ndim != 2 or self.cells.shape[1] != d + 1:
            raise MeshError(f"{d}-D simplices need {d + 1} vertices each, got cells of shape "
                            f"{self.cells.shape}")
        if self.cells.size and (self.cells.min() < 0 or self.cells.max() >= len(self.points)):
            raise MeshError(f"cell vertex index out of range [0, {len(self.points)})")
        if self.extent is None and len(self.points):
            self.extent = tuple((float(lo), float(hi)) for lo, hi in
                                zip(self.points.min(0), self.points.max(0)))

    @property
    def dim(self) -> int:
        return int(self.points.shape[1])

    @property
    def n_vertices(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_cells(self) -> int:
        return int(self.cells.shape[0])

    def centroids(self) -> np.ndarray:
        """``(n_cells, d)`` barycentres of the cells."""
        return self.points[self.cells].mean(axis=1)

    def signed_volumes(self) -> np.ndarray:
        """``(n_cells,)`` signed areas/volumes (positive for positively oriented cells)."""
        return signed_volumes(self.points, self.cells)

    def boundary_vertices(self, side: str, tol: float = 1e-12) -> np.ndarray:
        """Sorted vertices on one side of the box: ``left``/``right`` (x min/max),
        ``bottom``/``top`` (y min/max), ``back``/``front`` (z min/max, 3-D)."""
        axis, end = _SIDES.get(side, (None, None))
        if axis is None or axis >= self.dim:
            raise MeshError(f"unknown side {side!r} for a {self.dim}-D mesh; choose one of "
                            f"{[s for s, (a, _) in _SIDES.items() if a < self.dim]}")
        assert self.extent is not None
        value = self.extent[axis][end]
        scale = max(1.0, abs(value))
        return np.nonzero(np.abs(self.points[:, axis] - value) <= tol * scale)[0]

    def boundary_facet_vertices(self) -> np.ndarray:
        """Sorted vertices on the boundary (facets that belong to one cell only)."""
        facets, owners = _facets(self.cells)
        key, counts = np.unique(np.sort(facets, axis=1), axis=0, return_counts=True)
        return np.unique(key[counts == 1].reshape(-1))

    def adjacency(self) -> np.ndarray:
        """Pairs ``(a, b)``, ``a < b``, of cells sharing a facet (edge in 2-D, face in 3-D)."""
        return element_adjacency(self.cells)


_SIDES = {"left": (0, 0), "right": (0, 1), "bottom": (1, 0), "top": (1, 1),
          "back": (2, 0), "front": (2, 1)}


def signed_volumes(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Signed measure of every simplex: ``det([p1 - p0, ..., pd - p0]) / d!``."""
    p = np.asarray(points, dtype=np.float64)[np.asarray(cells)]
    edges = p[:, 1:, :] - p[:, :1, :]                  # (n, d, d): rows p_a - p_0
    d = p.shape[-1]
    return np.linalg.det(edges) / math.factorial(d)


def check_rest_cells(points: np.ndarray, cells: np.ndarray, rel_tol: float = 1e-10,
                     max_listed: int = 10) -> np.ndarray:
    """Signed volumes of the cells, or :class:`MeshError` naming inverted/degenerate ones.

    A cell is *degenerate* when ``|volume| <= rel_tol * h^d`` (``h`` its longest edge:
    collinear/coplanar vertices, repeated vertices) and *inverted* when its volume is
    negative (wrong orientation).
    """
    points = np.asarray(points, dtype=np.float64)
    cells = np.asarray(cells, dtype=np.int64)
    vol = signed_volumes(points, cells)
    p = points[cells]
    d = points.shape[1]
    longest = np.zeros(len(cells))
    for a, b in itertools.combinations(range(d + 1), 2):
        longest = np.maximum(longest, np.linalg.norm(p[:, a] - p[:, b], axis=1))
    degenerate = ~(np.abs(vol) > rel_tol * longest ** d)   # NaN counts as degenerate
    inverted = (vol < 0) & ~degenerate
    problems = []
    for label, mask in (("degenerate (zero or near-zero volume)", degenerate),
                        ("inverted (negative orientation)", inverted)):
        bad = np.nonzero(mask)[0]
        if bad.size:
            listed = ", ".join(f"{int(e)} (vertices {cells[e].tolist()}, volume {vol[e]:.3e})"
                               for e in bad[:max_listed])
            more = f" and {bad.size - max_listed} more" if bad.size > max_listed else ""
            problems.append(f"{bad.size} {label} element(s): {listed}{more}")
    if problems:
        raise MeshError("invalid rest mesh: " + "; ".join(problems) +
                        ". Fix the mesh: reorder the vertices of inverted elements, remove "
                        "degenerate ones.")
    return vol


def _facets(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All facets ``(n_cells * (d + 1), d)`` (vertex lists) and the cell owning each."""
    cells = np.asarray(cells, dtype=np.int64)
    k = cells.shape[1]
    facets = np.concatenate([np.delete(cells, i, axis=1) for i in range(k)], axis=0)
    owners = np.tile(np.arange(len(cells)), k)
    return facets, owners


def element_adjacency(cells: np.ndarray) -> np.ndarray:
    """``(n_pairs, 2)`` cells sharing a facet, each pair ``(a, b)`` with ``a < b``, sorted.

    These are the neighbours of the TV difference operator of a per-element field.
    """
    facets, owners = _facets(cells)
    if facets.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    keys = np.sort(facets, axis=1)
    order = np.lexsort(keys.T[::-1])
    keys, owners = keys[order], owners[order]
    same = np.all(keys[1:] == keys[:-1], axis=1)
    if bool(np.any(same[1:] & same[:-1])):
        raise MeshError("a facet is shared by more than two cells: the mesh is not a manifold")
    pairs = np.stack([owners[:-1][same], owners[1:][same]], axis=1)
    pairs = np.sort(pairs, axis=1)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def rectangle_triangles(nx: int, ny: int, width: float = 1.0, height: float = 1.0,
                        origin: tuple[float, float] = (0.0, 0.0)) -> SimplexMesh:
    """Structured triangulation of ``[x0, x0 + width] x [y0, y0 + height]``.

    ``nx * ny`` cells, each split into two counter-clockwise triangles along the
    diagonal ``(i, j) - (i + 1, j + 1)`` (see the module docstring for the numbering).
    """
    if int(nx) < 1 or int(ny) < 1:
        raise MeshError(f"need at least one cell per side, got nx={nx}, ny={ny}")
    if not (width > 0 and height > 0 and math.isfinite(width) and math.isfinite(height)):
        raise MeshError(f"width and height must be positive and finite, got {width}, {height}")
    nx, ny = int(nx), int(ny)
    xs = origin[0] + width * np.arange(nx + 1) / nx
    ys = origin[1] + height * np.arange(ny + 1) / ny
    X, Y = np.meshgrid(xs, ys)                        # (ny + 1, nx + 1)
    points = np.stack([X.reshape(-1), Y.reshape(-1)], axis=1)
    j, i = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    v00 = (j * (nx + 1) + i).reshape(-1)
    v10, v01, v11 = v00 + 1, v00 + nx + 1, v00 + nx + 2
    lower = np.stack([v00, v10, v11], axis=1)         # below the diagonal
    upper = np.stack([v00, v11, v01], axis=1)         # above it
    cells = np.stack([lower, upper], axis=1).reshape(-1, 3)
    extent = ((origin[0], origin[0] + width), (origin[1], origin[1] + height))
    return SimplexMesh(points, cells, (nx, ny), extent)


# Kuhn (Freudenthal) split of a cube into 6 tetrahedra along the main diagonal 0-7; the
# corners are numbered c = ix + 2 iy + 4 iz. Every tetrahedron is a monotone path
# 0 -> e_a -> e_a + e_b -> 7, so neighbouring cubes share conforming faces.
_KUHN = [(0, 1, 3, 7), (0, 3, 2, 7), (0, 2, 6, 7), (0, 6, 4, 7), (0, 4, 5, 7), (0, 5, 1, 7)]


def box_tetrahedra(nx: int, ny: int, nz: int,
                   size: tuple[float, float, float] = (1.0, 1.0, 1.0),
                   origin: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> SimplexMesh:
    """Structured tetrahedral mesh of a box: ``nx * ny * nz`` cubes, 6 tetrahedra each.

    Vertex ``(i, j, k)`` is ``(k * (ny + 1) + j) * (nx + 1) + i``; tetrahedra are
    positively oriented.
    """
    if min(int(nx), int(ny), int(nz)) < 1:
        raise MeshError(f"need at least one cell per side, got {nx}, {ny}, {nz}")
    nx, ny, nz = int(nx), int(ny), int(nz)
    axes = [origin[a] + size[a] * np.arange(n + 1) / n for a, n in enumerate((nx, ny, nz))]
    Z, Y, X = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    points = np.stack([X.reshape(-1), Y.reshape(-1), Z.reshape(-1)], axis=1)
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    base = ((k * (ny + 1) + j) * (nx + 1) + i).reshape(-1)
    offsets = np.array([(c & 1) + ((c >> 1) & 1) * (nx + 1) + ((c >> 2) & 1) * (nx + 1) * (ny + 1)
                        for c in range(8)])
    corners = base[:, None] + offsets[None, :]       # (n_cubes, 8)
    cells = corners[:, np.array(_KUHN)].reshape(-1, 4)
    vol = signed_volumes(points, cells)
    flip = vol < 0
    cells[flip] = cells[flip][:, [0, 2, 1, 3]]
    extent = tuple((origin[a], origin[a] + size[a]) for a in range(3))
    return SimplexMesh(points, cells, (nx, ny, nz), extent)


def normalized_points(points: np.ndarray,
                      extent: tuple[tuple[float, float], ...]) -> np.ndarray:
    """Points mapped affinely from the box ``extent`` onto the unit box."""
    lo = np.array([e[0] for e in extent])
    hi = np.array([e[1] for e in extent])
    return (np.asarray(points, dtype=np.float64) - lo) / (hi - lo)


def pair_groups(pairs: np.ndarray, n: int) -> np.ndarray:
    """``(n,)`` the group of each of ``n`` points joined by ``pairs`` ``(k, 2)`` (transitively:
    the connected components), numbered in order of their first point, so that points no
    pair joins keep their order (the welding of seams and of a canonical surface)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    _, first = np.unique(labels, return_index=True)
    rank = np.empty(len(first), dtype=np.int64)
    rank[np.argsort(first)] = np.arange(len(first))
    return rank[labels]
