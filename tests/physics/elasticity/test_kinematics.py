"""Kinematics: the polar rotation (closest rotation, finite derivatives at repeated singular
values) and the closed-form / fixed-iteration small decompositions against LAPACK."""
from __future__ import annotations

import pytest
import torch

from torchfit.physics.elasticity.kinematics import (PolarRotation3, det2, det3, polar_rotation,
                                                    solve_sym3, sym_eig2, sym_eig3)

from helpers.decompositions import DT, hard_batch
from helpers.elastic_models import rotation_matrix


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


@pytest.mark.parametrize("d", [2, 3])
def test_symmetric_eigen_matches_lapack(d):
    F = hard_batch(d, seed=3)
    S = F.transpose(-1, -2) @ F                     # PSD with repeated/zero eigenvalues
    g = torch.Generator().manual_seed(4)
    B = torch.randn(300, d, d, dtype=DT, generator=g)
    S = torch.cat([S, B + B.transpose(-1, -2)])      # indefinite
    values, V = (sym_eig2 if d == 2 else sym_eig3)(S)
    reference = torch.linalg.eigvalsh(S).flip(-1)
    scale = S.abs().amax(dim=(-2, -1)).clamp(min=1e-300)
    assert bool(((values - reference).abs().amax(-1) <= 1e-14 * scale + 1e-300).all())
    assert torch.allclose(V @ torch.diag_embed(values) @ V.transpose(-1, -2), S,
                          atol=1e-13, rtol=1e-14)
    assert torch.allclose(V.transpose(-1, -2) @ V, torch.eye(d, dtype=DT).expand_as(V),
                          atol=1e-14)
    assert torch.allclose(torch.linalg.det(V), torch.ones(len(S), dtype=DT), atol=1e-14)
    # a diagonal matrix is left exactly as it is
    D = torch.diag_embed(torch.tensor([[3.0] + [2.0] * (d - 1)], dtype=DT))
    values, V = (sym_eig2 if d == 2 else sym_eig3)(D)
    assert torch.equal(V[0], torch.eye(d, dtype=DT))


def test_determinants_and_symmetric_solve_match_lapack():
    g = torch.Generator().manual_seed(5)
    M3 = torch.randn(500, 3, 3, dtype=DT, generator=g)
    M2 = torch.randn(500, 2, 2, dtype=DT, generator=g)
    assert torch.allclose(det3(M3), torch.linalg.det(M3), atol=1e-14)
    assert torch.allclose(det2(M2), torch.linalg.det(M2), atol=1e-15)
    K = M3 @ M3.transpose(-1, -2) + 0.1 * torch.eye(3, dtype=DT)
    rhs = torch.randn(500, 3, dtype=DT, generator=g)
    x = solve_sym3(K, rhs)
    assert torch.allclose(x, torch.linalg.solve(K, rhs), rtol=1e-10, atol=1e-12)
    assert torch.allclose((K @ x[..., None])[..., 0], rhs, atol=1e-11)


def test_polar_backward_is_finite_at_repeated_singular_values_and_matches_autograd_of_svd():
    g = torch.Generator().manual_seed(6)
    F = (torch.eye(3, dtype=DT) + 0.3 * torch.randn(20, 3, 3, dtype=DT, generator=g))
    # away from repeated singular values the SVD's own autograd is a valid reference
    F_ref = F.clone().requires_grad_(True)
    U, _, Vh = torch.linalg.svd(F_ref)
    sign = torch.sign(torch.linalg.det(U @ Vh))
    R_ref = U @ torch.diag_embed(torch.stack([torch.ones_like(sign), torch.ones_like(sign), sign], -1)) @ Vh
    W = torch.randn(20, 3, 3, dtype=DT, generator=g)
    (grad_ref,) = torch.autograd.grad((R_ref * W).sum(), F_ref)
    F_new = F.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad((PolarRotation3.apply(F_new) * W).sum(), F_new)
    assert torch.allclose(grad, grad_ref, atol=1e-11)
    for F0 in (torch.eye(3, dtype=DT), torch.diag(torch.tensor([2.0, 2.0, 0.5], dtype=DT)),
               torch.diag(torch.tensor([1.0, 1.0, -0.5], dtype=DT))):   # inverted, repeated
        F0 = F0.clone().requires_grad_(True)
        (grad,) = torch.autograd.grad((polar_rotation(F0) * W[0]).sum(), F0)
        assert torch.isfinite(grad).all()


@pytest.mark.parametrize("d", [2, 3])
def test_rest_shape_in_closed_form_matches_lapack_and_names_bad_cells(d):
    """Volumes, ``D_m^{-1}`` and the shape-function gradients by triple and cross products
    equal numpy's batched ``det``/``inv`` to round-off on a jittered mesh; an inverted cell
    is a MeshError naming it (the host check's message); float32 is cast at the end."""
    import math

    import numpy as np

    from torchfit.mesh import MeshError, box_tetrahedra
    from torchfit.physics.elasticity.kinematics import RestShape

    if d == 3:
        mesh = box_tetrahedra(5, 4, 3, (1.0, 1.0, 1.0))
        points, cells = mesh.points, mesh.cells
    else:
        xs, ys = np.meshgrid(np.linspace(0, 1, 6), np.linspace(0, 1, 5))
        points = np.stack([xs.ravel(), ys.ravel()], 1)
        quads = np.array([[j * 6 + i, j * 6 + i + 1, (j + 1) * 6 + i + 1, (j + 1) * 6 + i]
                          for j in range(4) for i in range(5)])
        cells = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    points = points + 0.03 * np.random.default_rng(0).standard_normal(points.shape)
    rest = RestShape(points, cells)
    dm = np.transpose(points[cells][:, 1:] - points[cells][:, :1], (0, 2, 1))
    dm_inv = np.linalg.inv(dm)
    scale = np.abs(dm_inv).max()
    assert np.abs(rest.dm_inv.numpy() - dm_inv).max() <= 1e-14 * scale
    assert np.allclose(rest.volumes.numpy(), np.linalg.det(dm) / math.factorial(d),
                       rtol=1e-13, atol=0)
    grads = np.concatenate([-dm_inv.sum(axis=1, keepdims=True), dm_inv], axis=1)
    assert np.abs(rest.grads.numpy() - grads).max() <= 1e-14 * scale
    single = RestShape(points, cells, dtype=torch.float32)
    assert single.grads.dtype == torch.float32
    assert torch.allclose(single.grads.double(), rest.grads, rtol=1e-6, atol=1e-6 * scale)
    flipped = cells.copy()
    flipped[3, [0, 1]] = flipped[3, [1, 0]]
    with pytest.raises(MeshError, match=r"1 inverted .* element\(s\): 3 \(vertices"):
        RestShape(points, flipped)
