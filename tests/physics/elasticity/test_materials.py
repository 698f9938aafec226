"""The materials: names and defaults, the rotation-variant SVD against LAPACK, the SVD memo
shared by Newton."""
from __future__ import annotations

import math

import pytest
import torch

from torchfit.mesh import rectangle_triangles
from torchfit.physics.elasticity import MaterialError, SimplicialElasticity, get_material
from torchfit.physics.elasticity.kinematics import (polar_rotation, rotation_variant_svd, svd2,
                                                    svd3)

from helpers.decompositions import DT, hard_batch


def test_unknown_model_and_defaults():
    with pytest.raises(MaterialError, match="stable_neo_hookean"):
        get_material("mooney")
    assert get_material("neo_hookean").name == "stable_neo_hookean"
    mesh = rectangle_triangles(2, 1)
    model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                 "corotated")
    assert model.nu == 0.475                            # PhysBAM's default


@pytest.mark.parametrize("d", [2, 3])
def test_rotation_variant_svd_matches_lapack(d):
    F = hard_batch(d)
    U, sigma, Vh = (svd2 if d == 2 else svd3)(F)
    eye = torch.eye(d, dtype=DT).expand_as(U)
    assert torch.allclose(U @ torch.diag_embed(sigma) @ Vh, F, atol=2e-14, rtol=0)
    assert torch.allclose(U.transpose(-1, -2) @ U, eye, atol=1e-14)
    assert torch.allclose(Vh @ Vh.transpose(-1, -2), eye, atol=1e-14)
    assert torch.allclose(torch.linalg.det(U), torch.ones(len(F), dtype=DT), atol=1e-14)
    assert torch.allclose(torch.linalg.det(Vh), torch.ones(len(F), dtype=DT), atol=1e-14)
    # |sigma| are LAPACK's singular values; the sign of the last one is that of det F
    reference = torch.linalg.svdvals(F)
    assert torch.allclose(sigma.abs().sort(-1, descending=True).values, reference, atol=1e-14)
    assert bool((sigma[:, :-1] >= 0).all())
    assert bool((sigma[:, 0] >= sigma[:, -1].abs() - 1e-15).all())
    det = torch.linalg.det(F)
    clear = det.abs() > 1e-10
    assert torch.equal(torch.sign(sigma.prod(-1))[clear], torch.sign(det)[clear])
    # and the rotations agree with the sign-fixed LAPACK ones where the SVD is unique
    if d == 2:
        U_ref, s_ref, Vh_ref = torch.linalg.svd(F[:500])
        distinct = (s_ref[:, 0] - s_ref[:, 1]) > 1e-3
        R = U @ Vh
        R_ref = polar_rotation(F[:500])
        assert torch.allclose(R[:500][distinct], R_ref[distinct], atol=1e-13)


def test_rotation_variant_svd_2d_is_closed_form_and_3d_is_jacobi():
    F = hard_batch(2)
    U, sigma, Vh = rotation_variant_svd(F)
    U2, sigma2, Vh2 = svd2(F)
    assert torch.equal(U, U2) and torch.equal(sigma, sigma2) and torch.equal(Vh, Vh2)
    with pytest.raises(ValueError, match="d = 2 or 3"):
        rotation_variant_svd(torch.eye(4, dtype=DT)[None])
    assert math.isclose(float(svd2(torch.eye(2, dtype=DT)[None])[1].sum()), 2.0)


def test_svd_memo_serves_repeated_frames_bit_for_bit_and_decomposes_only_new_ones():
    from torchfit.physics.elasticity.materials import SVDMemo

    g = torch.Generator().manual_seed(5)
    frames = torch.eye(3, dtype=DT) + 0.4 * torch.randn(6, 50, 3, 3, dtype=DT, generator=g)
    frames[2, :, :, 0] *= -1                                 # an inverted frame
    memo = SVDMemo()
    first = memo(frames)
    reference = rotation_variant_svd(frames)
    assert all(torch.equal(a, b) for a, b in zip(first, reference))
    assert (memo.hits, memo.misses) == (0, 6)
    # Newton's next tangent: a subset of the frames the line search just evaluated
    subset = memo(frames[[1, 2, 4]])
    assert (memo.hits, memo.misses) == (3, 6)
    assert all(torch.equal(a, b[[1, 2, 4]]) for a, b in zip(subset, reference))
    # a moved frame (any bit) is decomposed afresh, the others still come from the memo
    moved = frames[[0, 3]].clone()
    moved[1, 7, 1, 2] += 1e-15
    mixed = memo(moved)
    assert (memo.hits, memo.misses) == (4, 7)
    assert all(torch.equal(a, b) for a, b in zip(mixed, rotation_variant_svd(moved)))
    # one frame without a frame dimension; a tensor with a graph is never stored
    single = memo(frames[5])
    assert memo.hits == 5 and all(torch.equal(a, b[5]) for a, b in zip(single, reference))
    memo(frames.clone().requires_grad_(True))
    assert (memo.hits, memo.misses) == (5, 7)
    # bounded: at most capacity x the largest batch (6 frames) are kept
    for shift in range(1, 5):
        memo(frames + shift)
    assert len(memo._frames) <= memo.capacity * 6


def test_corotated_newton_reuses_the_line_search_decomposition_for_its_tangent():
    from helpers.tetbox import clamped_box

    model, qs, bottom, top = clamped_box((2, 2, 3), (0.5, 0.5, 1.0), "corotated", atol=1e-15)
    X = model.rest.points
    positions = torch.cat([X[bottom], X[top] + torch.tensor([0.2, 0.0, 0.25], dtype=DT)])[None]
    memo = model.material.svd_memo
    qs(torch.ones(model.n_cells, dtype=DT), positions)
    iterations = sum(qs.last_newton_iterations)
    assert iterations >= 3
    # every tangent (one per Newton iteration, and the adjoint's at the solution) is at a
    # point the residual was just evaluated at
    assert memo.hits >= iterations + 1
