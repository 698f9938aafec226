"""Small elastic models of the elasticity tests: meshes, models, deformations, rotations."""
from __future__ import annotations

import math

import torch

from torchfit.mesh import box_tetrahedra, rectangle_triangles
from torchfit.physics.elasticity import MATERIALS, SimplicialElasticity


MODELS = sorted(MATERIALS)


def square_mesh():
    return rectangle_triangles(4, 3, 1.0, 0.75)


def cube_mesh():
    return box_tetrahedra(2, 2, 2, (1.0, 0.8, 0.9))


MESHES = {2: square_mesh, 3: cube_mesh}


def make_model(dim: int, material: str, nu: float = 0.3) -> tuple[SimplicialElasticity, object]:
    mesh = MESHES[dim]()
    return SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                material, nu=nu), mesh


def random_deformation(model: SimplicialElasticity, frames: int = 2, scale: float = 0.2,
                       seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    d = model.dim
    X = model.rest.points
    out = []
    for _ in range(frames):
        A = torch.eye(d) + scale * torch.randn(d, d, generator=g)
        out.append(X @ A.T + 0.02 * torch.randn(X.shape, generator=g))
    return torch.stack(out).reshape(frames, -1)


def rotation_matrix(dim: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    if dim == 2:
        a = 0.7
        return torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=g))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.linalg.det(q) > 0 else -q
