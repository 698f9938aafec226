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


def twisted_box(material: str, backend: str):
    """``(quasistatic, positions (2, n_dirichlet, 3))``: the ``3 x 2 x 4`` clamped box of
    :func:`clamped_box` with its top face twisted and lifted in 2 frames."""
    import numpy as np

    model, qs, bottom, top = clamped_box((3, 2, 4), (0.6, 0.4, 1.0), material, backend)
    X = model.rest.points
    frames = []
    for twist, lift in ((0.3, 0.1), (-0.2, -0.15)):
        c, s = np.cos(twist), np.sin(twist)
        R = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        moved = (X[top] - torch.tensor([0.3, 0.2, 0.0], dtype=torch.float64)) @ R.T \
            + torch.tensor([0.3, 0.2, lift], dtype=torch.float64)
        frames.append(torch.cat([X[bottom], moved]))
    return qs, torch.stack(frames)


def forward_backward_jvp(qs, positions):
    """``(x, gradient, tangent, counts)`` of ``qs`` at a seeded log-normal field: the
    equilibrium, the adjoint gradient of ``<w, x>`` and the jvp along a seeded direction
    (seeds 9, 10, 11), with the factorisations and solves they counted."""
    import torch.autograd.forward_ad as fwAD

    from torchfit.linalg import counting

    E = torch.exp(0.3 * torch.randn(qs.model.n_cells, dtype=torch.float64,
                                    generator=torch.Generator().manual_seed(9)))
    w = torch.randn(2, qs.model.n_vertices, 3, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(10))
    v = torch.randn(qs.model.n_cells, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(11))
    E_leaf = E.clone().requires_grad_(True)
    with counting() as count:
        x = qs(E_leaf, positions)
        (grad,) = torch.autograd.grad(x, E_leaf, w)
        with fwAD.dual_level():
            tangent = fwAD.unpack_dual(qs(fwAD.make_dual(E, v), positions)).tangent
    return x.detach(), grad, tangent, count.as_dict()
