"""A tetrahedral box held at its bottom and top faces, for equilibrium and backend tests."""
from __future__ import annotations

import torch

from torchfit.mesh import box_tetrahedra
from torchfit.physics import NewtonOptions
from torchfit.physics.elasticity import QuasistaticElasticity, SimplicialElasticity


def clamped_box(cells: tuple[int, int, int], size: tuple[float, float, float], material: str,
                backend: str = "scipy", atol: float = 1e-14):
    """``(model, quasistatic, bottom, top)``: a box of ``cells`` tetrahedral cells of ``size``
    (top face at ``z = size[2] = 1``), Dirichlet on its bottom and top vertices."""
    mesh = box_tetrahedra(*cells, size)
    model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                 material, nu=0.3)
    X = model.rest.points
    bottom = torch.nonzero(X[:, 2] <= 1e-12).reshape(-1)
    top = torch.nonzero(X[:, 2] >= size[2] - 1e-12).reshape(-1)
    qs = QuasistaticElasticity(model, torch.cat([bottom, top]), backend=backend,
                               newton=NewtonOptions(rtol=1e-13, atol=atol))
    return model, qs, bottom, top
