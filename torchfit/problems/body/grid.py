"""The rigged body's parameter grid along its principal axes, and its ``blocks`` truth.

The grid follows the body, not the world: a rotated body and its rotated animation get the
same grid in body coordinates, so the same fit (docs/notes/axes.md).

**Frame** (:func:`.frame.principal_frame` of the tetrahedra): origin at their volume
centroid, axes ``a0``, ``a1``, ``a2`` of increasing extent (the longest last, so
``problem.grid=[4, 4, 12]`` puts 12 nodes along the body's length whatever its
orientation), signs and round cross-sections settled by documented, rotation-equivariant
rules.

**Counts** (:func:`grid_counts`): proportional to the extents for a budget of nodes
(``problem.grid_nodes``, 192), at least :data:`MIN_NODES` per axis (4: a trilinear grid
with fewer cannot put a node inside a cross-section), the rest of the budget shared by the
longer axes: the procedural arm (0.11 x 0.10 x 0.58 m) gets ``4 x 4 x 12``. An explicit
``problem.grid`` gives the counts along ``a0, a1, a2``.

The grid is a box over the tetrahedron vertices in body coordinates; the parameterisation
is :func:`~torchfit.params.per_grid_node` on the centroids rotated into that frame. The
``blocks`` truth labels grid nodes (0 background, 1 stiff, 2 soft) in grid index space.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor

from ...params import Parameterization, per_grid_node
from .frame import principal_frame

#: fewest nodes per axis of a grid from a budget
MIN_NODES = 4


@dataclasses.dataclass(frozen=True)
class BodyGrid:
    """A node grid along a body's principal axes.

    Attributes:
        origin: ``(3,)`` the volume centroid (world coordinates).
        axes: ``(3, 3)`` rows ``a0, a1, a2`` (unit, right-handed, increasing extent).
        lower, upper: ``(3,)`` the box of the tetrahedron vertices in body coordinates.
        shape: nodes along ``a0, a1, a2``.
        from_budget: the counts came from ``grid_nodes`` (else from ``problem.grid``).
    """

    origin: np.ndarray
    axes: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    shape: tuple[int, int, int]
    from_budget: bool = True

    def to_body(self, points: np.ndarray) -> np.ndarray:
        """Body coordinates ``(n, 3)`` of world ``points`` ``(n, 3)``."""
        return (np.asarray(points, dtype=np.float64) - self.origin) @ self.axes.T

    def describe(self) -> dict[str, Any]:
        """What ``result.json`` records of the grid (``problem.grid``)."""
        return {"shape": list(self.shape), "nodes": int(np.prod(self.shape)),
                "counts_from": "grid_nodes" if self.from_budget else "grid",
                "axes": self.axes.tolist(), "origin": self.origin.tolist(),
                "extent": (self.upper - self.lower).tolist()}


def grid_counts(extents: Sequence[float], budget: int, minimum: int = MIN_NODES
                ) -> tuple[int, int, int]:
    """Node counts ``(3,)`` proportional to ``extents``, about ``budget`` nodes in all, at
    least ``minimum`` per axis (the axes below it get it; the others share the rest)."""
    extents = np.maximum(np.asarray(extents, dtype=np.float64), 1e-300)
    minimum = minimum if budget >= minimum ** 3 else 2
    fixed = np.zeros(3, dtype=bool)
    while True:
        free = ~fixed
        rest = budget / float(minimum) ** int(fixed.sum())
        scale = (rest / np.prod(extents[free])) ** (1.0 / int(free.sum()))
        counts = np.where(fixed, float(minimum), extents * scale)
        short = free & (counts < minimum)
        if not short.any() or short.sum() == free.sum():
            break
        fixed[np.flatnonzero(short)[np.argmin(counts[short])]] = True
    return tuple(int(max(minimum, round(c))) for c in counts)


def body_grid(points: np.ndarray, cells: np.ndarray, displacement: np.ndarray | None,
              budget: int, explicit: Sequence[int] | None = None,
              frame: tuple[np.ndarray, np.ndarray] | None = None) -> BodyGrid:
    """The grid of a tetrahedral body: its principal frame (or the given ``frame``, the
    fitted run's: a round body's frame follows its animation's motion), the box of
    ``points`` in it, and ``explicit`` counts or counts from the ``budget``."""
    origin, axes = principal_frame(points, cells, displacement) if frame is None else frame
    body = (np.asarray(points, dtype=np.float64) - origin) @ axes.T
    lower, upper = body.min(axis=0), body.max(axis=0)
    if explicit is not None:
        shape = tuple(int(n) for n in explicit)
    else:
        shape = grid_counts(upper - lower, budget)
    return BodyGrid(origin, axes, lower, upper, shape, explicit is None)


def grid_parameterization(grid: BodyGrid, centroids: np.ndarray, transform: str,
                          dtype: torch.dtype) -> Parameterization:
    """Young's modulus at the nodes of ``grid``, trilinear to ``centroids`` ``(n_tets, 3)``
    (world coordinates, rotated into the grid's frame)."""
    return per_grid_node(grid.shape, grid.to_body(centroids), grid.lower, grid.upper,
                         transform, name="Young's modulus", dtype=dtype)


def block_nodes(grid_shape: tuple[int, int, int]) -> np.ndarray:
    """Label per grid node of the ``blocks`` truth ``(n0 n1 n2,)``: 0 background, 1 stiff,
    2 soft.

    In grid index space (axes ``a0, a1, a2``, the longest last): the stiff block is the
    nodes with ``i0 >= n0/2`` and ``i2`` in the second quarter of the length; the soft block
    ``i1 < n1/2`` and ``i2`` in the third quarter. Both span several nodes in every direction.
    """
    nx, ny, nz = grid_shape
    ix, iy, iz = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    labels = np.zeros((nx, ny, nz), dtype=np.int64)
    stiff = (ix >= nx // 2) & (iz >= nz // 4) & (iz < nz // 2)
    soft = (iy < ny // 2) & (iz >= nz // 2) & (iz < (3 * nz) // 4)
    labels[stiff] = 1
    labels[soft] = 2
    return labels.reshape(-1)


def blocks_field(grid: BodyGrid, centroids: np.ndarray, E_blocks: list[float],
                 dtype: torch.dtype, device) -> Tensor:
    """The ``blocks`` truth per tetrahedron ``(n_tets,)``: the moduli ``E_blocks``
    (background, stiff, soft) at the grid nodes, trilinear to the tetrahedra."""
    parameterization = grid_parameterization(grid, centroids, "identity", dtype)
    values = torch.tensor(E_blocks, dtype=dtype)[torch.as_tensor(block_nodes(grid.shape))]
    return parameterization(values.to(device))
