"""Krylov solvers in torch: batched preconditioned CG and matrix-free CGLS.

CG solves SPD systems for many right-hand sides at once (one row of ``b`` each).
CGLS solves ``min ||A x - b||^2 + shift ||x||^2`` using only the products ``A v`` and
``A^T w``; Gauss-Newton and Levenberg-Marquardt use it on the Jacobian without ever
forming it. Both are plain torch and run on any device.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import torch
from torch import Tensor


def batched_cg(matvec: Callable[[Tensor], Tensor], b: Tensor,
               preconditioner: Callable[[Tensor], Tensor] | None = None,
               rtol: float = 1e-12, max_iter: int = 1000) -> tuple[Tensor, bool, int]:
    """Preconditioned CG on every row of ``b`` at once.

    Args:
        matvec: ``(c, n) -> (c, n)``, the SPD operator applied row-wise.
        b: ``(c, n)`` right-hand sides.
        preconditioner: ``(c, n) -> (c, n)``, an SPD approximation of the inverse.
        rtol: stop when every row has ``||r|| <= rtol ||b||``.
    Returns:
        ``(x, converged, iterations)``.
    """
    precondition = preconditioner or (lambda v: v)
    x = torch.zeros_like(b)
    r = b.clone()
    b_norm = torch.linalg.vector_norm(b, dim=1)
    target = rtol * b_norm
    z = precondition(r)
    p = z.clone()
    rz = (r * z).sum(dim=1)
    for iteration in range(1, max_iter + 1):
        if bool((torch.linalg.vector_norm(r, dim=1) <= target).all()):
            return x, True, iteration - 1
        q = matvec(p)
        pq = (p * q).sum(dim=1)
        active = torch.linalg.vector_norm(r, dim=1) > target
        alpha = torch.where(active, rz / torch.where(pq == 0, 1.0, pq), 0.0)
        x = x + alpha[:, None] * p
        r = r - alpha[:, None] * q
        z = precondition(r)
        rz_new = (r * z).sum(dim=1)
        beta = torch.where(active, rz_new / torch.where(rz == 0, 1.0, rz), 0.0)
        p = z + beta[:, None] * p
        rz = rz_new
    converged = bool((torch.linalg.vector_norm(r, dim=1) <= target).all())
    return x, converged, max_iter


@dataclasses.dataclass
class CGLSResult:
    """Outcome of :func:`cgls`.

    Attributes:
        x: the solution estimate ``(n,)``.
        iterations: CG iterations done (each costs one ``A v`` and one ``A^T w``).
        residual_norm: ``||A x - b||`` at the end (tracked by the recurrence).
        Ax: ``A x`` at the end (tracked by the recurrence, no extra product).
        stop_reason: ``'tolerance'``, ``'max_iter'``, ``'breakdown'`` or ``'boundary'``.
    """

    x: Tensor
    iterations: int
    residual_norm: float
    Ax: Tensor
    stop_reason: str


_ROUNDOFF = 1e-14     # relative M-norm of the normal residual at which CGLS always stops
#: ``s^T M s <= _GAMMA_ROUNDOFF eps ||s||^2``: the M-norm is round-off; CGLS stops
_GAMMA_ROUNDOFF = 16.0


def cgls(matvec: Callable[[Tensor], Tensor], rmatvec: Callable[[Tensor], Tensor], b: Tensor,
         n: int, shift: float = 0.0, residual_target: float = 0.0, max_iter: int = 100,
         project: Callable[[Tensor], Tensor] | None = None,
         rmatvec_b: Tensor | None = None, normal_rtol: float = 1e-14,
         preconditioner: Callable[[Tensor], Tensor] | None = None,
         max_abs: float = 0.0,
         box: tuple[Tensor, Tensor] | None = None) -> CGLSResult:
    """(Preconditioned) CGLS for ``min ||A x - b||^2 + shift ||x||^2`` from ``x = 0``.

    Stops when the least-squares residual ``||A x - b||`` drops to
    ``residual_target`` (the REGINN-style relative rule of Gauss-Newton), when the
    normal-equation residual ``||A^T (b - A x) - shift x||`` drops to ``normal_rtol``
    times its initial value (the rule of Levenberg-Marquardt), or after ``max_iter``.

    Args:
        matvec: ``v (n,) -> A v (m,)``.
        rmatvec: ``w (m,) -> A^T w (n,)``.
        b: ``(m,)`` right-hand side.
        n: number of unknowns.
        shift: Tikhonov/Levenberg-Marquardt damping ``>= 0``.
        project: optional orthogonal projector applied to search directions (keeps
            iterates out of a known null space, e.g. the stiffness scale).
        rmatvec_b: ``A^T b`` if the caller already has it (saves one product).
        max_abs: ``> 0``: a trust region ``||x||_inf <= max_abs`` (Steihaug's truncated CG
            with a box): the iteration stops where its next update would leave the box,
            at the point of that update on the box's boundary (``stop_reason``
            ``'boundary'``). The iterates' norms grow from ``x = 0``, so this keeps the
            first, best-determined Krylov directions instead of clipping an iterate that
            the later ones (small singular values) have taken far outside.
        box: ``(lower, upper)`` ``(n,)`` each with ``lower <= 0 <= upper`` (entries may be
            infinite): the same trust region for a box of any shape, e.g. the room a bounded
            parameter has left (``theta_min - theta``, ``theta_max - theta``); used with or
            instead of ``max_abs`` (the caller intersects them).
        preconditioner: ``s (n,) -> M s (n,)`` with ``M`` SPD, an approximation of
            ``(A^T A + shift I)^{-1}``: CG on the normal equations in the ``M^{-1}`` inner
            product. The iterates solve the same problem; only the Krylov space changes
            (``None``: ``M = I``, plain CGLS). The stopping rules use the unpreconditioned
            normal residual, so a preconditioner never loosens them.
    Returns:
        :class:`CGLSResult`; ``m`` iterations cost ``m`` matvecs and ``m`` rmatvecs
        (plus one rmatvec for ``A^T b`` unless given).
    """
    project = project or (lambda v: v)
    eps = torch.finfo(b.dtype).eps
    precondition = (lambda v: project(preconditioner(v))) if preconditioner is not None \
        else (lambda v: v)
    x = b.new_zeros(n)
    r = b.clone()                       # b - A x
    s = project(rmatvec_b.clone() if rmatvec_b is not None else rmatvec(r))   # normal residual
    z = precondition(s)
    p = z.clone()
    gamma = torch.dot(s, z)             # s^T M s (s^T s without a preconditioner)
    gamma0 = float(gamma)
    s_norm2_0 = float(torch.dot(s, s))
    s_norm2 = s_norm2_0
    # M's gain on the first normal residual, a lower bound of ||M|| (0 without a preconditioner:
    # M = I and s^T s is exact)
    gain = float(torch.linalg.vector_norm(z)) / s_norm2_0 ** 0.5 \
        if preconditioner is not None and s_norm2_0 > 0 else 0.0
    Ax = torch.zeros_like(b)
    r_norm = float(torch.linalg.vector_norm(r))
    if r_norm <= residual_target:
        return CGLSResult(x, 0, r_norm, Ax, "tolerance")
    stop = "max_iter"
    iterations = 0
    for iterations in range(1, max_iter + 1):
        # The M-norm test ends the iteration at round-off, where CG breaks down: with a
        # singular M (a gauge kept out by the preconditioner) ||s|| never gets small. Its
        # floor is the round-off of s^T M s itself, about eps ||M|| ||s||^2 (the gauge part
        # of s times the round-off M s leaves in the gauge; ||M|| estimated by its gain on
        # the first s); below it the next beta = gamma' / gamma multiplies round-off by 1e13
        # (measured on an AVX-512 CPU, 2026-12-02).
        if s_norm2 <= normal_rtol ** 2 * s_norm2_0 or float(gamma) <= _ROUNDOFF ** 2 * gamma0 \
                or float(gamma) <= _GAMMA_ROUNDOFF * eps * gain * s_norm2:
            stop = "tolerance"
            iterations -= 1
            break
        q = matvec(p)
        delta = torch.dot(q, q) + shift * torch.dot(p, p)
        if float(delta) <= 0.0:
            stop = "breakdown"
            iterations -= 1
            break
        alpha = gamma / delta
        if box is not None:
            reach = _general_box_reach(x, p, box)
            if float(alpha) > reach:
                x = torch.minimum(torch.maximum(x + reach * p, box[0]), box[1])
                Ax = Ax + reach * q
                r = r - reach * q
                r_norm = float(torch.linalg.vector_norm(r))
                stop = "boundary"
                break
        elif max_abs > 0:
            reach = _box_reach(x, p, max_abs)
            if float(alpha) > reach:
                # clamped: the point is on the boundary, not round-off outside it
                x = (x + reach * p).clamp_(-max_abs, max_abs)
                Ax = Ax + reach * q
                r = r - reach * q
                r_norm = float(torch.linalg.vector_norm(r))
                stop = "boundary"
                break
        x = x + alpha * p
        Ax = Ax + alpha * q
        r = r - alpha * q
        r_norm = float(torch.linalg.vector_norm(r))
        if r_norm <= residual_target:
            stop = "tolerance"
            break
        if iterations == max_iter:
            break
        s = project(rmatvec(r) - shift * x)
        z = precondition(s) if preconditioner is not None else s
        s_norm2 = float(torch.dot(s, s))
        gamma_new = torch.dot(s, z)
        p = z + (gamma_new / gamma) * p
        gamma = gamma_new
    return CGLSResult(x, iterations, r_norm, Ax, stop)


def _box_reach(x: Tensor, p: Tensor, radius: float) -> float:
    """The largest ``t >= 0`` with ``||x + t p||_inf <= radius`` (``x`` inside the box)."""
    moving = p != 0
    if not bool(moving.any()):
        return float("inf")
    room = radius - torch.sign(p[moving]) * x[moving]
    return float(torch.clamp(room, min=0.0).div(p[moving].abs()).min())


def _general_box_reach(x: Tensor, p: Tensor, box: tuple[Tensor, Tensor]) -> float:
    """The largest ``t >= 0`` with ``lower <= x + t p <= upper`` (``x`` inside the box)."""
    lower, upper = box
    room = torch.where(p > 0, upper - x, torch.where(p < 0, lower - x, torch.inf))
    moving = p != 0
    if not bool(moving.any()):
        return float("inf")
    return float(torch.clamp(room[moving] / p[moving], min=0.0).min())
