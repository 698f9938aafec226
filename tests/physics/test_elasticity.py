"""Simplicial FEM elasticity: energies, forces, tangents, patch tests, invariance, bad input."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchfit.linalg import counting
from torchfit.mesh import MeshError, box_tetrahedra, rectangle_triangles
from torchfit.physics import NewtonConvergenceError, NewtonOptions
from torchfit.physics.elasticity import (MATERIALS, DirichletDataError, MaterialError,
                                         PolarRotation3, QuasistaticElasticity,
                                         SimplicialElasticity, get_material, polar_rotation,
                                         project_psd)

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


# -- forces, tangents, projection -------------------------------------------------------------
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


def test_project_psd_clamps_only_negative_eigenvalues():
    g = torch.Generator().manual_seed(0)
    M = torch.randn(5, 4, 4, generator=g)
    M = M + M.transpose(-1, -2)
    P = project_psd(M.reshape(5, 2, 2, 2, 2)).reshape(5, 4, 4)
    w, V = torch.linalg.eigh(M)
    expected = (V * w.clamp(min=0)[:, None, :]) @ V.transpose(-1, -2)
    assert torch.allclose(P, expected, atol=1e-12)


# -- polar decomposition ------------------------------------------------------------------------
def test_polar_rotation_3d_derivatives_and_rest_shape():
    g = torch.Generator().manual_seed(0)
    F = (torch.eye(3) + 0.3 * torch.randn(4, 3, 3, generator=g)).requires_grad_(True)
    assert torch.autograd.gradcheck(PolarRotation3.apply, (F,))
    assert torch.autograd.gradgradcheck(PolarRotation3.apply, (F,))
    # repeated singular values (rest shape, pure rotation): finite, and zero for a rotation
    Q = rotation_matrix(3)
    for F0 in (torch.eye(3), Q, 2.0 * Q):
        F0 = F0.clone().requires_grad_(True)
        R = polar_rotation(F0)
        (grad,) = torch.autograd.grad((R * torch.randn(3, 3, generator=g)).sum(), F0)
        assert torch.isfinite(grad).all()
    # a naive SVD backward is NaN there, which is why the custom derivative exists
    F0 = torch.eye(3, requires_grad=True)
    U, _, Vh = torch.linalg.svd(F0)
    (naive,) = torch.autograd.grad((U @ Vh)[0, 1], F0)
    assert not torch.isfinite(naive).all()


def test_polar_rotation_is_the_closest_rotation_also_when_inverted():
    g = torch.Generator().manual_seed(1)
    for d in (2, 3):
        F = torch.eye(d) + 0.4 * torch.randn(50, d, d, generator=g)
        F[:10, :, 0] *= -1                     # some inverted
        R = polar_rotation(F)
        eye = torch.eye(d).expand_as(R)
        assert torch.allclose(R.transpose(-1, -2) @ R, eye, atol=1e-12)
        assert torch.allclose(torch.linalg.det(R), torch.ones(50), atol=1e-12)
        S = R.transpose(-1, -2) @ F
        assert torch.allclose(S, S.transpose(-1, -2), atol=1e-12)


# -- rotation invariance ------------------------------------------------------------------------
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


# -- patch test ---------------------------------------------------------------------------------
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


# -- the quasistatic solve ----------------------------------------------------------------------
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


# -- bad input ----------------------------------------------------------------------------------
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


@pytest.mark.parametrize("nu", [0.5, -1.0, 0.7, float("nan")])
def test_poisson_ratio_outside_range_is_rejected(nu):
    mesh = rectangle_triangles(2, 1)
    with pytest.raises(MaterialError, match=r"\(-1, 0.5\)"):
        SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                             "corotated", nu=nu)


def test_unknown_model_and_defaults():
    with pytest.raises(MaterialError, match="stable_neo_hookean"):
        get_material("mooney")
    assert get_material("neo_hookean").name == "stable_neo_hookean"
    mesh = rectangle_triangles(2, 1)
    model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                 "corotated")
    assert model.nu == 0.475                            # PhysBAM's default


def test_non_positive_modulus_is_named():
    model, _ = make_model(2, "corotated")
    E = torch.ones(model.n_cells)
    E[5] = -0.5
    with pytest.raises(MaterialError, match="element 5 has E = -0.5"):
        model.residual(model.rest.points.reshape(1, -1), E)
    E[5] = 0.0
    with pytest.raises(MaterialError, match="element 5"):
        model.energy(model.rest.points.reshape(1, -1), E)


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
