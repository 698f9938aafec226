"""Two tetrahedral blocks, one above the other, a gap smaller than the contact distance
between them: the lower one held at its bottom, the upper one pressed down at its top."""
from __future__ import annotations

import numpy as np
import torch

from torchfit.mesh import box_tetrahedra

SIZE = (0.2, 0.2, 0.1)
DHAT = 0.01            # fraction of the two blocks' diagonal
GAP = 0.001            # metres (the diagonal is about 0.36 m: dhat about 3.6 mm)


def blocks(cells: tuple[int, int, int] = (2, 2, 1), gap: float = GAP
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(points, tets, bottom, top)``: the two blocks' rest points ``(n, 3)``, tetrahedra
    ``(m, 4)``, the lower block's bottom vertices and the upper block's top vertices."""
    mesh = box_tetrahedra(*cells, SIZE)
    lower = np.asarray(mesh.points, dtype=np.float64)
    upper = lower + np.array([0.0, 0.0, SIZE[2] + gap])
    points = np.concatenate([lower, upper])
    tets = np.concatenate([mesh.cells, mesh.cells + len(lower)]).astype(np.int64)
    bottom = np.nonzero(points[:, 2] <= 1e-12)[0]
    top = np.nonzero(points[:, 2] >= 2 * SIZE[2] + gap - 1e-12)[0]
    return points, tets, bottom, top


def fixed_dofs(vertices: np.ndarray) -> torch.Tensor:
    return torch.from_numpy((vertices[:, None] * 3 + np.arange(3)).reshape(-1))
