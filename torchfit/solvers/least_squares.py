"""What Gauss-Newton and Levenberg-Marquardt share beyond :class:`~.base.Solver`: the
linearisation they carry (``lin``, whose ``theta`` is the current point), the difference
operator their ``preconditioner=difference`` needs, and the dense-Jacobian path.

Dense Jacobian (few parameters): when the residual provides ``jacobian`` (a problem with
a one-pass Jacobian, see :class:`~torchfit.residual.ResidualFunction`) and the number of
parameters ``n`` is at most ``dense_jacobian_max_params``, every linearisation the
solver adopts as its current point materialises ``J`` once (``F`` solves with ``n``
right-hand sides instead of one solve per product) and every product of that iteration
is a matrix product. Gauss-Newton keeps its CGLS (its early stopping regularises);
Levenberg-Marquardt solves its damped normal equations exactly
(:class:`DenseNormalEquations`). Trial points that are rejected never pay for ``J``.
Records carry ``dense_jacobian = 1.0`` on this path.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Optional

import torch
from torch import Tensor

from ..linalg import CGLSResult
from ..residual import Linearization
from .base import Need, Solver, SolverConfig, SolverConfigError, require
from .bounds import Box, ThetaBounds, box_scale, clip_to_box, gauge_direction, inside
from .total_variation import check_difference_operator


@dataclasses.dataclass
class LeastSquaresConfig(SolverConfig):
    """Settings every least-squares solver has (Gauss-Newton, Levenberg-Marquardt)."""

    # dense J (one simulator pass per linearisation) when the residual provides a
    # jacobian and n <= this; 0: always matrix-free products
    dense_jacobian_max_params: int = 1000
    # the largest change of any single parameter in one step (0: no limit): every
    # component of a step is clipped to [-max_step, max_step] (and J d recomputed). With
    # theta = log E, max_step = 1 lets a modulus change by at most a factor e per step:
    # weakly observed parameters cannot leap to values the simulation cannot solve, and
    # the well observed ones still take their full step. Where clipping would turn the
    # step away from descent, the whole step is scaled into the box (box_step; LM).
    # Gauss-Newton instead stops its CGLS on the box's boundary (a trust region): its
    # steps are inside the box and never clipped.
    max_step: float = 0.0

    def check(self) -> None:
        require(self.dense_jacobian_max_params >= 0,
                f"solver.dense_jacobian_max_params must be >= 0 (0 disables the dense "
                f"Jacobian), got {self.dense_jacobian_max_params}")
        require(self.max_step >= 0, f"solver.max_step must be >= 0 (0: no limit), got "
                f"{self.max_step}")


def require_difference_operator(D: Optional[Tensor]) -> None:
    """The error of ``preconditioner=difference`` without ``D`` (and a check of ``D``)."""
    if D is None:
        raise SolverConfigError(
            "solver.preconditioner=difference needs the difference operator D of the "
            "parameterisation (pass D=parameterization.difference_operator()), or set "
            "solver.preconditioner=none")
    n = D.shape[1] if isinstance(D, Tensor) and D.dim() == 2 else 0
    check_difference_operator(D, n)


def box_step(lin: Linearization, direction: Tensor, model_change: Tensor,
             limit: float | Box) -> tuple[Tensor, Tensor]:
    """``(d, J d)`` with no component of ``d`` beyond ``limit`` (``solver.max_step``, or a
    per-component box ``(lo, hi)``, see :mod:`.bounds`).

    ``direction`` must descend the linear model (``||r + J d|| < ||r||``, as every
    Gauss-Newton and damped step does) and ``model_change`` be its ``J d``. Each component
    is clipped (the well observed parameters keep their full step while a weakly
    observed one is held back) and ``J d`` recomputed (one product). Clipping a nearly
    cancelling pair of large components can leave a step the linear model says does not
    descend, which a line search would take for convergence and Levenberg-Marquardt
    could only reject; the step scaled into the box is returned then (it descends:
    ``||r + a J d||^2 < ||r||^2`` for ``0 < a <= 1``)."""
    clipped, clipped_change, descends = clip_step(lin, direction, limit)
    if clipped is direction:
        return direction, model_change
    if descends:
        return clipped, clipped_change
    if isinstance(limit, tuple):
        scale = box_scale(direction, limit)
    else:
        scale = limit / float(direction.abs().max())
    return direction * scale, model_change * scale


def clip_step(lin: Linearization, direction: Tensor, limit: float | Box
              ) -> tuple[Tensor, Tensor | None, bool]:
    """``(clipped d, J clipped d, whether ||r + J clipped d|| < ||r||)``; ``direction``
    itself (and ``None``, ``True``) when no component exceeds ``limit`` (a number: the
    box ``[-limit, limit]``; a pair ``(lo, hi)`` of ``(n,)`` tensors: that box)."""
    if isinstance(limit, tuple):
        if not direction.numel() or inside(direction, limit):
            return direction, None, True
        clipped = clip_to_box(direction, limit)
    else:
        if not direction.numel() or float(direction.abs().max()) <= limit:
            return direction, None, True
        clipped = direction.clamp(-limit, limit)
    clipped_change = lin.jvp(clipped)
    model = lin.r + clipped_change
    return clipped, clipped_change, float(torch.dot(model, model)) < lin.norm ** 2


def wants_dense_jacobian(residual: Any, n: int, max_params: int) -> bool:
    """Whether a solver with ``dense_jacobian_max_params = max_params`` takes the dense
    path for ``residual`` with ``n`` parameters (the residual must provide ``jacobian``)."""
    return 0 < n <= max_params and getattr(residual, "jacobian", None) is not None


def projector_matrix(project: Callable[[Tensor], Tensor] | None, like: Tensor) -> Tensor | None:
    """The ``(n, n)`` matrix of a (linear) projector, or ``None`` without one."""
    if project is None:
        return None
    eye = torch.eye(like.numel(), dtype=like.dtype, device=like.device)
    return torch.stack([project(eye[:, j]) for j in range(like.numel())], dim=1)


class DenseNormalEquations:
    """Exact solutions of ``min ||J d - b||^2 + shift ||d||^2`` with the dense ``J`` of one
    linearisation, ``d`` orthogonal to the gauge when the residual has a projector ``P``.

    The Gram matrix ``P J^T J P`` is formed once (``m n^2``); each solve is a Cholesky
    factorisation of ``P J^T J P + shift I`` (``n^3 / 3``) and, where that fails (no
    shift and a singular ``J``), a least-squares solve (``torch.linalg.lstsq``). The
    result has the fields of :class:`~torchfit.linalg.CGLSResult` (``iterations = 0``,
    ``stop_reason = 'exact'``), so the solvers treat both alike.
    """

    def __init__(self, lin: Any, project: Callable[[Tensor], Tensor] | None) -> None:
        self.lin = lin
        self.J = lin.jacobian()
        self.P = projector_matrix(project, lin.theta.to(dtype=self.J.dtype, device=self.J.device))
        gram = self.J.T @ self.J
        if self.P is not None:
            gram = self.P @ gram @ self.P
        self.gram = 0.5 * (gram + gram.T)

    def solve(self, b: Tensor, shift: float, rmatvec_b: Tensor | None = None) -> CGLSResult:
        rhs = self.J.T @ b if rmatvec_b is None else \
            rmatvec_b.to(dtype=self.J.dtype, device=self.J.device)
        if self.P is not None:
            rhs = self.P @ rhs
        n = rhs.numel()
        system = self.gram + shift * torch.eye(n, dtype=self.J.dtype, device=self.J.device)
        factor, info = torch.linalg.cholesky_ex(system)
        if int(info) == 0:
            x = torch.cholesky_solve(rhs[:, None], factor)[:, 0]
        else:
            x = torch.linalg.lstsq(system, rhs[:, None]).solution[:, 0]
        if self.P is not None:
            x = self.P @ x
        Ax = self.J @ x
        return CGLSResult(x, 0, float(torch.linalg.vector_norm(Ax - b)), Ax, "exact")


class LeastSquaresSolver(Solver):
    """A solver of ``min 0.5 ||r(theta)||^2`` that carries its current linearisation.

    Its config is a :class:`LeastSquaresConfig`; ``D`` is checked where its settings
    require one (:meth:`SolverConfig.needs`).
    """

    config: LeastSquaresConfig

    def __init__(self, config: SolverConfig | None = None, *, D: Tensor | None = None,
                 groups: Tensor | None = None) -> None:
        super().__init__(config, D=D, groups=groups)
        if self.config.needs().difference_operator is Need.required:
            require_difference_operator(D)
        self.lin: Linearization | None = None
        self.dense = False

    supports_bounds = True

    def set_bounds(self, lower: Tensor, upper: Tensor) -> None:
        self.bounds = ThetaBounds(lower, upper)

    def choose_path(self, theta: Tensor) -> None:
        """Dense-Jacobian or matrix-free products for this run (from the residual and ``n``)."""
        self.dense = wants_dense_jacobian(self.residual, theta.numel(),
                                          int(self.config.dense_jacobian_max_params))

    def adopt(self, lin: Any) -> Any:
        """``lin`` becomes a current point: on the dense path its ``J`` is made now."""
        if self.dense:
            lin.use_dense()
        return lin

    def path_extra(self) -> dict[str, float]:
        """What the records say about the path (``dense_jacobian = 1.0`` when dense) and,
        with bounds, how many parameters sit on the lower / upper bound."""
        extra = {"dense_jacobian": 1.0} if self.dense else {}
        if self.bounds is not None and self.lin is not None:
            at_lower, at_upper = self.bounds.on_bounds(self.lin.theta)
            extra.update(at_lower_bound=float(at_lower.sum()),
                         at_upper_bound=float(at_upper.sum()))
        return extra

    # -- bounds (see .bounds): every hook is the unbounded computation without them ------
    def step_limit(self, gradient: Tensor) -> float | Box:
        """The box of this iteration's step: ``max_step`` without bounds, else the room
        the free parameters have left (intersected with ``max_step``)."""
        if self.bounds is None:
            return float(self.config.max_step)
        return self.bounds.step_box(self.theta, gradient, float(self.config.max_step))

    def projector(self, gradient: Tensor) -> Callable[[Tensor], Tensor] | None:
        """The inner solves' projector: the residual's gauge projector, and with bounds
        also the active parameters removed (:meth:`.bounds.ThetaBounds.free_projector`)."""
        theta = self.theta
        project = self.residual.projector(theta)
        if self.bounds is None:
            return project
        return self.bounds.free_projector(theta, gradient, gauge_direction(project, theta))

    def stationarity(self, theta: Tensor, gradient: Tensor) -> float:
        """``||J^T r||`` for the stop rules; with bounds, without the active parameters."""
        if self.bounds is not None:
            gradient = self.bounds.free_gradient(theta, gradient)
        return float(torch.linalg.vector_norm(gradient))

    @property
    def theta(self) -> Tensor:
        assert self.lin is not None
        return self.lin.theta
