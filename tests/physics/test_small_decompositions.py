"""The closed-form / fixed-iteration 2x2 and 3x3 decompositions of the materials against
torch.linalg (LAPACK): random, repeated, inverted, near-degenerate and collapsed batches."""
from __future__ import annotations

import math

import pytest
import torch

from torchfit.physics.elasticity.kinematics import (PolarRotation3, det2, det3, polar_rotation,
                                                    solve_sym3, svd2, svd3, sym_eig2, sym_eig3)
from torchfit.physics.elasticity.materials import (StableNeoHookean, lame_parameters,
                                                   project_psd, rotation_variant_svd)

DT = torch.float64


def rotation(d: int, seed: int, n: int = 1) -> torch.Tensor:
    """``n`` random ``d x d`` rotations (``det = +1``)."""
    g = torch.Generator().manual_seed(seed)
    Q, _ = torch.linalg.qr(torch.randn(n, d, d, dtype=DT, generator=g))
    Q[..., :, 0] *= torch.sign(torch.linalg.det(Q))[:, None]
    return Q


def hard_batch(d: int, seed: int = 0) -> torch.Tensor:
    """Random, inverted, repeated, nearly repeated, opposite, rank-deficient and zero
    matrices, each also rotated on both sides."""
    g = torch.Generator().manual_seed(seed)
    random = torch.eye(d, dtype=DT) + 0.5 * torch.randn(400, d, d, dtype=DT, generator=g)
    inverted = random[:100].clone()
    inverted[:, :, 0] *= -1
    diagonals = [[1.0] * d, [2.0] * d, [1.0] * (d - 1) + [-1.0], [1.0 + 1e-9] + [1.0] * (d - 1),
                 [3.0] + [1e-12] * (d - 1), [1.0] * (d - 1) + [0.0], [0.0] * d,
                 [-1.0] * d, [1.0, 1.0 - 1e-13] + [0.5] * (d - 2), [1e-8] * d]
    special = torch.diag_embed(torch.tensor(diagonals, dtype=DT))
    n = special.shape[0]
    rotated = rotation(d, seed + 1, n) @ special @ rotation(d, seed + 2, n).transpose(-1, -2)
    return torch.cat([random, inverted, special, rotated])


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
def test_neo_hookean_eigensystem_and_projection_match_eigh(d):
    F = hard_batch(d, seed=7)
    F = torch.cat([F, 0.6 * torch.eye(d, dtype=DT) + 0.05 * F[:200]])   # compressed: indefinite
    n = F.shape[0]
    material = StableNeoHookean()
    E = torch.rand(n, dtype=DT, generator=torch.Generator().manual_seed(8)) + 0.5
    mu, lam = lame_parameters(E, 0.3)
    A = material.stress_derivative(F, mu, lam)
    values, modes = material.eigensystem(F, mu, lam)
    d2 = d * d
    flat = modes.reshape(n, d2, d2)
    assert torch.allclose(flat @ flat.transpose(-1, -2), torch.eye(d2, dtype=DT).expand(n, -1, -1),
                          atol=1e-13)
    reconstructed = torch.einsum("nm,nmij,nmkl->nijkl", values, modes, modes)
    scale = A.abs().amax()
    assert float((reconstructed - A).abs().max()) < 1e-14 * float(scale) * 10
    reference = torch.linalg.eigvalsh(A.reshape(n, d2, d2))
    assert torch.allclose(values.sort(-1).values, reference, atol=1e-13 * float(scale))
    projected = material.stress_derivative(F, mu, lam, projected=True)
    indefinite = reference.amin(-1) < -1e-6
    assert int(indefinite.sum()) > 50              # the projection has work to do
    assert torch.allclose(projected, project_psd(A), atol=1e-13 * float(scale))
    # unchanged (bit for bit) where nothing is negative
    assert torch.equal(projected[~indefinite & (reference.amin(-1) > 0)],
                       A[~indefinite & (reference.amin(-1) > 0)])


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
    from tetbox import clamped_box

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
