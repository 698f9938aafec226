"""Inexact Gauss-Newton (REGINN) with the discrepancy principle.

Minimises ``0.5 ||r(theta)||^2``. Each outer iteration solves the linearised problem
``min ||J d + r||`` matrix-free by CGLS on ``J v`` / ``J^T w``, stopped by the relative
linear-residual rule ``||J d + r|| <= eta_k ||r||`` (Rieder's REGINN; ``eta_k`` follows
the Eisenstat-Walker forcing sequence in ``[eta_min, eta_max]`` and never asks for a
linear residual below the noise level). A backtracking (Armijo) line search on
``0.5 ||r||^2`` safeguards the step. Outer stop: :func:`~.base.least_squares_stop`
(discrepancy ``||r|| <= tau delta`` when the noise level is known, else relative
decrease, gradient or residual negligible); ``tolerance`` also when CGLS finds no
descent direction, ``line_search`` when no step length decreases the objective,
``resolution`` (converged) when a trial's misfit is bit-identical to the current one (the
simulation cannot tell the step from the current point; shorter steps would repeat it).

Bounds on ``theta`` (:meth:`~.base.Solver.set_bounds`, :mod:`.bounds`): the active
parameters are projected out of CGLS and its trust-region box is the room the free ones
have left (with ``max_step``'s), so the step and every shorter one stay inside.

``max_step`` (the largest change of one parameter per step) is a trust region for the
inner CGLS (Steihaug's truncated CG with a box): it stops where its next update would
leave ``||d||_inf <= max_step``, on the boundary, so steps are never clipped afterwards
(why: ``docs/notes/gauss_newton.md``).

``preconditioner=difference`` (needs the parameterisation's ``D``) runs CGLS on
``J S`` with ``S S^T = D^T D + s I`` (:class:`~.preconditioners.DifferencePreconditioner`);
the shift ``s`` starts at ``preconditioner_shift`` (units of the largest diagonal of
``D^T D``) and is scaled by ``||r_k|| / ||r_0||``: rough steps only once the linear model
is good. ``preconditioner=auto`` (the default) decides once, at ``theta0``
(:func:`wants_difference_preconditioner`): ``difference`` when ``D`` is given, the data
are at least as many as the parameters (``m >= n``) and the noise level is unknown, zero
or at most ``auto_noise_ratio`` times ``||r_0||``; ``none`` otherwise, where the
discrepancy principle's early stopping is the regularisation (the preconditioner's first
Krylov vectors are the rough modes). Measurements: ``docs/notes/gauss_newton.md``.

Cost of one accepted full step with ``m`` CG iterations: one factorisation (the new
point) and at most ``2m + 1`` solves.

Dense Jacobian (``dense_jacobian_max_params``, see :mod:`.least_squares`): when the
residual provides ``jacobian`` and ``n`` is small, each accepted point materialises
``J`` once (one solve with ``n`` right-hand sides per stored factor) and CGLS runs on
matrix products: the same REGINN and discrepancy logic, iterations cost no simulation.

Carried state (:meth:`GaussNewton.state_dict`): ``theta``, the gradient ``J^T r`` at
``theta``, the forcing term ``eta``, the previous ``||r||``, ``||J^T r_0||`` and
``||r_0||`` (the preconditioner shift follows from it).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Iterable

import torch
from torch import Tensor

from ..linalg import cgls
from ..records import Callback, IterationRecord, SolveResult, StopReason
from ..residual import Linearization, ResidualFunction, try_linearize
from ..settings import Choice
from .base import Need, Needs, Stop, clone, least_squares_stop, require
from .least_squares import LeastSquaresConfig, LeastSquaresSolver
from .preconditioners import DifferencePreconditioner

class GaussNewtonPreconditioner(Choice):
    """CGLS in parameter space: ``none``, ``difference`` (``D^T D + s I``; needs ``D``) or
    ``auto`` (decided at ``theta0``: :func:`wants_difference_preconditioner`)."""

    auto = "auto"
    none = "none"
    difference = "difference"


@dataclasses.dataclass
class GaussNewtonConfig(LeastSquaresConfig):
    """Settings of ``solver=gauss_newton``."""

    name: str = "gauss_newton"
    max_iter: int = 50              # outer iterations
    tau: float = 1.5                # discrepancy principle ||r|| <= tau * delta
    eta_max: float = 0.1            # REGINN: largest relative linear residual asked of CGLS
    eta_min: float = 1e-6           # smallest (fast local convergence without noise)
    cg_max_iter: int = 200          # CGLS iterations per outer iteration
    cg_rtol: float = 0.0            # also stop CGLS when ||J^T (r + J d)|| <= cg_rtol ||J^T r||
                                    # (0: off; for penalised problems whose minimum ||r|| > 0)
    rtol: float = 1e-4              # stop when ||r|| decreased by less than this fraction
    gtol: float = 1e-12             # stop when ||J^T r|| <= gtol * ||J^T r_0||
    atol: float = 0.0               # stop when ||r|| <= atol
    armijo: float = 1e-4            # sufficient-decrease constant of the line search
    max_backtracks: int = 12        # step halvings before giving up
    preconditioner: GaussNewtonPreconditioner = GaussNewtonPreconditioner.auto
                                    # CGLS in parameter space: auto | none | difference
                                    # (D^T D + s I); auto: see wants_difference_preconditioner
    auto_noise_ratio: float = 1e-3  # auto: data with noise level <= this * ||r_0|| are clean
    preconditioner_shift: float = 4.0  # s at theta0, in units of the largest diagonal of
                                       # D^T D; scaled by ||r_k|| / ||r_0|| as r falls

    def check(self) -> None:
        super().check()
        require(self.tau > 1, f"solver.tau must be > 1 (discrepancy principle), got {self.tau}")
        require(0 < self.eta_min <= self.eta_max < 1,
                f"need 0 < solver.eta_min <= solver.eta_max < 1, got {self.eta_min}, "
                f"{self.eta_max}")
        require(self.cg_max_iter >= 1, f"solver.cg_max_iter must be >= 1, got {self.cg_max_iter}")
        require(0 <= self.cg_rtol < 1, f"solver.cg_rtol must be in [0, 1), got {self.cg_rtol}")
        require(self.rtol >= 0 and self.gtol >= 0 and self.atol >= 0,
                "solver.rtol, solver.gtol and solver.atol must be >= 0")
        require(0 < self.armijo < 0.5, f"solver.armijo must be in (0, 0.5), got {self.armijo}")
        require(self.max_backtracks >= 0, "solver.max_backtracks must be >= 0")
        require(self.auto_noise_ratio >= 0,
                f"solver.auto_noise_ratio must be >= 0, got {self.auto_noise_ratio}")
        require(self.preconditioner_shift >= 0,
                f"solver.preconditioner_shift must be >= 0, got {self.preconditioner_shift}")

    def needs(self) -> Needs:
        """``D`` with ``preconditioner=difference``; where offered with ``auto``."""
        if self.preconditioner == GaussNewtonPreconditioner.difference:
            return Needs(Need.required)
        if self.preconditioner == GaussNewtonPreconditioner.auto:
            return Needs(Need.if_offered)
        return Needs()


def wants_difference_preconditioner(has_D: bool, m: int, n: int, noise_level: float | None,
                                    initial_misfit: float, noise_ratio: float) -> bool:
    """``preconditioner=auto``: whether CGLS is preconditioned by ``D^T D`` for this run.

    Yes when ``D`` is there, the data determine the parameters (``m >= n``) and are clean
    (noise level unknown, zero, or ``<= noise_ratio * ||r_0||``): nothing is left for early
    stopping to regularise, and the preconditioner cuts CGLS's iterations. No on noisy or
    sparse data, where the discrepancy principle stops a Krylov method early on purpose
    and the preconditioned one keeps a rougher field. Figures:
    ``docs/notes/gauss_newton.md``.
    """
    if not has_D or m < n:
        return False
    return noise_level is None or noise_level <= noise_ratio * initial_misfit


class GaussNewton(LeastSquaresSolver):
    """Inexact Gauss-Newton (see the module docstring).

    Args:
        config: :class:`GaussNewtonConfig`.
        D: ``(n_edges, n)`` sparse difference operator, needed by
            ``preconditioner='difference'`` (ignored otherwise).
        groups: unused (accepted for a uniform call).
    """

    config_class = GaussNewtonConfig
    config: GaussNewtonConfig

    def __init__(self, config: GaussNewtonConfig | None = None, *, D: Tensor | None = None,
                 groups: Tensor | None = None) -> None:
        super().__init__(config, D=D, groups=groups)
        self.preconditioner: DifferencePreconditioner | None = None
        self.preconditioned = False

    def _setup(self, like: Tensor) -> None:
        self.preconditioner = DifferencePreconditioner(self.D, like) \
            if self.preconditioned else None

    def _choose_preconditioner(self, lin: Linearization) -> bool:
        """Whether this run preconditions CGLS (``auto`` decides from the start point)."""
        cfg = self.config
        if cfg.preconditioner != GaussNewtonPreconditioner.auto:
            return cfg.preconditioner == GaussNewtonPreconditioner.difference
        return wants_difference_preconditioner(
            self.D is not None, lin.r.numel(), lin.theta.numel(), self.residual.noise_level,
            lin.norm, cfg.auto_noise_ratio)

    def start(self, theta0: Tensor) -> IterationRecord:
        theta = theta0.detach().clone()
        self.choose_path(theta)
        self.lin = self.residual.linearize(theta)
        self.preconditioned = self._choose_preconditioner(self.lin)
        self._setup(theta)
        self.lin = self.adopt(self.lin)
        self.gradient = self.lin.vjp(self.lin.r)
        self.gradient_norm0 = self.stationarity(theta, self.gradient)
        self.eta = self.config.eta_max
        self.previous_norm: float | None = None
        self.norm0 = self.lin.norm
        return self._record(0.0, 0, eta=self.eta, gradient_norm=self.gradient_norm0)

    def _record(self, step_norm: float, cg_iterations: int, **extra: float) -> IterationRecord:
        lin = self.lin
        assert lin is not None
        return self.record(lin.theta, 0.5 * lin.norm ** 2, lin.norm, step_norm, cg_iterations,
                           math.nan, True, **extra, preconditioned=float(self.preconditioned),
                           **self.path_extra())

    def stop_rule(self) -> Stop | None:
        cfg = self.config
        assert self.lin is not None
        return least_squares_stop(self.lin.norm, self.previous_norm,
                                  self.stationarity(self.lin.theta, self.gradient),
                                  self.gradient_norm0, self.residual.noise_level,
                                  cfg.tau, cfg.atol, cfg.gtol, cfg.rtol)

    def step(self) -> IterationRecord | Stop:
        cfg, residual, lin = self.config, self.residual, self.lin
        assert lin is not None
        theta = lin.theta
        # Inner solve: never ask the linear model to fit below the noise.
        target = self.eta * lin.norm
        if residual.noise_level is not None:
            target = max(target, residual.noise_level)
        if self.preconditioner is not None:
            # Shift continuation (like Levenberg-Marquardt damping): smooth steps while the
            # linear model is poor, full Laplacian preconditioning near the solution.
            self.preconditioner.shift = cfg.preconditioner_shift * lin.norm / max(self.norm0,
                                                                                 1e-300)
        inner = cgls(lin.jvp, lin.vjp, -lin.r, theta.numel(), residual_target=target,
                     max_iter=cfg.cg_max_iter, project=self.projector(self.gradient),
                     rmatvec_b=-self.gradient, preconditioner=self.preconditioner,
                     max_abs=cfg.max_step, box=self.step_box(),
                     **({"normal_rtol": cfg.cg_rtol} if cfg.cg_rtol > 0 else {}))
        # inside the max_step box by construction (CGLS stops on its boundary)
        direction, model_change = inner.x, inner.Ax
        slope = float(torch.dot(lin.r, model_change))  # d/da 0.5||r + a J d||^2 at a = 0
        if slope >= 0 or not math.isfinite(slope):
            return Stop(True, StopReason.tolerance)
        trial, step, at_resolution = self._line_search(theta, direction, slope)
        if at_resolution:
            return Stop(True, StopReason.resolution)
        if trial is None:
            return Stop(False, StopReason.line_search)
        self.previous_norm = lin.norm
        # Eisenstat-Walker (choice 2) forcing term for the next inner solve.
        eta_next = 0.9 * (trial.norm / lin.norm) ** 2
        if 0.9 * self.eta ** 2 > 0.1:
            eta_next = max(eta_next, 0.9 * self.eta ** 2)
        self.eta = min(cfg.eta_max, max(cfg.eta_min, eta_next))
        step_norm = float(torch.linalg.vector_norm(trial.theta - theta))
        self.lin = self.adopt(trial)
        self.gradient = trial.vjp(trial.r)
        return self._record(step_norm, inner.iterations, eta=self.eta, step_length=step,
                            gradient_norm=float(torch.linalg.vector_norm(self.gradient)),
                            linear_residual=inner.residual_norm)

    def step_box(self) -> tuple[Tensor, Tensor] | None:
        """With bounds, CGLS's trust region: the room the free parameters have left (and
        ``max_step``); every step length of the line search (``<= 1``) stays inside."""
        limit = self.step_limit(self.gradient)
        return limit if isinstance(limit, tuple) else None

    def _line_search(self, theta: Tensor, direction: Tensor,
                     slope: float) -> tuple[Linearization | None, float, bool]:
        """Backtracking (Armijo); each trial point is one factorisation. Returns the
        accepted point (or ``None``), its step length, and whether a trial's misfit was
        bit-identical to the current one: the simulation cannot tell the step from this
        point (a warm-started Newton converged there in 0 iterations), and every shorter
        step would be the same, so the fit is at the simulation's resolution."""
        cfg, lin = self.config, self.lin
        assert lin is not None
        step = 1.0
        for _ in range(cfg.max_backtracks + 1):
            candidate = try_linearize(self.residual, theta + step * direction)
            if candidate is not None and candidate.norm == lin.norm:
                return None, step, True
            if candidate is not None and math.isfinite(candidate.norm) and \
                    0.5 * candidate.norm ** 2 <= 0.5 * lin.norm ** 2 + cfg.armijo * step * slope:
                return candidate, step, False
            step *= 0.5
        return None, step, False

    # -- state -----------------------------------------------------------------------------
    def _get_state(self) -> dict[str, Any]:
        return {"gradient": clone(self.gradient), "eta": self.eta,
                "previous_norm": self.previous_norm, "gradient_norm0": self.gradient_norm0,
                "norm0": self.norm0, "preconditioned": self.preconditioned}

    def _set_state(self, state: dict[str, Any]) -> None:
        self._saved_theta = state["theta"].detach().clone()
        self.gradient = state["gradient"].detach().clone()
        self.eta = float(state["eta"])
        self.previous_norm = None if state["previous_norm"] is None \
            else float(state["previous_norm"])
        self.gradient_norm0 = float(state["gradient_norm0"])
        self.norm0 = float(state["norm0"])
        self.preconditioned = bool(state.get(
            "preconditioned", self.config.preconditioner == GaussNewtonPreconditioner.difference))

    def resume(self) -> None:
        self._setup(self._saved_theta)
        self.choose_path(self._saved_theta)
        self.lin = self.adopt(self.residual.linearize(self._saved_theta))


def gauss_newton(residual: ResidualFunction, theta0: Tensor,
                 config: GaussNewtonConfig | None = None,
                 callbacks: Iterable[Callback] = (), *, D: Tensor | None = None,
                 groups: Tensor | None = None) -> SolveResult:
    """``GaussNewton(config, D=D, groups=groups).solve(residual, theta0, callbacks)``.

    Minimise ``0.5 ||r(theta)||^2`` from ``theta0``; callbacks get an
    :class:`IterationRecord` per outer iteration (0 = the initial point) and stop the
    run by returning ``True``; ``D`` is needed by ``preconditioner='difference'``.
    """
    return GaussNewton(config, D=D, groups=groups).solve(residual, theta0, callbacks)


__all__ = ["GaussNewton", "GaussNewtonConfig", "GaussNewtonPreconditioner", "gauss_newton",
           "wants_difference_preconditioner"]
