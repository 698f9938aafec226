"""What a solver sees: a residual ``r(theta)`` with its products ``J v`` and ``J^T w``.

Solvers know nothing of meshes or physics; a problem hands them a
:class:`ResidualFunction` built from any torch function ``theta -> y`` and the data.
Products come from torch autograd through the differentiable simulator, whose custom
adjoints do the work: ``J^T w`` is a reverse pass over one retained graph and ``J v`` a
forward-mode pass (the simulator returns its stored solution for an unchanged
``theta``, so neither product refactorises anything).
"""
from __future__ import annotations

from typing import Callable

import torch
import torch.autograd.forward_ad as fwAD
from torch import Tensor

from .errors import SimulationError


class Linearization:
    """The residual at one ``theta`` and its Jacobian products.

    Attributes:
        theta: ``(n,)`` the point (detached).
        r: ``(m,)`` residual ``forward(theta) - data``.
        norm: ``||r||_2`` as a float.
    """

    def __init__(self, forward: Callable[[Tensor], Tensor], data: Tensor, theta: Tensor) -> None:
        self._forward = forward
        self.theta = theta.detach()
        self._theta_leaf = self.theta.clone().requires_grad_(True)
        with torch.enable_grad():
            self._y = forward(self._theta_leaf)
        if self._y.shape != data.shape:
            raise ValueError(f"forward model returned shape {tuple(self._y.shape)} but the data "
                             f"have shape {tuple(data.shape)}")
        self.r = (self._y - data).detach()
        self.norm = float(torch.linalg.vector_norm(self.r))

    def jvp(self, v: Tensor) -> Tensor:
        """``J v`` ``(m,)`` for ``v`` ``(n,)``: one forward-mode pass (one solve)."""
        with fwAD.dual_level():
            y = self._forward(fwAD.make_dual(self.theta, v.to(self.theta)))
            tangent = fwAD.unpack_dual(y).tangent
        return torch.zeros_like(self.r) if tangent is None else tangent.detach()

    def vjp(self, w: Tensor) -> Tensor:
        """``J^T w`` ``(n,)`` for ``w`` ``(m,)``: one reverse pass (one adjoint solve)."""
        (grad,) = torch.autograd.grad(self._y, self._theta_leaf, grad_outputs=w.to(self._y),
                                      retain_graph=True, allow_unused=True)
        return torch.zeros_like(self.theta) if grad is None else grad.detach()


class ResidualFunction:
    """``r(theta) = forward(theta) - data`` plus what the solvers may know about it.

    Args:
        forward: ``theta (n,) -> y (m,)``, differentiable (``observe(simulate(map(theta)))``).
        data: ``(m,)`` target values ``y_t``.
        noise_level: ``delta``, the expected ``||noise||_2`` of the data (discrepancy
            principle), or ``None`` when unknown.
        gauge: ``theta -> (n,)`` unit direction the residual does not depend on (the
            global stiffness scale of a scale-free problem), or ``None``.
    """

    def __init__(self, forward: Callable[[Tensor], Tensor], data: Tensor,
                 noise_level: float | None = None,
                 gauge: Callable[[Tensor], Tensor] | None = None) -> None:
        if data.dim() != 1:
            raise ValueError(f"data must be a flat vector, got shape {tuple(data.shape)}")
        if not bool(torch.isfinite(data).all()):
            raise ValueError("data contain NaN or infinite values")
        if noise_level is not None and not noise_level >= 0:
            raise ValueError(f"noise level must be >= 0, got {noise_level}")
        self.forward = forward
        self.data = data
        self.noise_level = noise_level
        self.gauge = gauge

    @property
    def size(self) -> int:
        return int(self.data.numel())

    def value(self, theta: Tensor) -> Tensor:
        """``r(theta)`` without building a graph."""
        with torch.no_grad():
            return self.forward(theta.detach()) - self.data

    def linearize(self, theta: Tensor) -> Linearization:
        return Linearization(self.forward, self.data, theta)

    def try_linearize(self, theta: Tensor) -> Linearization | None:
        """:func:`try_linearize` of this residual."""
        return try_linearize(self, theta)

    def projector(self, theta: Tensor) -> Callable[[Tensor], Tensor] | None:
        """Orthogonal projector removing the gauge direction at ``theta`` (or ``None``)."""
        if self.gauge is None:
            return None
        direction = self.gauge(theta)

        def project(v: Tensor) -> Tensor:
            return v - torch.dot(direction, v) * direction

        return project


def try_linearize(residual, theta: Tensor):
    """``residual.linearize(theta)`` at a trial point, or ``None`` where the simulation has
    no answer there (a :class:`~torchfit.errors.SimulationError`: Newton failure, singular
    system, infeasible parameters), which solvers count as a failed step. Works for any
    object with ``linearize``."""
    try:
        return residual.linearize(theta)
    except SimulationError:
        return None
