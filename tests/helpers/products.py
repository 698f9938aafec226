"""A problem's explicit derivative products against its autograd ones (the reference)."""
from __future__ import annotations

import torch


def explicit_and_autograd(problem, seed: int):
    """``problem``'s linearisations with explicit products and with autograd products (the
    reference) at ``theta0 + 0.3 * xi``, and random directions ``v`` (parameters) and ``w``
    (data): ``(theta, lin, reference, v, w)``."""
    g = torch.Generator().manual_seed(seed)
    theta = problem.theta0 + 0.3 * torch.randn(problem.theta0.shape, generator=g,
                                               dtype=torch.float64)
    explicit, autograd = problem.residual(), problem.residual(explicit_products=False)
    assert explicit.products is not None and autograd.products is None
    lin, reference = explicit.linearize(theta), autograd.linearize(theta)
    v = torch.randn(theta.shape, generator=g, dtype=torch.float64)
    w = torch.randn(lin.r.shape, generator=g, dtype=torch.float64)
    return theta, lin, reference, v, w
