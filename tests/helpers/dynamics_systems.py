"""Small dynamic systems of the dynamics tests (a hanging chain, a corotated sheet), their
derivative checks, the one-thread fixture and the one-line error check."""
from __future__ import annotations

import numpy as np
import torch

from torchfit.mesh import rectangle_triangles
from torchfit.physics import ScalarSpringNetwork
from torchfit.physics.dynamics import DynamicSystem, KeyedMotion
from torchfit.physics.elasticity import SimplicialElasticity
from torchfit.residual import ResidualFunction
from torchfit.verification import dot_product_test, random_direction, taylor_test


DT = torch.float64


def chain_system(n: int = 6, stiffness: float = 30.0, loads=None, x0=None,
                 density_scale: float | None = None) -> tuple[DynamicSystem, torch.Tensor]:
    """A hanging chain of ``n`` springs released at rest length, with an eased end load;
    ``density_scale``: the parameters end with it (a density-scaled system)."""
    nodes = torch.arange(n + 1)
    springs = ScalarSpringNetwork(torch.stack([nodes[:-1], nodes[1:]], 1),
                            torch.full((n,), 1.0 / n, dtype=DT), torch.zeros(1, n + 1, dtype=DT))
    end = torch.zeros(2, n + 1, dtype=DT)
    end[1, n] = 1.5
    if loads is None:
        loads = KeyedMotion(torch.tensor([0.1, 0.3], dtype=DT), end)
    rest = nodes.to(DT) / n
    system = DynamicSystem(springs, n, torch.full((n + 1,), 1.0 / n, dtype=DT), torch.tensor([0]),
                           KeyedMotion(torch.zeros(1, dtype=DT), torch.zeros(1, 1, dtype=DT)),
                           loads, torch.full((n + 1,), 9.81, dtype=DT),
                           rest if x0 is None else x0, vertex_dim=1,
                           density_scaled=density_scale is not None)
    k = stiffness * (1.0 + 0.5 * torch.sin(torch.arange(n, dtype=DT)))
    scale = [] if density_scale is None else [density_scale]
    return system, torch.cat([k, torch.tensor([0.8, 2e-3, *scale], dtype=DT)])


def sheet_system(material: str = "corotated") -> tuple[DynamicSystem, torch.Tensor]:
    """A 6 x 2 sheet, left edge held, right edge moved by a keyed translation that stops."""
    mesh = rectangle_triangles(6, 2, 1.0, 0.3)
    model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                 material, nu=0.3)
    left, right = mesh.boundary_vertices("left"), mesh.boundary_vertices("right")
    dirichlet = np.sort(np.concatenate([left, right]))
    fixed = torch.as_tensor((dirichlet[:, None] * 2 + np.arange(2)).reshape(-1))
    rest = model.rest.points.to(DT)
    moving = torch.as_tensor(np.isin(dirichlet, right), dtype=DT)[:, None]
    base = rest[torch.as_tensor(dirichlet)]
    shift = torch.tensor([[0.0, 0.0], [0.15, 0.1]], dtype=DT)
    keys = base[None] + shift[:, None, :] * moving[None]
    mass = torch.zeros(model.n_vertices, dtype=DT).index_add(
        0, torch.as_tensor(mesh.cells.reshape(-1)),
        (model.rest.volumes.to(DT) / 3.0).repeat_interleave(3)).repeat_interleave(2)
    system = DynamicSystem(model, model.n_cells, mass, fixed,
                           KeyedMotion(torch.tensor([0.0, 0.2], dtype=DT), keys.reshape(2, -1)),
                           None, torch.zeros(model.n_dofs, dtype=DT), rest.reshape(-1),
                           vertex_dim=2)
    E = 2.0 + torch.rand(model.n_cells, generator=torch.Generator().manual_seed(1), dtype=DT)
    return system, torch.cat([E, torch.tensor([0.5, 3e-3], dtype=DT)])


def residual_of(integrator, params: torch.Tensor) -> tuple[ResidualFunction, torch.Tensor]:
    """``theta = log params`` -> every position at the output times, data offset from it."""
    def forward(theta: torch.Tensor) -> torch.Tensor:
        return integrator(torch.exp(theta)).reshape(-1)

    theta = torch.log(params)
    data = forward(theta).detach() + 0.01
    return ResidualFunction(forward, data), theta


def check_derivatives(integrator, params: torch.Tensor, *, taylor_steps: int = 18):
    residual, theta = residual_of(integrator, params)
    generator = torch.Generator().manual_seed(3)
    point = theta + 0.1 * random_direction(theta.numel(), generator, theta)
    lin = residual.linearize(point)
    v = random_direction(theta.numel(), generator, theta)
    w = random_direction(residual.size, generator, theta)
    dot = dot_product_test(lin, v, w)
    taylor = taylor_test(residual, point, v, lin=lin, n_steps=taylor_steps)
    return taylor, dot


def one_line(error: BaseException) -> str:
    text = str(error)
    assert "\n" not in text and text
    return text
