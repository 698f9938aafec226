"""Quasistatic frames: the patch test, the adjoint and jvp against finite differences, the
factorisations a forward, a backward and a warm start cost, Dirichlet data and Newton
failures named."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfit.linalg import counting
from torchfit.mesh import box_tetrahedra, rectangle_triangles
from torchfit.physics import NewtonConvergenceError, NewtonOptions
from torchfit.physics.elasticity import (DirichletDataError, QuasistaticElasticity,
                                         SimplicialElasticity)

from helpers.elastic_models import MODELS, make_model


def boundary_solve(model: SimplicialElasticity, mesh, x_exact: torch.Tensor,
                   newton: NewtonOptions | None = None) -> torch.Tensor:
    boundary = mesh.boundary_facet_vertices()
    qs = QuasistaticElasticity(model, boundary, newton=newton or NewtonOptions(rtol=1e-13, atol=1e-14))
    E = torch.full((model.n_cells,), 3.0)
    return qs(E, x_exact[:, torch.as_tensor(boundary)]), qs


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("material", ["linear", "corotated", "stable_neo_hookean"])
def test_patch_test_linear_field_is_reproduced_inside(dim, material):
    if dim == 2:
        model, mesh = make_model(dim, material)
    else:                                   # 3x3x3 cubes: 8 interior vertices
        mesh = box_tetrahedra(3, 3, 3, (1.0, 0.8, 0.9))
        model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                     material, nu=0.3)
    g = torch.Generator().manual_seed(4)
    X = model.rest.points
    frames = []
    for scale in (0.05, 0.3):
        A = torch.eye(dim) + scale * torch.randn(dim, dim, generator=g)
        b = torch.randn(dim, generator=g)
        frames.append(X @ A.T + b)
    x_exact = torch.stack(frames)
    x, qs = boundary_solve(model, mesh, x_exact)
    assert qs.free_vertices.numel() == (6 if dim == 2 else 8)
    error = float((x - x_exact).abs().max())
    assert error <= 1e-10, error


@pytest.mark.parametrize("material", MODELS)
def test_quasistatic_adjoint_and_jvp_match_finite_differences(material):
    mesh = rectangle_triangles(4, 2, 1.0, 0.5)
    model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                 material, nu=0.3)
    left, right = mesh.boundary_vertices("left"), mesh.boundary_vertices("right")
    qs = QuasistaticElasticity(model, np.concatenate([left, right]),
                               newton=NewtonOptions(rtol=1e-13, atol=1e-15))
    X = model.rest.points
    right_pos = torch.stack([X[right] + torch.tensor([0.15, 0.0]), X[right] + torch.tensor([0.1, 0.1]),
                             X[right] - torch.tensor([0.08, 0.0])])
    positions = torch.cat([X[left].expand(3, -1, -1), right_pos], dim=1)
    E = (torch.rand(model.n_cells, generator=torch.Generator().manual_seed(0)) + 0.5).requires_grad_()
    assert torch.autograd.gradcheck(lambda e: qs(e, positions), (E,), atol=1e-7)
    assert torch.autograd.gradcheck(lambda e: qs(e, positions), (E,), check_forward_ad=True,
                                    check_backward_ad=False, check_undefined_grad=False,
                                    check_batched_grad=False, atol=1e-7)


def test_backward_after_forward_needs_no_factorization():
    mesh = rectangle_triangles(6, 2, 1.5, 0.5)
    model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                 "corotated", nu=0.3)
    left, right = mesh.boundary_vertices("left"), mesh.boundary_vertices("right")
    qs = QuasistaticElasticity(model, np.concatenate([left, right]))
    X = model.rest.points
    positions = torch.cat([X[left], X[right] + torch.tensor([0.2, 0.05])])[None].repeat(2, 1, 1)
    positions[1, len(left):, 0] -= 0.3
    E = torch.ones(model.n_cells, requires_grad=True)
    x = qs(E, positions)
    with counting() as count:
        torch.autograd.grad(x, E, torch.randn_like(x))
    assert count.factorizations == 0 and count.solves == 2     # one per frame


def test_warm_start_agrees_with_cold_start():
    mesh = rectangle_triangles(8, 2, 2.0, 0.5)
    model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                 "stable_neo_hookean", nu=0.3)
    left, right = mesh.boundary_vertices("left"), mesh.boundary_vertices("right")
    X = model.rest.points
    positions = torch.cat([X[left], X[right] + torch.tensor([0.3, 0.1])])[None]
    warm = QuasistaticElasticity(model, np.concatenate([left, right]))
    cold = QuasistaticElasticity(model, np.concatenate([left, right]), warm_start=False)
    E0 = torch.ones(model.n_cells)
    E1 = E0 * torch.exp(0.3 * torch.randn(model.n_cells, generator=torch.Generator().manual_seed(0)))
    warm(E0, positions)
    x_warm = warm(E1, positions)
    assert warm.equilibrium.last_warm_started
    x_cold = cold(E1, positions)
    assert not cold.equilibrium.last_warm_started
    assert float((x_warm - x_cold).abs().max()) < 1e-12


def test_linear_model_is_one_factorization_for_all_frames():
    model, mesh = make_model(2, "linear")
    boundary = mesh.boundary_facet_vertices()
    qs = QuasistaticElasticity(model, boundary)
    X = model.rest.points
    positions = torch.stack([X[boundary] * s for s in (1.0, 1.1, 0.9)])
    with counting() as count:
        qs(torch.ones(model.n_cells), positions)
    assert count.factorizations == 1


def test_dirichlet_data_must_match_the_dirichlet_set():
    model, mesh = make_model(2, "corotated")
    boundary = mesh.boundary_facet_vertices()
    qs = QuasistaticElasticity(model, boundary)
    X = model.rest.points
    E = torch.ones(model.n_cells)
    good = X[boundary]
    with pytest.raises(DirichletDataError, match="frame 1"):
        qs(E, [good, good[:-1], good])
    with pytest.raises(DirichletDataError, match="shape"):
        qs(E, good[None, :, :1])
    nan = good.clone()
    nan[2, 0] = float("nan")
    with pytest.raises(DirichletDataError, match=f"frame 1: .*vertex {int(boundary[2])}"):
        qs(E, torch.stack([good, nan]))
    with pytest.raises(DirichletDataError, match="empty"):
        QuasistaticElasticity(model, [])


def test_newton_failure_names_frame_and_residual():
    mesh = rectangle_triangles(6, 2, 1.5, 0.5)
    model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                 "corotated", nu=0.3)
    left, right = mesh.boundary_vertices("left"), mesh.boundary_vertices("right")
    qs = QuasistaticElasticity(model, np.concatenate([left, right]),
                               newton=NewtonOptions(max_iter=1, rtol=1e-14, atol=1e-16))
    X = model.rest.points
    positions = torch.stack([torch.cat([X[left], X[right] + torch.tensor([s, 0.0])])
                             for s in (0.0, 0.4)])
    with pytest.raises(NewtonConvergenceError, match=r"frame 1: residual norm"):
        qs(torch.ones(model.n_cells), positions)
