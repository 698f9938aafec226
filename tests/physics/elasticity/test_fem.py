"""Simplicial FEM: forces are the energy's gradient, tangents its Hessian (exact, at rest,
projected), rigid rotations, bad rest elements and moduli named."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchfit.mesh import MeshError, box_tetrahedra, rectangle_triangles
from torchfit.physics.elasticity import MaterialError, SimplicialElasticity

from helpers.elastic_models import MODELS, make_model, random_deformation, rotation_matrix


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("material", MODELS)
def test_forces_are_autograd_of_energy(dim, material):
    model, _ = make_model(dim, material)
    E = torch.rand(model.n_cells) + 0.5
    x = random_deformation(model).requires_grad_(True)
    (grad,) = torch.autograd.grad(model.energy(x, E).sum(), x)
    forces = model.forces(x.detach(), E)
    assert torch.allclose(-grad, forces, rtol=0, atol=1e-12 * float(forces.abs().max()))


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("material", MODELS)
def test_tangent_matches_finite_differences_of_forces(dim, material):
    model, _ = make_model(dim, material)
    E = torch.rand(model.n_cells) + 0.5
    x = random_deformation(model, frames=2, seed=1)
    values = model.tangent_pattern.assemble(model.tangent_values(x, E))
    g = torch.Generator().manual_seed(2)
    for frame in range(2):
        K = model.tangent_pattern.to_scipy(values[min(frame, values.shape[0] - 1)]).toarray()
        assert np.abs(K - K.T).max() <= 1e-12 * np.abs(K).max()
        for _ in range(3):
            v = torch.randn(model.n_dofs, generator=g)
            h = 1e-6
            fd = (model.residual(x[frame:frame + 1] + h * v, E)
                  - model.residual(x[frame:frame + 1] - h * v, E))[0] / (2 * h)
            Kv = torch.from_numpy(K) @ v
            assert float((fd - Kv).norm() / Kv.norm()) < 1e-7


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("material", MODELS)
def test_rest_tangent_is_linear_elasticity(dim, material):
    """At the rest shape every model has the tangent of linear elasticity."""
    model, _ = make_model(dim, material)
    linear, _ = make_model(dim, "linear")
    E = torch.rand(model.n_cells) + 0.5
    rest = model.rest.points.reshape(1, -1)
    assert torch.allclose(model.tangent_values(rest, E), linear.tangent_values(rest, E),
                          atol=1e-12)
    assert float(model.residual(rest, E).abs().max()) < 1e-13
    assert float(model.energy(rest, E).abs().max()) < 1e-13


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("material", ["corotated", "stable_neo_hookean"])
def test_projected_tangent_is_positive_semidefinite(dim, material):
    model, _ = make_model(dim, material)
    E = torch.rand(model.n_cells) + 0.5
    # strong compression: element Hessians become indefinite
    x = (model.rest.points @ (0.6 * torch.eye(dim)).T).reshape(1, -1)
    x = x + 0.05 * torch.randn(x.shape, generator=torch.Generator().manual_seed(3))
    A = model.stress_derivative(x, E)
    d2 = dim * dim
    exact_eigs = torch.linalg.eigvalsh(A.reshape(-1, d2, d2))
    assert float(exact_eigs.min()) < -1e-3          # the projection has work to do
    A_proj = model.stress_derivative(x, E, projected=True)
    eigs = torch.linalg.eigvalsh(A_proj.reshape(-1, d2, d2))
    assert float(eigs.min()) >= -1e-12 * float(eigs.abs().max())
    K = model.tangent_pattern.to_scipy(model.tangent_pattern.assemble(
        model.tangent_values(x, E, projected=True))[0]).toarray()
    assert np.linalg.eigvalsh(K).min() >= -1e-10 * np.abs(K).max()
    # unchanged where already positive definite
    rest = model.rest.points.reshape(1, -1)
    assert torch.equal(model.stress_derivative(rest, E, projected=True),
                       model.stress_derivative(rest, E))


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("material", ["corotated", "stable_neo_hookean"])
def test_rigid_rotation_gives_zero_force_and_finite_gradient(dim, material):
    model, _ = make_model(dim, material)
    E = torch.rand(model.n_cells) + 0.5
    Q = rotation_matrix(dim)
    x = (model.rest.points @ Q.T + torch.arange(1, dim + 1) * 0.3).reshape(1, -1)
    forces = model.forces(x, E)
    assert float(forces.abs().max()) < 1e-10
    assert float(model.energy(x, E).abs().max()) < 1e-10
    # gradients at the rest shape (repeated singular values) are finite
    rest = model.rest.points.reshape(1, -1).clone().requires_grad_(True)
    Ev = E.clone().requires_grad_(True)
    energy = model.energy(rest, Ev).sum()
    grad_x, = torch.autograd.grad(energy, rest, create_graph=True)
    assert torch.isfinite(grad_x).all() and float(grad_x.detach().abs().max()) < 1e-12
    hess_row, grad_E = torch.autograd.grad(grad_x[0, -1], (rest, Ev))
    assert torch.isfinite(hess_row).all() and torch.isfinite(grad_E).all()
    force_grad, = torch.autograd.grad(model.residual(rest, Ev).sum(), Ev)
    assert torch.isfinite(force_grad).all()


def test_inverted_and_degenerate_rest_elements_are_named():
    mesh = rectangle_triangles(3, 2)
    cells = mesh.cells.copy()
    cells[4] = cells[4][[0, 2, 1]]                     # inverted
    with pytest.raises(MeshError, match=r"inverted.*element\(s\): 4 "):
        SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(cells))
    points = mesh.points.copy()
    cells = mesh.cells.copy()
    cells[7] = [0, 1, 2]                               # collinear vertices (bottom row)
    with pytest.raises(MeshError, match=r"degenerate.*element\(s\): 7 "):
        SimplicialElasticity(torch.from_numpy(points), torch.from_numpy(cells))
    tets = box_tetrahedra(1, 1, 1)
    bad = tets.cells.copy()
    bad[2] = bad[2][[1, 0, 2, 3]]
    with pytest.raises(MeshError, match=r"inverted.*: 2 "):
        SimplicialElasticity(torch.from_numpy(tets.points), torch.from_numpy(bad))


def test_non_positive_modulus_is_named():
    model, _ = make_model(2, "corotated")
    E = torch.ones(model.n_cells)
    E[5] = -0.5
    with pytest.raises(MaterialError, match="element 5 has E = -0.5"):
        model.residual(model.rest.points.reshape(1, -1), E)
    E[5] = 0.0
    with pytest.raises(MaterialError, match="element 5"):
        model.energy(model.rest.points.reshape(1, -1), E)
