"""Box constraints ``theta_min <= theta <= theta_max`` for the least-squares solvers: the
contract, the active set and the projected step.

Contract: a run whose problem has bounds (``InverseProblem.theta_bounds``; with
``transform=exp`` the bounds on ``theta = log E`` are ``log E_min``, ``log E_max``) calls
:meth:`~.base.Solver.set_bounds` before ``solve``. Solvers with
``supports_bounds = True`` (Gauss-Newton, Levenberg-Marquardt) keep every iterate inside
the box; the others refuse in one line (:class:`~.base.SolverConfigError`). Entries may be
``-inf`` / ``+inf`` (no bound on that side). A start outside the box is refused, never
moved into it.

Method (a projected active-set step, the simple variant of the bound-constrained
Gauss-Newton / Levenberg-Marquardt of Coleman and Li's reflective methods and scipy's
``trf``, without their scaling): at the current point ``theta`` with gradient
``g = J^T r`` of ``0.5 ||r||^2``,

1. the *active set* is the parameters on a bound (within ``BOUND_TOL`` of it, relative)
   whose descent direction ``-g`` points out of the box; they are fixed for this step
   (the step's search space is ``{d : d_active = 0}``, and orthogonal to the gauge where
   the residual has one: :meth:`ThetaBounds.free_projector`, an exact orthogonal projector);
2. the step of the solver's own linear model is computed on the free parameters (CGLS
   or the dense normal equations, as without bounds);
3. it is kept inside the room the free parameters have left, ``[theta_min - theta,
   theta_max - theta]`` intersected with ``solver.max_step``'s box: Gauss-Newton's CGLS
   stops on that box's boundary (a trust region: its step is inside by construction);
   Levenberg-Marquardt clips each component to it and recomputes ``J d`` (the same
   per-component box as ``max_step``: the gain ratio is that of the step actually taken),
   and where the clipped step does not descend the damped system is solved again with
   more damping, finally the step is scaled into the box (which descends).

Why this and not scipy's ``trf``: the solvers already had a per-component box (the
``max_step`` trust region), a projector in their inner solves (the gauge) and a gain-ratio
test on the step actually taken; bounds on ``theta`` are one more box and the active set
one more projector, so a bound that binds costs nothing extra and an unbounded run is the
same computation as before. ``trf``'s affine scaling (``D = diag(|v|^(1/2))``) is not
used: it keeps iterates strictly inside, so a field never *sits* on a bound, while a TD's
bound is a value the field may take (the region report counts the parameters on it).
The measure of stationarity for the stop rules is the norm of the gradient with the
active parameters removed (zero at a constrained minimiser).
"""
from __future__ import annotations

import math
from typing import Callable, Optional

import torch
from torch import Tensor

from .base import SolverConfigError

#: a parameter within ``BOUND_TOL * max(1, |bound|)`` of a bound is on it
BOUND_TOL = 1e-9

Box = tuple[Tensor, Tensor]


class ThetaBounds:
    """``lower <= theta <= upper`` (``(n,)`` each; ``-inf`` / ``inf`` where unbounded).

    Raises :class:`~.base.SolverConfigError` when they do not describe a box
    (``lower >= upper`` anywhere, NaN, a shape other than ``(n,)``).
    """

    def __init__(self, lower: Tensor, upper: Tensor) -> None:
        lower = torch.as_tensor(lower).detach().flatten()
        upper = torch.as_tensor(upper).detach().flatten().to(lower)
        if lower.shape != upper.shape:
            raise SolverConfigError(f"parameter bounds: lower has {lower.numel()} entries, "
                                    f"upper {upper.numel()}; give one of each per parameter")
        if bool(torch.isnan(lower).any() | torch.isnan(upper).any()):
            raise SolverConfigError("parameter bounds: NaN in the bounds")
        bad = torch.nonzero(lower >= upper).flatten()
        if bad.numel():
            i = int(bad[0])
            raise SolverConfigError(f"parameter bounds: lower >= upper at parameter {i} "
                                    f"({float(lower[i])} >= {float(upper[i])}); the lower "
                                    f"bound must lie below the upper one")
        self.lower = lower
        self.upper = upper

    @property
    def n(self) -> int:
        return self.lower.numel()

    def to(self, like: Tensor) -> "ThetaBounds":
        """The bounds in ``like``'s dtype and device."""
        if self.lower.dtype == like.dtype and self.lower.device == like.device:
            return self
        return ThetaBounds(self.lower.to(like), self.upper.to(like))

    def outside(self, theta: Tensor) -> Optional[int]:
        """The first parameter of ``theta`` outside the box (``None``: inside)."""
        theta = theta.detach()
        bad = torch.nonzero((theta < self.lower) | (theta > self.upper)).flatten()
        return None if not bad.numel() else int(bad[0])

    def check_start(self, theta: Tensor) -> None:
        """Refuse a start outside the box (:class:`~.base.SolverConfigError`)."""
        if theta.numel() != self.n:
            raise SolverConfigError(f"parameter bounds have {self.n} entries, theta "
                                    f"{theta.numel()}")
        i = self.outside(theta)
        if i is not None:
            raise SolverConfigError(
                f"the start lies outside the parameter bounds: parameter {i} is "
                f"{float(theta[i])}, outside [{float(self.lower[i])}, {float(self.upper[i])}]")

    def on_bounds(self, theta: Tensor) -> tuple[Tensor, Tensor]:
        """Masks ``(n,)`` of the parameters on the lower and on the upper bound."""
        theta = theta.detach()
        lower_tol = BOUND_TOL * self.lower.abs().clamp(min=1.0)
        upper_tol = BOUND_TOL * self.upper.abs().clamp(min=1.0)
        return theta <= self.lower + lower_tol, theta >= self.upper - upper_tol

    def active(self, theta: Tensor, gradient: Tensor) -> Tensor:
        """Mask of the parameters fixed for the step: on a bound, ``-gradient`` outward."""
        at_lower, at_upper = self.on_bounds(theta)
        return (at_lower & (gradient > 0)) | (at_upper & (gradient < 0))

    def step_box(self, theta: Tensor, gradient: Tensor, max_step: float = 0.0) -> Box:
        """``(lo, hi)`` for the step ``d``: the room left to each bound (``lo <= 0 <= hi``),
        zero for the active parameters, intersected with ``[-max_step, max_step]`` when
        ``max_step > 0``."""
        theta = theta.detach()
        lo = torch.clamp(self.lower - theta, max=0.0)
        hi = torch.clamp(self.upper - theta, min=0.0)
        if max_step > 0:
            lo, hi = lo.clamp(min=-max_step), hi.clamp(max=max_step)
        fixed = self.active(theta, gradient)
        return lo.masked_fill(fixed, 0.0), hi.masked_fill(fixed, 0.0)

    def free_gradient(self, theta: Tensor, gradient: Tensor) -> Tensor:
        """``gradient`` with the active parameters' entries zeroed (the projected gradient:
        zero at a point that satisfies the bound-constrained first-order conditions)."""
        return gradient.masked_fill(self.active(theta, gradient), 0.0)

    def free_projector(self, theta: Tensor, gradient: Tensor,
                       gauge: Optional[Tensor] = None) -> Optional[Callable[[Tensor], Tensor]]:
        """The orthogonal projector onto ``{d : d_active = 0, gauge . d = 0}`` (``None``
        when nothing is active and there is no gauge).

        With ``M`` the diagonal mask of the free parameters and ``u = M gauge / ||M gauge||``
        it is ``M - u u^T`` (``M`` without a gauge): ``M`` and ``u u^T`` commute because
        ``u`` lies in ``M``'s range, so their difference is a projector.
        """
        free = (~self.active(theta, gradient)).to(theta.dtype)
        if gauge is None:
            if bool(free.all()):
                return None
            return lambda v: v * free
        u = gauge.detach() * free
        norm = float(torch.linalg.vector_norm(u))
        if norm == 0.0 or not math.isfinite(norm):
            return lambda v: v * free
        u = u / norm
        return lambda v: v * free - torch.dot(u, v) * u


def gauge_direction(project: Optional[Callable[[Tensor], Tensor]], theta: Tensor
                    ) -> Optional[Tensor]:
    """The unit direction ``g`` a residual's gauge projector ``v -> v - (g . v) g`` removes
    (``None`` without a projector): ``v - project(v)`` for ``v`` the ones vector, or a ramp
    where that is orthogonal to ``g``."""
    if project is None:
        return None
    for v in (torch.ones_like(theta), torch.linspace(1.0, 2.0, theta.numel()).to(theta)):
        removed = v - project(v)
        norm = float(torch.linalg.vector_norm(removed))
        if norm > 1e-12 * float(torch.linalg.vector_norm(v)):
            return removed / norm
    return None


def inside(direction: Tensor, box: Box) -> bool:
    """Whether ``box[0] <= direction <= box[1]``."""
    return bool(((direction >= box[0]) & (direction <= box[1])).all())


def clip_to_box(direction: Tensor, box: Box) -> Tensor:
    """Each component of ``direction`` clipped to ``[box[0], box[1]]``."""
    return torch.minimum(torch.maximum(direction, box[0]), box[1])


def box_scale(direction: Tensor, box: Box) -> float:
    """The largest ``a`` in ``[0, 1]`` with ``a * direction`` inside ``box``."""
    lo, hi = box
    ratio = torch.where(direction > 0, hi / direction,
                        torch.where(direction < 0, lo / direction, torch.inf))
    return float(torch.clamp(ratio.min(), min=0.0, max=1.0)) if direction.numel() else 1.0


__all__ = ["BOUND_TOL", "ThetaBounds", "box_scale", "clip_to_box", "gauge_direction", "inside"]
