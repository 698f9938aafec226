"""The rigged body's parameter grid and its ``blocks`` truth (``parameters=grid``).

A coarse regular grid of nodes over the tetrahedral mesh's box, trilinear to the
tetrahedra (:func:`~torchfit.params.per_grid_node`); ``grid_shape`` is ``(n0, n1, n2)``
nodes per axis. The ``blocks`` truth labels grid nodes (0 background, 1 stiff, 2 soft).
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..params import Parameterization, per_grid_node


def grid_parameterization(grid_shape: tuple[int, int, int], points: np.ndarray,
                          centroids: np.ndarray, transform: str,
                          dtype: torch.dtype) -> Parameterization:
    """Young's modulus at the nodes of a grid over the box of ``points`` ``(n, 3)``,
    trilinear to ``centroids`` ``(n_tets, 3)``."""
    return per_grid_node(grid_shape, centroids, points.min(0), points.max(0), transform,
                         name="Young's modulus", dtype=dtype)


def block_nodes(grid_shape: tuple[int, int, int]) -> np.ndarray:
    """Label per grid node of the ``blocks`` truth ``(n0 n1 n2,)``: 0 background, 1 stiff,
    2 soft.

    In grid index space: the stiff block is the nodes with ``ix >= nx/2`` (the front
    half) and ``iz`` in the second quarter of the length; the soft block ``iy < ny/2``
    and ``iz`` in the third quarter. Both span several nodes in every direction.
    """
    nx, ny, nz = grid_shape
    ix, iy, iz = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    labels = np.zeros((nx, ny, nz), dtype=np.int64)
    stiff = (ix >= nx // 2) & (iz >= nz // 4) & (iz < nz // 2)
    soft = (iy < ny // 2) & (iz >= nz // 2) & (iz < (3 * nz) // 4)
    labels[stiff] = 1
    labels[soft] = 2
    return labels.reshape(-1)


def blocks_field(grid_shape: tuple[int, int, int], points: np.ndarray, centroids: np.ndarray,
                 E_blocks: list[float], dtype: torch.dtype, device) -> Tensor:
    """The ``blocks`` truth per tetrahedron ``(n_tets,)``: the moduli ``E_blocks``
    (background, stiff, soft) at the grid nodes, trilinear to the tetrahedra."""
    grid = grid_parameterization(grid_shape, points, centroids, "identity", dtype)
    values = torch.tensor(E_blocks, dtype=dtype)[torch.as_tensor(block_nodes(grid_shape))]
    return grid(values.to(device))
