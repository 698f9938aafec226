"""Levenberg-Marquardt with gain-ratio damping.

Minimises ``0.5 ||r(theta)||^2``. Each iteration solves the damped normal equations
``(J^T J + lam I) d = -J^T r`` matrix-free (CGLS with a shift) and compares the actual
decrease of ``0.5 ||r||^2`` with the one the model predicts (gain ratio ``rho``):

* ``rho > 0``: the step is accepted; ``lam`` shrinks by ``decrease`` when
  ``rho > 0.75`` and grows by ``increase`` when ``rho < 0.25`` (Marquardt), or
  ``lam *= max(decrease, 1 - (2 rho - 1)^3)`` (``damping_update='nielsen'``);
* otherwise the step is rejected: ``theta`` stays exactly unchanged and ``lam`` grows by
  a doubling factor (2, 4, 8, ... until a step is accepted). A rejected step costs one
  factorisation (the trial point); the current point's linearisation is kept. A step
  whose linear (or second-order) model predicts no decrease is rejected without
  simulating the trial (its gain ratio could not be positive).

``max_step`` (a bound on every parameter's change) clips each component of the step;
where clipping leaves a step the linear model says does not descend, the damping doubles
and the damped system is solved again before any trial is simulated (see
:meth:`LevenbergMarquardt._limit_step`).

Bounds on ``theta`` (:meth:`~.base.Solver.set_bounds`, :mod:`.bounds`): the active
parameters are projected out of the damped solve and the step's box is the room the free
ones have left (with ``max_step``'s), handled as ``max_step``'s box is.

Stop rules: :func:`~.base.least_squares_stop` (discrepancy first), then ``stalled``
when ``lam`` exceeds ``damping_max`` times its start; ``resolution`` (converged) when a
trial's misfit is bit-identical to the current one: the simulation cannot tell the step
from the current point (a warm-started Newton converged there in 0 iterations), and
more damping would only repeat that.

Dense Jacobian (``dense_jacobian_max_params``, see :mod:`.least_squares`): when the
residual provides ``jacobian`` and ``n`` is small, each accepted point materialises
``J`` once and the damped normal equations ``(J^T J + lam I) d = -J^T r`` (on the
complement of the gauge) are solved exactly by Cholesky
(:class:`~.least_squares.DenseNormalEquations`; ``lstsq`` where Cholesky fails), also
for the geodesic acceleration; the difference preconditioner (which only changes the
Krylov space) is not used there. A rejected step then costs one factorisation per frame
and no solve. Measurements: ``docs/notes/levenberg_marquardt.md``.

Opt-in (all on in ``solver=levenberg_marquardt_geodesic``):
``geodesic_acceleration`` (Transtrum and Sethna: a second-order correction ``a / 2``
from one finite-difference simulation; steps with ``2 ||a|| / ||v|| > geodesic_alpha``
are rejected without a trial) and ``preconditioner='difference'`` (CGLS in the metric
``C^{-1} (D^T D + eps I) C^{-1}``, ``C`` the Jacobian's column norms from
``preconditioner_probes`` random products ``J^T w`` per linearisation; switched on
after the first damped solve that reaches ``cg_max_iter``). The damped system, hence
the step, is the same with and without it. Measurements and the reasons for these
choices: ``docs/notes/levenberg_marquardt.md``.

Carried state (:meth:`LevenbergMarquardt.state_dict`): ``theta``, the gradient, the
damping ``lam``, its rejection growth factor, ``lam_0``, ``||J^T r_0||``, the previous
``||r||``, whether the difference preconditioner is active and its column scaling at
the current linearisation, and the probe generator's state.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Iterable

import torch
from torch import Tensor

from ..errors import SimulationError
from ..linalg import CGLSResult, cgls, column_norms
from ..records import Callback, IterationRecord, SolveResult, StopReason
from ..residual import Linearization, ResidualFunction, try_linearize
from ..settings import Choice
from .base import Need, Needs, Stop, clone, least_squares_stop, require
from .least_squares import (DenseNormalEquations, LeastSquaresConfig, LeastSquaresSolver,
                            box_step, clip_step)
from .preconditioners import ColumnScaledLaplacian, GraphLaplacian


class LevenbergMarquardtPreconditioner(Choice):
    """CGLS metric of the damped solve: ``none`` or ``difference``
    (``C^{-1} (D^T D + eps I) C^{-1}``; needs ``D``)."""

    none = "none"
    difference = "difference"


class DampingUpdate(Choice):
    """Damping after an accepted step: ``marquardt`` (gain-ratio thresholds) or
    ``nielsen`` (``max(decrease, 1 - (2 rho - 1)^3)``)."""

    marquardt = "marquardt"
    nielsen = "nielsen"


@dataclasses.dataclass
class LevenbergMarquardtConfig(LeastSquaresConfig):
    """Settings of ``solver=levenberg_marquardt``."""

    name: str = "levenberg_marquardt"
    max_iter: int = 100             # outer iterations (accepted and rejected)
    tau: float = 1.5                # discrepancy principle ||r|| <= tau * delta
    damping_init: float = 0.1       # lam_0 relative to ||J^T r||^2 / ||r||^2 (a J^T J scale)
    damping_update: DampingUpdate = DampingUpdate.marquardt   # after an accepted step:
                                                              # marquardt (thresholds) | nielsen
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
    preconditioner: LevenbergMarquardtPreconditioner = LevenbergMarquardtPreconditioner.none
                                    # none | difference (CGLS in the D^T D + eps I metric; needs D)
    preconditioner_shift: float = 1e-2   # eps, relative to D^T D (eigenvalues in [0, 2 max degree])
    preconditioner_probes: int = 16      # products J^T w per linearisation estimating C
    seed: int = 0                   # of those random probes
    max_box_resolves: int = 30      # max_step: damping doublings while a clipped step does
                                    # not descend (then the step is scaled into the box)

    def check(self) -> None:
        super().check()
        require(self.tau > 1, f"solver.tau must be > 1 (discrepancy principle), got {self.tau}")
        require(self.damping_init > 0, f"solver.damping_init must be > 0, got {self.damping_init}")
        require(0 < self.decrease < 1 < self.increase,
                f"need 0 < solver.decrease < 1 < solver.increase, got {self.decrease}, "
                f"{self.increase}")
        require(self.damping_max > 1, f"solver.damping_max must be > 1, got {self.damping_max}")
        require(self.cg_max_iter >= 1, f"solver.cg_max_iter must be >= 1, got {self.cg_max_iter}")
        require(0 < self.cg_rtol < 1, f"solver.cg_rtol must be in (0, 1), got {self.cg_rtol}")
        require(self.rtol >= 0 and self.gtol >= 0 and self.atol >= 0,
                "solver.rtol, solver.gtol and solver.atol must be >= 0")
        require(self.geodesic_step > 0 and self.geodesic_alpha > 0
                and self.geodesic_cg_max_iter >= 1,
                "solver.geodesic_step and solver.geodesic_alpha must be > 0 and "
                "solver.geodesic_cg_max_iter >= 1")
        require(self.preconditioner_shift > 0,
                f"solver.preconditioner_shift must be > 0, got {self.preconditioner_shift}")
        require(self.max_box_resolves >= 0,
                f"solver.max_box_resolves must be >= 0, got {self.max_box_resolves}")
        require(self.preconditioner_probes >= 1,
                f"solver.preconditioner_probes must be >= 1, got {self.preconditioner_probes}")

    def needs(self) -> Needs:
        """``D`` with ``preconditioner=difference``."""
        if self.preconditioner == LevenbergMarquardtPreconditioner.difference:
            return Needs(Need.required)
        return Needs()


class LevenbergMarquardt(LeastSquaresSolver):
    """Levenberg-Marquardt (see the module docstring). Records carry the damping used
    and whether the step was accepted.

    Args:
        config: :class:`LevenbergMarquardtConfig`.
        D: ``(n_edges, n)`` sparse difference operator, needed by
            ``preconditioner='difference'`` (ignored otherwise).
        groups: unused.
    """

    config_class = LevenbergMarquardtConfig
    config: LevenbergMarquardtConfig

    def set_bounds(self, lower: Tensor, upper: Tensor) -> None:
        require(not self.config.geodesic_acceleration, "solver.geodesic_acceleration cannot "
                "keep the parameters within bounds (its correction leaves the step's box); "
                "set it false or turn the bounds off")
        super().set_bounds(lower, upper)

    def __init__(self, config: LevenbergMarquardtConfig | None = None, *,
                 D: Tensor | None = None, groups: Tensor | None = None) -> None:
        super().__init__(config, D=D, groups=groups)
        self._normal: DenseNormalEquations | None = None   # dense path: of self.lin

    def _setup(self, like: Tensor) -> None:
        cfg = self.config
        self.laplacian = GraphLaplacian(self.D, like) \
            if cfg.preconditioner == LevenbergMarquardtPreconditioner.difference else None
        self.generator = torch.Generator().manual_seed(cfg.seed)

    def start(self, theta0: Tensor) -> IterationRecord:
        cfg = self.config
        theta = theta0.detach().clone()
        self._setup(theta)
        self.laplacian_active = False
        self.choose_path(theta)
        lin = self.lin = self.adopt(self.residual.linearize(theta))
        self.gradient = lin.vjp(lin.r)
        self.gradient_norm0 = self.stationarity(theta, self.gradient)
        if lin.norm > 0 and self.gradient_norm0 > 0:
            self.damping = cfg.damping_init * (self.gradient_norm0 / lin.norm) ** 2
        else:
            self.damping = cfg.damping_init
        self.damping0 = self.damping
        # The preconditioner follows the linearisation (a rejected step keeps it). It waits
        # for the first damped solve that reaches cg_max_iter: while lam dominates J^T J the
        # identity is the better preconditioner (and costs no probes).
        self.precondition: ColumnScaledLaplacian | None = None
        self.growth = 2.0
        self.previous_norm: float | None = None
        return self.record(lin.theta, 0.5 * lin.norm ** 2, lin.norm, 0.0, 0, self.damping, True,
                           gradient_norm=self.gradient_norm0, **self.path_extra())

    def stop_rule(self) -> Stop | None:
        cfg = self.config
        assert self.lin is not None
        stop = least_squares_stop(self.lin.norm, self.previous_norm,
                                  self.stationarity(self.lin.theta, self.gradient),
                                  self.gradient_norm0, self.residual.noise_level,
                                  cfg.tau, cfg.atol, cfg.gtol, cfg.rtol)
        if stop is None and self.damping > cfg.damping_max * self.damping0:
            stop = Stop(False, StopReason.stalled)
        return stop

    def step(self) -> IterationRecord | Stop:
        cfg, residual, lin = self.config, self.residual, self.lin
        assert lin is not None
        theta = lin.theta
        used_damping = damping = self.damping
        normal = self._normal_equations()
        if normal is None and self.laplacian_active and self.precondition is None:
            self.precondition = _preconditioner(lin, self.laplacian, cfg, self.generator)
        inner = self._damped_step(damping, normal)
        if normal is None:
            if self.laplacian is not None and self.precondition is None \
                    and inner.stop_reason == "max_iter":
                self.laplacian_active = True
        if cfg.max_step > 0 or self.bounds is not None:     # the step's box (.bounds)
            inner, damping = self._limit_step(inner, damping, normal)
            self.damping = used_damping = damping
        direction = inner.x
        # the model's residual at the trial point: r + J d (linear model)
        model_residual = lin.r + inner.Ax
        cg_iterations = inner.iterations
        acceleration_ratio = math.nan
        if cfg.geodesic_acceleration:
            accel = _geodesic_acceleration(lin, direction, inner.Ax, damping, residual, theta,
                                           cfg, self.precondition, normal)
            if accel is None:           # no simulation at the probe point: a failed step
                acceleration_ratio = math.inf
            else:
                second, accel = accel
                acceleration_ratio = 2.0 * float(torch.linalg.vector_norm(accel.x)) / max(
                    float(torch.linalg.vector_norm(direction)), 1e-300)
                cg_iterations += accel.iterations
                direction = direction + 0.5 * accel.x
                # second-order model of the path theta + v + a / 2: r + J v + (r_vv + J a) / 2
                model_residual = model_residual + 0.5 * (second + accel.Ax)
        predicted = 0.5 * lin.norm ** 2 - 0.5 * float(torch.dot(model_residual, model_residual))
        # Transtrum's safeguard: a correction comparable with the step means the
        # quadratic model of the path is not trustworthy either; reject without a trial.
        # A step the model itself says does not descend (a clipped step, see _limit_step;
        # a second-order correction) is rejected without one too: its gain ratio could
        # not be positive, and a trial costs a simulation.
        candidate = try_linearize(residual, theta + direction) \
            if predicted > 0 and not acceleration_ratio > cfg.geodesic_alpha else None
        if candidate is not None and candidate.norm == lin.norm:
            # A trial misfit bit-identical to this one: the simulation cannot tell the step
            # from this point (a Newton warm-started here is already converged at the trial,
            # 0 iterations in every frame; or theta + d rounds to theta). More damping only
            # shortens the step, so every later trial would be the same: the fit is at the
            # simulation's resolution (no record: theta is unchanged).
            return Stop(True, StopReason.resolution)
        actual = 0.5 * lin.norm ** 2 - 0.5 * candidate.norm ** 2 if candidate is not None \
            else -math.inf
        gain = actual / predicted if predicted > 0 else -math.inf
        if candidate is not None and math.isfinite(candidate.norm) and gain > 0:
            step_norm = float(torch.linalg.vector_norm(direction))
            self._accept(candidate, gain)
            accepted = True
        else:
            # Rejected: theta and its linearisation stay exactly as they were.
            step_norm = 0.0
            self.damping *= self.growth
            self.growth *= 2.0
            accepted = False
        lin = self.lin
        extra = {"acceleration_ratio": acceleration_ratio} if cfg.geodesic_acceleration else {}
        return self.record(lin.theta, 0.5 * lin.norm ** 2, lin.norm, step_norm, cg_iterations,
                           used_damping, accepted,
                           gain_ratio=gain if math.isfinite(gain) else -1.0,
                           gradient_norm=float(torch.linalg.vector_norm(self.gradient)), **extra,
                           **self.path_extra())

    def _limit_step(self, inner: CGLSResult, damping: float,
                    normal: DenseNormalEquations | None) -> tuple[CGLSResult, float]:
        """``inner`` with every component clipped to ``[-max_step, max_step]`` and ``J d``
        recomputed (a matrix product on the dense path, one ``J v`` otherwise), and the
        damping it was solved with.

        Clipping per parameter, not raising the damping: a few weakly observed parameters
        (a grid node outside the body) would otherwise damp every other direction as
        well. But clipping a nearly cancelling pair of large components can leave a step
        the linear model says does not descend; then the damping doubles (2, 4, 8, ...
        times) and the damped system is solved again, as a rejected trial would have
        done, without simulating the trial (an exact solve on the dense path, CGLS
        products otherwise). After ``max_box_resolves`` doublings the step is scaled into
        the box instead (:func:`~.least_squares.box_step`), which descends."""
        cfg = self.config
        lin = self.lin
        assert lin is not None
        growth, limit = 2.0, self.step_limit(self.gradient)
        for _ in range(cfg.max_box_resolves):
            clipped, j_clipped, descends = clip_step(lin, inner.x, limit)
            if clipped is inner.x:
                return inner, damping
            if descends:
                return dataclasses.replace(inner, x=clipped, Ax=j_clipped), damping
            damping *= growth
            growth *= 2.0
            inner = self._damped_step(damping, normal)
        x, Ax = box_step(lin, inner.x, inner.Ax, limit)
        return (inner if x is inner.x else dataclasses.replace(inner, x=x, Ax=Ax)), damping

    def _damped_step(self, damping: float, normal: DenseNormalEquations | None) -> CGLSResult:
        """The damped step at the current linearisation (exact on the dense path)."""
        lin = self.lin
        assert lin is not None
        if normal is not None:
            return normal.solve(-lin.r, damping, rmatvec_b=-self.gradient)
        return _damped_solve(lin, self.gradient, damping, self.projector(self.gradient),
                             self.config, self.precondition)

    def _normal_equations(self) -> DenseNormalEquations | None:
        """The exact damped solver of the current linearisation (dense path only)."""
        if not self.dense:
            return None
        normal = self._normal
        if normal is None or normal.lin is not self.lin:
            normal = self._normal = DenseNormalEquations(self.lin,
                                                         self.projector(self.gradient))
        return normal

    def _accept(self, candidate: Linearization, gain: float) -> None:
        cfg = self.config
        assert self.lin is not None
        self.previous_norm = self.lin.norm
        self.lin = self.adopt(candidate)
        self.gradient = candidate.vjp(candidate.r)
        self.precondition = None            # belongs to the old linearisation
        if cfg.damping_update == DampingUpdate.nielsen:
            self.damping *= max(cfg.decrease, 1.0 - (2.0 * min(gain, 1.0) - 1.0) ** 3)
        elif gain > 0.75:
            self.damping *= cfg.decrease
        elif gain < 0.25:
            self.damping *= cfg.increase
        self.growth = 2.0

    # -- state -----------------------------------------------------------------------------
    def _get_state(self) -> dict[str, Any]:
        return {"gradient": clone(self.gradient), "damping": self.damping,
                "growth": self.growth, "damping0": self.damping0,
                "gradient_norm0": self.gradient_norm0, "previous_norm": self.previous_norm,
                "laplacian_active": self.laplacian_active,
                "preconditioner_inverse_norms": None if self.precondition is None
                else clone(self.precondition.inverse_norms),
                "generator_state": self.generator.get_state()}

    def _set_state(self, state: dict[str, Any]) -> None:
        self._saved = state
        self.gradient = state["gradient"].detach().clone()
        self.damping = float(state["damping"])
        self.growth = float(state["growth"])
        self.damping0 = float(state["damping0"])
        self.gradient_norm0 = float(state["gradient_norm0"])
        self.previous_norm = None if state["previous_norm"] is None \
            else float(state["previous_norm"])
        self.laplacian_active = bool(state["laplacian_active"])

    def resume(self) -> None:
        state = self._saved
        theta = state["theta"].detach().clone()
        self._setup(theta)
        self.generator.set_state(state["generator_state"].clone())
        norms = state["preconditioner_inverse_norms"]
        self.precondition = None if norms is None or self.laplacian is None else \
            ColumnScaledLaplacian(self.laplacian, norms.detach().clone(),
                                  self.config.preconditioner_shift)
        self.choose_path(theta)
        self.lin = self.adopt(self.residual.linearize(theta))


def levenberg_marquardt(residual: ResidualFunction, theta0: Tensor,
                        config: LevenbergMarquardtConfig | None = None,
                        callbacks: Iterable[Callback] = (), *, D: Tensor | None = None,
                        groups: Tensor | None = None) -> SolveResult:
    """``LevenbergMarquardt(config, D=D).solve(residual, theta0, callbacks)``."""
    return LevenbergMarquardt(config, D=D, groups=groups).solve(residual, theta0, callbacks)


def _damped_solve(lin: Linearization, gradient: Tensor, damping: float,
                  project: Callable[[Tensor], Tensor] | None, cfg: LevenbergMarquardtConfig,
                  precondition: Callable[[Tensor], Tensor] | None = None) -> CGLSResult:
    """CGLS on ``min ||J d + r||^2 + lam ||d||^2`` to relative normal residual ``cg_rtol``
    (``d`` in the range of ``project``: the gauge's complement, the free parameters)."""
    return cgls(lin.jvp, lin.vjp, -lin.r, lin.theta.numel(), shift=damping, residual_target=0.0,
                max_iter=cfg.cg_max_iter, project=project,
                rmatvec_b=-gradient, normal_rtol=cfg.cg_rtol, preconditioner=precondition)


def _geodesic_acceleration(lin: Linearization, velocity: Tensor, j_velocity: Tensor,
                           damping: float, residual: ResidualFunction, theta: Tensor,
                           cfg: LevenbergMarquardtConfig,
                           precondition: Callable[[Tensor], Tensor] | None,
                           normal: DenseNormalEquations | None = None
                           ) -> tuple[Tensor, CGLSResult] | None:
    """Transtrum and Sethna's geodesic acceleration ``a`` of the damped step ``v``.

    ``a`` solves ``min ||J a + r_vv||^2 + lam ||a||^2`` with the second directional
    derivative ``r_vv ~ (2 / h) ((r(theta + h v) - r) / h - J v)`` (one simulation
    without a graph, ``h = geodesic_step``); the trial step is ``v + a / 2`` (``a`` exact
    with ``normal``, the dense path's solver of the same damped system). Returns
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
    if normal is not None:
        return second, normal.solve(-second, damping)
    return second, cgls(lin.jvp, lin.vjp, -second, theta.numel(), shift=damping,
                        residual_target=0.0, max_iter=cfg.geodesic_cg_max_iter,
                        project=residual.projector(theta), normal_rtol=cfg.cg_rtol,
                        preconditioner=precondition)


def _preconditioner(lin: Linearization, laplacian: GraphLaplacian | None,
                    cfg: LevenbergMarquardtConfig,
                    generator: torch.Generator) -> ColumnScaledLaplacian | None:
    """``C^{-1} (D^T D + eps I) C^{-1}`` at this linearisation (``None``: no preconditioner).

    ``C = diag(c)``, ``c_j`` the column norm ``||J e_j||`` normalised to mean 1, from
    ``k = preconditioner_probes`` Rademacher vectors ``w`` (``E[(J^T w)_j^2] = ||J e_j||^2``,
    relative error about ``(2 k)^{-1/2}``): ``k`` products ``J^T w``, no factorisation.
    Norms below 1e-3 of the mean (parameters the data barely see) are raised to it.
    """
    if laplacian is None:
        return None
    norms = column_norms(lin.vjp, lin.r, lin.theta, cfg.preconditioner_probes, generator)
    mean = float(norms.mean())
    inverse_norms = (1.0 / (norms / mean).clamp(min=1e-3)) if mean > 0 and math.isfinite(mean) \
        else torch.ones_like(norms)
    return ColumnScaledLaplacian(laplacian, inverse_norms, cfg.preconditioner_shift)


__all__ = ["DampingUpdate", "LevenbergMarquardt", "LevenbergMarquardtConfig",
           "LevenbergMarquardtPreconditioner", "levenberg_marquardt"]
