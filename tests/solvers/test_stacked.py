"""Stacked, linear and cached residuals (the inner problem of split Bregman)."""
import math

import pytest
import torch

from torchfit.params import grid_edges, per_element
from torchfit.solvers import ResidualFunction
from torchfit.solvers.stacked import CachedResidual, LinearResidual, StackedResidual


def test_stacked_residual_products_are_adjoint_and_cached():
    torch.manual_seed(0)
    A = torch.randn(7, 5)
    model = ResidualFunction(lambda th: torch.tanh(A @ th), torch.randn(7))
    D = per_element(5, grid_edges((5,))).difference_operator()
    cached = CachedResidual(model)
    stacked = StackedResidual([cached, LinearResidual(D, torch.randn(4))], [3.0, 0.5])
    theta = torch.randn(5)
    lin = stacked.linearize(theta)
    v, w = torch.randn(5), torch.randn(11)
    assert float(torch.dot(lin.jvp(v), w)) == pytest.approx(float(torch.dot(v, lin.vjp(w))),
                                                            rel=1e-12)
    assert torch.allclose(lin.r, stacked.value(theta))
    expected = torch.cat([math.sqrt(3.0) * model.value(theta),
                          math.sqrt(0.5) * (torch.mv(D, theta) - stacked.blocks[1].target)])
    assert torch.allclose(lin.r, expected)
    stacked.linearize(theta.clone())
    assert cached.evaluations == 1                       # same point: no new simulation
