"""The material contract's shared pieces: the generic PSD projection, Poisson ratios."""
from __future__ import annotations

import pytest
import torch

from torchfit.mesh import rectangle_triangles
from torchfit.physics.elasticity import MaterialError, SimplicialElasticity
from torchfit.physics.elasticity.material_base import project_psd


def test_project_psd_clamps_only_negative_eigenvalues():
    g = torch.Generator().manual_seed(0)
    M = torch.randn(5, 4, 4, generator=g)
    M = M + M.transpose(-1, -2)
    P = project_psd(M.reshape(5, 2, 2, 2, 2)).reshape(5, 4, 4)
    w, V = torch.linalg.eigh(M)
    expected = (V * w.clamp(min=0)[:, None, :]) @ V.transpose(-1, -2)
    assert torch.allclose(P, expected, atol=1e-12)


@pytest.mark.parametrize("nu", [0.5, -1.0, 0.7, float("nan")])
def test_poisson_ratio_outside_range_is_rejected(nu):
    mesh = rectangle_triangles(2, 1)
    with pytest.raises(MaterialError, match=r"\(-1, 0.5\)"):
        SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                             "corotated", nu=nu)
