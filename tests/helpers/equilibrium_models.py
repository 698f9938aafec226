"""Small equilibrium models of the equilibrium tests (a hardening spring chain, a double
well) and the reference derivatives they are checked against."""
from __future__ import annotations

import torch
import torch.autograd.forward_ad as fwAD

from torchfit.linalg import SparsePattern
from torchfit.physics import Equilibrium, NewtonOptions


class HardeningChain:
    """Springs with tension ``k (s + c s^3)`` (s = stretch): non-linear, frame-dependent tangent."""

    linear = False
    symmetric = True

    def __init__(self, n: int, loads: torch.Tensor, c: float = 50.0) -> None:
        self.n_dofs = n + 1
        self.c = c
        self.a = torch.arange(n)
        self.b = self.a + 1
        self.rest = torch.full((n,), 1.0 / n)
        self.external = torch.zeros(loads.numel(), n + 1)
        self.external[:, 1:] = 0.5 / n
        self.external[:, n] += loads
        rows = torch.stack([self.a, self.a, self.b, self.b], 1).reshape(-1)
        cols = torch.stack([self.a, self.b, self.a, self.b], 1).reshape(-1)
        self.tangent_pattern = SparsePattern(rows, cols, (n + 1, n + 1))

    def _stretch(self, x):
        return x[:, self.b] - x[:, self.a] - self.rest

    def residual(self, x, k):
        s = self._stretch(x)
        t = k * (s + self.c * s ** 3)
        return x.new_zeros(x.shape).index_add(1, self.b, t).index_add(1, self.a, -t) - self.external

    def tangent_values(self, x, k):
        s = self._stretch(x)
        d = k * (1 + 3 * self.c * s ** 2)
        return torch.stack([d, -d, -d, d], dim=-1).reshape(x.shape[0], -1)


def make_hardening(n=12):
    """``(model, eq, fixed)``: a hardening chain of ``n`` springs, 3 load cases, node 0 fixed."""
    model = HardeningChain(n, torch.tensor([0.0, 0.3, 1.0]))
    eq = Equilibrium(model, torch.tensor([0]), newton=NewtonOptions(rtol=1e-13, atol=1e-14))
    return model, eq, torch.zeros(3, 1)


class DoubleWell:
    """One free dof in the energy ``x^4 / 4 - x^2 / 2 - a x``: two stable equilibria (near
    -1 and +1) while ``|a| < 0.385``, one beyond. Dof 0 is a fixed dummy."""

    linear = False
    symmetric = True
    n_dofs = 2
    tangent_pattern = SparsePattern(torch.tensor([0, 1]), torch.tensor([0, 1]), (2, 2))

    def residual(self, x, a):
        free = x[:, 1:] ** 3 - x[:, 1:] - a
        return torch.cat([torch.zeros_like(free), free], dim=1)

    def tangent_values(self, x, a):
        return torch.stack([torch.ones_like(x[:, 1]), 3 * x[:, 1] ** 2 - 1], dim=-1)


def jvp_columns(fn, params, directions):
    """Forward-mode jvps of ``fn`` at ``params`` along every column of ``directions``,
    stacked on a last axis."""
    columns = []
    for j in range(directions.shape[1]):
        with fwAD.dual_level():
            columns.append(fwAD.unpack_dual(fn(fwAD.make_dual(params, directions[:, j]))).tangent)
    return torch.stack(columns, dim=-1)


def relative(a, b):
    """``||a - b|| / ||b||``."""
    return float((a - b).norm() / b.norm())
