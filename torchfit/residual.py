"""What a solver sees: a residual ``r(theta)`` with its products ``J v`` and ``J^T w``.

Solvers know nothing of meshes or physics; a problem hands them a
:class:`ResidualFunction` built from any torch function ``theta -> y`` and the data.
Products come from torch autograd through the differentiable simulator, whose custom
adjoints do the work: ``J^T w`` is a reverse pass over one retained graph and ``J v`` a
forward-mode pass (the simulator returns its stored solution for an unchanged
``theta``, so neither product refactorises anything).

Explicit products: a problem whose forward is a chain of explicit derivatives (a
parameterisation, an equilibrium with the model's ``param_derivative``, a gather) may hand
over ``products(theta) -> ForwardProducts``: the forward value and ``J v`` / ``J^T w`` as
plain functions. :class:`Linearization` then builds no autograd graph and runs no
autograd engine (what that saves: ``docs/notes/time_to_accuracy.md``). The autograd
route stays the definition (tests compare the two).

Few parameters: a problem may also hand over ``jacobian(theta) -> (m, n)``, the whole
``d forward / d theta`` in one pass (the simulator solves with ``n`` right-hand sides per
stored factor). :meth:`Linearization.jacobian` returns it (computed once per
linearisation), and after :meth:`Linearization.use_dense` the products ``J v`` and
``J^T w`` are matrix products with it, with no simulation call. Without the callable
:meth:`Linearization.jacobian` stacks ``n`` jvps (exact, generic, slow). Nothing changes
for a solver that does not ask.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import torch
import torch.autograd.forward_ad as fwAD
from torch import Tensor

from .errors import SimulationError


_WARM = False


def warm_up_autograd() -> None:
    """Pay torch's one-time lazy initialisation of derivative products now.

    The first forward-mode product of a process loads torch's jvp decompositions
    (compiled by TorchScript) and the first ``autograd.grad`` *given* ``grad_outputs``
    (every vector-Jacobian product, every adjoint of a simulation) imports sympy through
    ``symbolic_shapes``, once per process (0.6-1.5 s on the development machine; one
    second or more of the "first backward" measured on the H200 host). :func:`torchfit.fit`
    calls this during set-up, so solver clocks and iteration records measure solving (the
    cost: ``docs/notes/time_to_accuracy.md``). Idempotent.
    """
    global _WARM
    if _WARM:
        return
    x = torch.ones(2, dtype=torch.float64, requires_grad=True)
    with fwAD.dual_level():
        fwAD.unpack_dual(torch.exp(fwAD.make_dual(x.detach(), torch.ones_like(x))))
    with torch.enable_grad():
        # with grad_outputs: a scalar output's implicit one does not load symbolic_shapes
        torch.autograd.grad(torch.exp(x), x, torch.ones_like(x))
    _WARM = True


@dataclasses.dataclass
class ForwardProducts:
    """The forward model at one ``theta`` with explicit derivative products.

    Attributes:
        y: ``(m,)`` the forward value ``forward(theta)`` (no graph).
        jvp: ``v (n,) -> J v (m,)``.
        vjp: ``w (m,) -> J^T w (n,)``.
    """

    y: Tensor
    jvp: Callable[[Tensor], Tensor]
    vjp: Callable[[Tensor], Tensor]


class Linearization:
    """The residual at one ``theta`` and its Jacobian products.

    Args:
        forward, data, theta: the residual ``forward(theta) - data`` at ``theta``.
        jacobian: ``theta -> (m, n)`` dense ``d forward / d theta`` or ``None``.
        products: ``theta -> ForwardProducts`` (explicit products, no graph) or ``None``
            (autograd: one retained graph for ``J^T w``, forward mode for ``J v``).

    Attributes:
        theta: ``(n,)`` the point (detached).
        r: ``(m,)`` residual ``forward(theta) - data``.
        norm: ``||r||_2`` as a float.
        dense: whether :meth:`use_dense` switched the products to the stored ``J``.
    """

    def __init__(self, forward: Callable[[Tensor], Tensor], data: Tensor, theta: Tensor,
                 jacobian: Callable[[Tensor], Tensor] | None = None,
                 products: Callable[[Tensor], ForwardProducts] | None = None) -> None:
        self._forward = forward
        self._jacobian_fn = jacobian
        self._J: Tensor | None = None
        self.dense = False
        self.theta = theta.detach()
        self._products = None if products is None else products(self.theta)
        if self._products is not None:
            self._y = self._products.y.detach()
        else:
            self._theta_leaf = self.theta.clone().requires_grad_(True)
            with torch.enable_grad():
                self._y = forward(self._theta_leaf)
        if self._y.shape != data.shape:
            raise ValueError(f"forward model returned shape {tuple(self._y.shape)} but the data "
                             f"have shape {tuple(data.shape)}")
        self.r = (self._y - data).detach()
        self.norm = float(torch.linalg.vector_norm(self.r))

    def jacobian(self) -> Tensor:
        """``J = d forward / d theta`` at :attr:`theta`, dense ``(m, n)``, computed once.

        From the residual's ``jacobian`` callable when it has one (one pass of the
        simulator), else the stack of the ``n`` jvps of the unit vectors (``n``
        forward-mode passes). Under ``torchrun`` the callable returns the rows kept on their
        ranks instead of a tensor (:mod:`torchfit.run.distributed.rows`): ``J @ x``,
        ``J.T @ w`` and ``J.T @ J`` are then all the dense path may form.
        """
        if self._J is None:
            m, n = self.r.numel(), self.theta.numel()
            if self._jacobian_fn is not None:
                J = self._jacobian_fn(self.theta).detach()
                if J.shape != (m, n):
                    raise ValueError(f"the residual's jacobian returned shape {tuple(J.shape)}, "
                                     f"expected (m, n) = ({m}, {n})")
                J = J.to(self.r)
            else:
                eye = torch.eye(n, dtype=self.theta.dtype, device=self.theta.device)
                J = torch.stack([self._forward_jvp(eye[j]) for j in range(n)], dim=1) \
                    if n else self.r.new_zeros(m, 0)
            self._J = J
        return self._J

    def use_dense(self) -> "Linearization":
        """From now on ``jvp``/``vjp`` are products with :meth:`jacobian` (computed now)."""
        self.jacobian()
        self.dense = True
        return self

    def jvp(self, v: Tensor) -> Tensor:
        """``J v`` ``(m,)`` for ``v`` ``(n,)``: one forward-mode pass (one solve), or a matrix
        product after :meth:`use_dense`."""
        if self.dense:
            assert self._J is not None
            return self._J @ v.to(self.r)
        return self._forward_jvp(v)

    def _forward_jvp(self, v: Tensor) -> Tensor:
        if self._products is not None:
            return self._products.jvp(v.to(self.theta)).detach()
        with fwAD.dual_level():
            y = self._forward(fwAD.make_dual(self.theta, v.to(self.theta)))
            tangent = fwAD.unpack_dual(y).tangent
        return torch.zeros_like(self.r) if tangent is None else tangent.detach()

    def vjp(self, w: Tensor) -> Tensor:
        """``J^T w`` ``(n,)`` for ``w`` ``(m,)``: one reverse pass (one adjoint solve), or a
        matrix product after :meth:`use_dense`."""
        if self.dense:
            assert self._J is not None
            return self._J.T @ w.to(self.r)
        if self._products is not None:
            return self._products.vjp(w.to(self.r)).detach()
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
        jacobian: ``theta (n,) -> (m, n)``, the dense ``d forward / d theta`` in one pass,
            or ``None``. Solvers use it for problems with few parameters (see their
            ``dense_jacobian_max_params``); it must agree with the products of ``forward``.
        accuracy: relative accuracy of ``forward`` (e.g. a Newton tolerance), or ``None``
            for machine precision; derivative checks choose their finite-difference step
            from it.
        product_consistency: relative agreement of the ``J^T w`` that ``forward``'s
            autograd gives with its ``J v`` when the two are separate approximations
            (a continuous adjoint against forward sensitivities, each accurate to an ODE
            tolerance), or ``None`` when one is the exact transpose of the other; the
            dot-product check takes its bound from it
            (:func:`torchfit.verification.default_dot_tol`).
        products: ``theta (n,) -> ForwardProducts``: ``forward(theta)`` with explicit
            ``J v`` and ``J^T w`` (no autograd), or ``None``; it must agree with
            ``forward`` and its autograd products.
    """

    def __init__(self, forward: Callable[[Tensor], Tensor], data: Tensor,
                 noise_level: float | None = None,
                 gauge: Callable[[Tensor], Tensor] | None = None,
                 jacobian: Callable[[Tensor], Tensor] | None = None,
                 accuracy: float | None = None,
                 products: Callable[[Tensor], ForwardProducts] | None = None,
                 product_consistency: float | None = None) -> None:
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
        self.jacobian = jacobian
        self.accuracy = accuracy
        self.products = products
        self.product_consistency = product_consistency

    @property
    def size(self) -> int:
        return int(self.data.numel())

    def value(self, theta: Tensor) -> Tensor:
        """``r(theta)`` without building a graph."""
        with torch.no_grad():
            return self.forward(theta.detach()) - self.data

    def linearize(self, theta: Tensor) -> Linearization:
        return Linearization(self.forward, self.data, theta, self.jacobian, self.products)

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
