"""Levenberg-Marquardt with gain-ratio damping (Nielsen's update).

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
"""
from __future__ import annotations

import dataclasses
import math
from typing import Iterable

import torch
from torch import Tensor

from ..linalg import cgls
from .gauss_newton import SolverConfigError, _require, _stop_reason
from .records import Callback, IterationRecord, RunClock, SolveResult, emit, finish
from .residual import Linearization, ResidualFunction, try_linearize


@dataclasses.dataclass
class LevenbergMarquardtConfig:
    """Settings of ``solver=levenberg_marquardt``."""

    name: str = "levenberg_marquardt"
    max_iter: int = 100             # outer iterations (accepted and rejected)
    tau: float = 1.5                # discrepancy principle ||r|| <= tau * delta
    damping_init: float = 0.1       # lam_0 relative to ||J^T r||^2 / ||r||^2 (a J^T J scale)
    decrease: float = 1.0 / 3.0     # lam factor after a good step (gain ratio > 0.75)
    increase: float = 2.0           # lam factor after a poor accepted step (gain ratio < 0.25)
    damping_max: float = 1e12       # give up ('stalled') when lam exceeds this times lam_0
    cg_max_iter: int = 200          # CGLS iterations per damped solve
    cg_rtol: float = 1e-6           # stop CGLS when ||J^T J d + lam d + J^T r|| <= cg_rtol ||J^T r||
    rtol: float = 1e-4              # stop when an accepted step reduced ||r|| by less than this
    gtol: float = 1e-12             # stop when ||J^T r|| <= gtol * ||J^T r_0||
    atol: float = 0.0               # stop when ||r|| <= atol

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


def levenberg_marquardt(residual: ResidualFunction, theta0: Tensor,
                        config: LevenbergMarquardtConfig | None = None,
                        callbacks: Iterable[Callback] = ()) -> SolveResult:
    """Minimise ``0.5 ||r(theta)||^2`` from ``theta0`` by Levenberg-Marquardt.

    Args and return as :func:`~torchfit.solvers.gauss_newton.gauss_newton`; records
    carry the damping ``lam`` and whether the step was accepted.
    """
    cfg = config or LevenbergMarquardtConfig()
    cfg.validate()
    callbacks = list(callbacks)
    clock = RunClock()
    theta = theta0.detach().clone()
    lin = residual.linearize(theta)
    gradient = lin.vjp(lin.r)
    gradient_norm0 = float(torch.linalg.vector_norm(gradient))
    if lin.norm > 0 and gradient_norm0 > 0:
        damping = cfg.damping_init * (gradient_norm0 / lin.norm) ** 2
    else:
        damping = cfg.damping_init
    damping0 = damping
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
        inner = _damped_solve(lin, gradient, damping, residual, theta, cfg)
        direction = inner.x
        jd = inner.Ax
        predicted = -float(torch.dot(lin.r, jd)) - 0.5 * float(torch.dot(jd, jd))
        candidate = try_linearize(residual, theta + direction)
        actual = 0.5 * lin.norm ** 2 - 0.5 * candidate.norm ** 2 if candidate is not None else -math.inf
        gain = actual / predicted if predicted > 0 else -math.inf
        if candidate is not None and math.isfinite(candidate.norm) and gain > 0:
            step_norm = float(torch.linalg.vector_norm(direction))
            previous_norm = lin.norm
            theta, lin = candidate.theta, candidate
            gradient = lin.vjp(lin.r)
            if gain > 0.75:
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
        stop = record(iteration, step_norm, inner.iterations, accepted, used_damping,
                      gain_ratio=gain if math.isfinite(gain) else -1.0,
                      gradient_norm=float(torch.linalg.vector_norm(gradient)))
        if stop:
            return finish(theta, False, "interrupted", history, clock)
    reason = _stop_reason(lin.norm, previous_norm, float(torch.linalg.vector_norm(gradient)),
                          gradient_norm0, residual.noise_level, cfg)
    return finish(theta, reason is not None, reason or "max_iter", history, clock)


def _damped_solve(lin: Linearization, gradient: Tensor, damping: float,
                  residual: ResidualFunction, theta: Tensor, cfg: LevenbergMarquardtConfig):
    """CGLS on ``min ||J d + r||^2 + lam ||d||^2`` to relative normal residual ``cg_rtol``."""
    return cgls(lin.jvp, lin.vjp, -lin.r, theta.numel(), shift=damping, residual_target=0.0,
                max_iter=cfg.cg_max_iter, project=residual.projector(theta),
                rmatvec_b=-gradient, normal_rtol=cfg.cg_rtol)


__all__ = ["LevenbergMarquardtConfig", "SolverConfigError", "levenberg_marquardt"]
