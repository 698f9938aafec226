"""Levenberg-Marquardt with gain-ratio damping.

Each iteration solves the damped normal equations ``(J^T J + lam I) d = -J^T r``
matrix-free (CGLS with a shift), compares the actual decrease of ``0.5 ||r||^2`` with
the decrease the linear model predicts, and

* accepts the step when the gain ratio ``rho > 0``; ``lam`` shrinks by ``decrease``
  (1/3) when ``rho > 0.75`` and grows by ``increase`` (2) when ``rho < 0.25``
  (Marquardt's thresholds; on spring1d they reach 1e-7 in 13 iterations where Nielsen's
  smooth rule needs 20, because the normal matrix has eigenvalues over four decades and
  ``lam`` must fall fast once the model predicts well);
* rejects it otherwise, leaving ``theta`` exactly unchanged and growing ``lam`` by a
  doubling factor (2, 4, 8, ... until a step is accepted). A rejected step costs one factorisation (the trial point); the
  current point's factorisation is kept, so the next damped solve costs none.

Stopping rules are those of Gauss-Newton (discrepancy principle first).

Three opt-in additions, all on in ``solver=levenberg_marquardt_geodesic`` (the solver of
``problem=membrane2d``; measured there at 96x24, 40 iterations: plain LM 0.082 in
``k_err_rel_aligned``, geodesic acceleration alone 0.018 after 30, all three 9e-5 and
below 1e-2 from iteration 20):

* ``damping_update='nielsen'``: after an accepted step ``lam *= max(decrease,
  1 - (2 rho - 1)^3)``. Where the model's quality falls sharply with ``lam``, Marquardt's
  thresholds alternate two accepted steps with one rejected one; Nielsen's rule settles
  at a gain ratio of about 0.7 instead and rejects none.
* ``geodesic_acceleration`` (Transtrum and Sethna): the second directional derivative
  ``r_vv`` along the damped step ``v``, by one finite difference (one simulation without
  a graph), gives the acceleration ``a`` of the same damped system with right-hand side
  ``-J^T r_vv`` (at most ``geodesic_cg_max_iter`` CGLS iterations); the trial point is
  ``theta + v + a / 2``, the predicted decrease that of the second-order model
  ``r + J v + (r_vv + J a) / 2``, and a step with ``2 ||a|| / ||v|| > geodesic_alpha``
  is rejected without a trial. It lets ``lam`` fall where steps are limited by the
  curvature of the forward model, not by the linear solve.
* ``preconditioner='difference'`` preconditions the inner CGLS in parameter space with
  ``M = C^{-1} (D^T D + eps I) C^{-1}`` (``D`` the parameterisation's difference operator,
  ``C`` the Jacobian's column norms estimated by a few random products ``J^T w`` at each
  new linearisation). The damped system, hence the step, is the same; only the Krylov
  space changes. It pays where the data resolve rough parameter modes worst (a Jacobian
  that smooths, as an elliptic forward model observed everywhere does: on membrane2d at
  24x6 ``cond(J)`` is 2.9e3, ``cond(J C^{-1} (D^T D + eps I)^{1/2})`` 5.4e2) and CGLS hits
  ``cg_max_iter``. While ``lam`` dominates ``J^T J`` the identity is the better
  preconditioner, so it switches on after the first damped solve that reaches the cap.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable, Iterable

import torch
from torch import Tensor

from ..errors import SimulationError
from ..linalg import CGLSResult, cgls
from .gauss_newton import SolverConfigError, _require, _stop_reason
from ..records import Callback, IterationRecord, SolveResult
from .base import RunClock, emit, finish
from .preconditioners import GraphLaplacian
from ..residual import Linearization, ResidualFunction, try_linearize


PRECONDITIONERS = ("none", "difference")
DAMPING_UPDATES = ("marquardt", "nielsen")


@dataclasses.dataclass
class LevenbergMarquardtConfig:
    """Settings of ``solver=levenberg_marquardt``."""

    name: str = "levenberg_marquardt"
    max_iter: int = 100             # outer iterations (accepted and rejected)
    tau: float = 1.5                # discrepancy principle ||r|| <= tau * delta
    damping_init: float = 0.1       # lam_0 relative to ||J^T r||^2 / ||r||^2 (a J^T J scale)
    damping_update: str = "marquardt"   # after an accepted step: marquardt (thresholds) | nielsen
    decrease: float = 1.0 / 3.0     # lam factor after a good step (gain ratio > 0.75); nielsen:
                                    # the smallest factor, max(decrease, 1 - (2 rho - 1)^3)
    increase: float = 2.0           # lam factor after a poor accepted step (gain ratio < 0.25)
    damping_max: float = 1e12       # give up ('stalled') when lam exceeds this times lam_0
    cg_max_iter: int = 200          # CGLS iterations per damped solve
    cg_rtol: float = 1e-6           # stop CGLS when ||J^T J d + lam d + J^T r|| <= cg_rtol ||J^T r||
    rtol: float = 1e-4              # stop when an accepted step reduced ||r|| by less than this
    gtol: float = 1e-12             # stop when ||J^T r|| <= gtol * ||J^T r_0||
    atol: float = 0.0               # stop when ||r|| <= atol
    geodesic_acceleration: bool = False  # add Transtrum's second-order correction a / 2
    geodesic_step: float = 0.1      # h of the finite difference giving r_vv
    geodesic_alpha: float = 0.75    # reject when 2 ||a|| / ||v|| exceeds this
    geodesic_cg_max_iter: int = 50  # CGLS iterations for a
    preconditioner: str = "none"    # none | difference (CGLS in the D^T D + eps I metric; needs D)
    preconditioner_shift: float = 1e-2   # eps, relative to D^T D (eigenvalues in [0, 2 max degree])
    preconditioner_probes: int = 16      # products J^T w per linearisation estimating C
    seed: int = 0                   # of those random probes

    def validate(self) -> None:
        _require(self.max_iter >= 0, f"solver.max_iter must be >= 0, got {self.max_iter}")
        _require(self.tau > 1, f"solver.tau must be > 1 (discrepancy principle), got {self.tau}")
        _require(self.damping_init > 0, f"solver.damping_init must be > 0, got {self.damping_init}")
        _require(0 < self.decrease < 1 < self.increase,
                 f"need 0 < solver.decrease < 1 < solver.increase, got {self.decrease}, {self.increase}")
        _require(self.damping_max > 1, f"solver.damping_max must be > 1, got {self.damping_max}")
        _require(self.cg_max_iter >= 1, f"solver.cg_max_iter must be >= 1, got {self.cg_max_iter}")
        _require(0 < self.cg_rtol < 1, f"solver.cg_rtol must be in (0, 1), got {self.cg_rtol}")
        _require(self.rtol >= 0 and self.gtol >= 0 and self.atol >= 0,
                 "solver.rtol, solver.gtol and solver.atol must be >= 0")
        _require(self.damping_update in DAMPING_UPDATES,
                 f"solver.damping_update={self.damping_update!r}; choose one of {DAMPING_UPDATES}")
        _require(self.geodesic_step > 0 and self.geodesic_alpha > 0
                 and self.geodesic_cg_max_iter >= 1,
                 "solver.geodesic_step and solver.geodesic_alpha must be > 0 and "
                 "solver.geodesic_cg_max_iter >= 1")
        _require(self.preconditioner in PRECONDITIONERS,
                 f"solver.preconditioner={self.preconditioner!r}; choose one of {PRECONDITIONERS}")
        _require(self.preconditioner_shift > 0,
                 f"solver.preconditioner_shift must be > 0, got {self.preconditioner_shift}")
        _require(self.preconditioner_probes >= 1,
                 f"solver.preconditioner_probes must be >= 1, got {self.preconditioner_probes}")


def levenberg_marquardt(residual: ResidualFunction, theta0: Tensor,
                        config: LevenbergMarquardtConfig | None = None,
                        callbacks: Iterable[Callback] = (), D: Tensor | None = None,
                        **_: object) -> SolveResult:
    """Minimise ``0.5 ||r(theta)||^2`` from ``theta0`` by Levenberg-Marquardt.

    Args and return as :func:`~torchfit.solvers.gauss_newton.gauss_newton`; records
    carry the damping ``lam`` and whether the step was accepted. ``D`` (sparse
    ``(n_edges, n)``, the parameterisation's difference operator) is needed by
    ``preconditioner='difference'`` only; other keyword inputs (``groups``) are ignored.
    """
    cfg = config or LevenbergMarquardtConfig()
    cfg.validate()
    callbacks = list(callbacks)
    theta = theta0.detach().clone()
    laplacian = GraphLaplacian(D, theta) if cfg.preconditioner == "difference" else None
    laplacian_active = False
    generator = torch.Generator().manual_seed(cfg.seed)
    clock = RunClock()
    lin = residual.linearize(theta)
    gradient = lin.vjp(lin.r)
    gradient_norm0 = float(torch.linalg.vector_norm(gradient))
    if lin.norm > 0 and gradient_norm0 > 0:
        damping = cfg.damping_init * (gradient_norm0 / lin.norm) ** 2
    else:
        damping = cfg.damping_init
    damping0 = damping
    # The preconditioner follows the linearisation (a rejected step keeps it). It waits for
    # the first damped solve that reaches cg_max_iter: while lam dominates J^T J the
    # identity is the better preconditioner (and costs no probes).
    precondition = None
    growth = 2.0
    history: list[IterationRecord] = []
    previous_norm: float | None = None

    def record(iteration: int, step_norm: float, cg_iterations: int, accepted: bool,
               used_damping: float, **extra: float) -> bool:
        factorizations, solves = clock.counts()
        rec = IterationRecord(iteration, lin.theta, 0.5 * lin.norm ** 2, lin.norm, step_norm,
                              cg_iterations, used_damping, accepted, clock.elapsed(),
                              factorizations, solves, dict(extra))
        history.append(rec)
        return emit(callbacks, rec)

    if record(0, 0.0, 0, True, damping, gradient_norm=gradient_norm0):
        return finish(theta, False, "interrupted", history, clock)
    for iteration in range(1, cfg.max_iter + 1):
        gradient_norm = float(torch.linalg.vector_norm(gradient))
        reason = _stop_reason(lin.norm, previous_norm, gradient_norm, gradient_norm0,
                              residual.noise_level, cfg)
        if reason is not None:
            return finish(theta, True, reason, history, clock)
        if damping > cfg.damping_max * damping0:
            return finish(theta, False, "stalled", history, clock)
        used_damping = damping
        if laplacian_active and precondition is None:
            precondition = _preconditioner(lin, laplacian, cfg, generator)
        inner = _damped_solve(lin, gradient, damping, residual, theta, cfg, precondition)
        if laplacian is not None and precondition is None and inner.stop_reason == "max_iter":
            laplacian_active = True
        direction = inner.x
        # the model's residual at the trial point: r + J d (linear model)
        model_residual = lin.r + inner.Ax
        cg_iterations = inner.iterations
        acceleration_ratio = math.nan
        if cfg.geodesic_acceleration:
            accel = _geodesic_acceleration(lin, direction, inner.Ax, damping, residual, theta,
                                           cfg, precondition)
            if accel is None:           # no simulation at the probe point: a failed step
                acceleration_ratio = math.inf
            else:
                second, accel = accel
                acceleration_ratio = 2.0 * float(torch.linalg.vector_norm(accel.x)) / max(
                    float(torch.linalg.vector_norm(direction)), 1e-300)
                cg_iterations += accel.iterations
                direction = direction + 0.5 * accel.x
                # second-order model of the path theta + v + a / 2:
                # r + J v + (r_vv + J a) / 2
                model_residual = model_residual + 0.5 * (second + accel.Ax)
        predicted = 0.5 * lin.norm ** 2 - 0.5 * float(torch.dot(model_residual, model_residual))
        # Transtrum's safeguard: a correction comparable with the step means the
        # quadratic model of the path is not trustworthy either; reject without a trial.
        candidate = try_linearize(residual, theta + direction) \
            if not acceleration_ratio > cfg.geodesic_alpha else None
        actual = 0.5 * lin.norm ** 2 - 0.5 * candidate.norm ** 2 if candidate is not None else -math.inf
        gain = actual / predicted if predicted > 0 else -math.inf
        if candidate is not None and math.isfinite(candidate.norm) and gain > 0:
            step_norm = float(torch.linalg.vector_norm(direction))
            previous_norm = lin.norm
            theta, lin = candidate.theta, candidate
            gradient = lin.vjp(lin.r)
            precondition = None         # belongs to the old linearisation
            if cfg.damping_update == "nielsen":
                damping *= max(cfg.decrease, 1.0 - (2.0 * min(gain, 1.0) - 1.0) ** 3)
            elif gain > 0.75:
                damping *= cfg.decrease
            elif gain < 0.25:
                damping *= cfg.increase
            growth = 2.0
            accepted = True
        else:
            # Rejected: theta and its linearisation stay exactly as they were.
            step_norm = 0.0
            damping *= growth
            growth *= 2.0
            accepted = False
        extra = {"acceleration_ratio": acceleration_ratio} if cfg.geodesic_acceleration else {}
        stop = record(iteration, step_norm, cg_iterations, accepted, used_damping,
                      gain_ratio=gain if math.isfinite(gain) else -1.0,
                      gradient_norm=float(torch.linalg.vector_norm(gradient)), **extra)
        if stop:
            return finish(theta, False, "interrupted", history, clock)
    reason = _stop_reason(lin.norm, previous_norm, float(torch.linalg.vector_norm(gradient)),
                          gradient_norm0, residual.noise_level, cfg)
    return finish(theta, reason is not None, reason or "max_iter", history, clock)


def _damped_solve(lin: Linearization, gradient: Tensor, damping: float,
                  residual: ResidualFunction, theta: Tensor, cfg: LevenbergMarquardtConfig,
                  precondition: Callable[[Tensor], Tensor] | None = None) -> CGLSResult:
    """CGLS on ``min ||J d + r||^2 + lam ||d||^2`` to relative normal residual ``cg_rtol``."""
    return cgls(lin.jvp, lin.vjp, -lin.r, theta.numel(), shift=damping, residual_target=0.0,
                max_iter=cfg.cg_max_iter, project=residual.projector(theta),
                rmatvec_b=-gradient, normal_rtol=cfg.cg_rtol, preconditioner=precondition)


def _geodesic_acceleration(lin: Linearization, velocity: Tensor, j_velocity: Tensor,
                           damping: float, residual: ResidualFunction, theta: Tensor,
                           cfg: LevenbergMarquardtConfig,
                           precondition: Callable[[Tensor], Tensor] | None
                           ) -> tuple[Tensor, CGLSResult] | None:
    """Transtrum and Sethna's geodesic acceleration ``a`` of the damped step ``v``.

    ``a`` solves ``min ||J a + r_vv||^2 + lam ||a||^2`` with the second directional
    derivative ``r_vv ~ (2 / h) ((r(theta + h v) - r) / h - J v)`` (one simulation
    without a graph, ``h = geodesic_step``); the trial step is ``v + a / 2``. Returns
    ``(r_vv, a)``, or ``None`` when the simulation fails at ``theta + h v``.
    """
    h = cfg.geodesic_step
    try:
        shifted = residual.value(theta + h * velocity)
    except SimulationError:
        return None
    if not bool(torch.isfinite(shifted).all()):
        return None
    second = (2.0 / h) * ((shifted - lin.r) / h - j_velocity)
    return second, cgls(lin.jvp, lin.vjp, -second, theta.numel(), shift=damping,
                        residual_target=0.0, max_iter=cfg.geodesic_cg_max_iter,
                        project=residual.projector(theta), normal_rtol=cfg.cg_rtol,
                        preconditioner=precondition)


def _preconditioner(lin: Linearization, laplacian: GraphLaplacian | None,
                    cfg: LevenbergMarquardtConfig,
                    generator: torch.Generator) -> Callable[[Tensor], Tensor] | None:
    """``s -> C^{-1} (D^T D + eps I) C^{-1} s`` at this linearisation (``None``: no preconditioner).

    ``C = diag(c)``, ``c_j`` the column norm ``||J e_j||`` normalised to mean 1, from
    ``k = preconditioner_probes`` Rademacher vectors ``w`` (``E[(J^T w)_j^2] = ||J e_j||^2``,
    relative error about ``(2 k)^{-1/2}``): ``k`` products ``J^T w``, no factorisation.
    Norms below 1e-3 of the mean (parameters the data barely see) are raised to it.
    """
    if laplacian is None:
        return None
    squares = torch.zeros_like(lin.theta)
    for _ in range(cfg.preconditioner_probes):
        signs = torch.randint(0, 2, lin.r.shape, generator=generator) * 2 - 1
        squares += lin.vjp(signs.to(lin.r)) ** 2
    norms = (squares / cfg.preconditioner_probes).sqrt()
    mean = float(norms.mean())
    inverse_norms = (1.0 / (norms / mean).clamp(min=1e-3)) if mean > 0 and math.isfinite(mean) \
        else torch.ones_like(norms)
    shift = cfg.preconditioner_shift

    def precondition(s: Tensor) -> Tensor:
        v = inverse_norms * s
        return inverse_norms * (laplacian(v) + shift * v)

    return precondition


def _needs_difference_operator(config: LevenbergMarquardtConfig) -> bool:
    return config.preconditioner == "difference"


#: experiments/fit.py hands this solver the parameterisation's ``D`` when its config asks.
levenberg_marquardt.needs_difference_operator = _needs_difference_operator  # type: ignore[attr-defined]

__all__ = ["PRECONDITIONERS", "LevenbergMarquardtConfig", "SolverConfigError", "levenberg_marquardt"]
