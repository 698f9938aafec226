"""Stable neo-Hookean: its analytic eigensystem and PSD projection against LAPACK."""
from __future__ import annotations

import pytest
import torch

from torchfit.physics.elasticity.material_base import lame_parameters, project_psd
from torchfit.physics.elasticity.stable_neo_hookean import StableNeoHookean

from helpers.decompositions import DT, hard_batch


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
