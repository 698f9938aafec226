r"""Split Bregman TV for non-linear forward models: the solver and its outer iteration.

Minimises ``Phi_mu(theta) = TV(theta) + mu/2 ||r(theta)||^2`` with
``TV(theta) = sum_g ||(D theta + c)_g||_2``: ``r`` the residual of any problem (only
``r``, ``J v`` and ``J^T w`` are used), ``D`` the parameterisation's sparse difference
operator (handed over, never built here), ``g`` the groups of its rows (each row its own
group: anisotropic TV; ``groups`` with ``isotropic=true``: isotropic TV), ``c`` an
optional constant ``offset``. One outer iteration (scaled ADMM on ``d = D theta + c``)::

    theta <- argmin  mu/2 ||r(theta) - e||^2 + beta/2 ||D theta + c - d + b||^2   (inner solve)
    d     <- shrink(D theta + c + b, 1/beta)                                       (per group)
    b     <- b + D theta + c - d;    e <- e - r(theta) (data Bregman only, else e = 0)

* Inner solve: ``inner_max_iter`` Gauss-Newton or Levenberg-Marquardt steps on the
  stacked residual (:mod:`.stacked`), dense on the stacked Jacobian under
  ``dense_jacobian_max_params``; its CGLS stops at the relative normal residual
  ``clip(cg_rtol_factor * max(primal_rel, dual_rel), cg_rtol, cg_rtol_max)``, never
  rising within a stage. The model residual is a :class:`~.stacked.CachedResidual`:
  every distinct parameter vector is simulated (and factorised) once.
* Weights: :mod:`.weights`; stages and their search in ``mu``:
  :mod:`.stages`; settings: :mod:`.settings`.
* Rejection: an iteration whose objective is not finite, exceeds ``divergence_factor``
  times the best of its stage, or whose inner solve found no descent leaves ``theta``,
  ``d``, ``b`` exactly as they were and doubles ``beta`` (``beta b`` kept); more than
  ``max_rejections`` in a row end the run (``stalled``).

Records (0 is ``theta0``): ``objective`` = ``Phi_mu`` of the current stage, ``misfit`` =
``||r||``, ``cg_iterations`` of the inner solve, ``damping`` (inner LM; ``nan`` for GN),
``accepted`` and ``extra``: ``tv``, ``split_residual`` (``||d - D theta - c||``), ``mu``,
``beta``, ``stage``, ``dual_residual``, ``inner_iterations``, ``inner_rtol`` (accepted
steps), ``dense_jacobian`` (dense path), ``restored = 1`` (the return to an earlier stage).
Stop reasons: ``discrepancy``, ``plateau``, ``tolerance``, ``max_iter``, ``stalled``,
``interrupted`` (:class:`~torchfit.records.StopReason`).

Bounds on ``theta`` (:meth:`~.base.Solver.set_bounds`): handed to the inner solver, which
keeps every iterate inside them (:mod:`.bounds`); a rejected iteration keeps ``theta``.

Carried state (:meth:`SplitBregman.state_dict`, plain values): ``theta``, ``D theta + c``,
``d``, ``b``, ``e``, ``mu``, ``beta``, the stage and its bookkeeping (iteration count,
spectral pair, objective, misfit and ADMM-residual windows, best objective, rejections,
inner tolerance), the search's memory, and what the last record left to decide (the
stage-end test and the ``beta`` update run after a record, so first on resume).
Reasons and figures: ``docs/notes/split_bregman.md``.
"""
from __future__ import annotations

import math
from typing import Any, Iterable

import torch
from torch import Tensor

from ...records import Callback, IterationRecord, SolveResult, StopReason
from ...residual import ResidualFunction
from ..base import Solver, Stop, clone
from ..bounds import ThetaBounds
from ..gauss_newton import GaussNewton, GaussNewtonConfig, GaussNewtonPreconditioner
from ..least_squares import wants_dense_jacobian
from ..levenberg_marquardt import LevenbergMarquardt, LevenbergMarquardtConfig
from .settings import DataBregman, InnerSolver, SplitBregmanConfig
from .stages import StageSearch, at_fixed_point, fixed_weight_stop
from .weights import adapted_beta, admm_stalled, initial_weights
from ..stacked import CachedResidual, LinearResidual, ShiftedResidual, StackedResidual
from ..total_variation import GroupTV, check_difference_operator


_SNAPSHOT = ("theta", "Dtheta", "d", "b", "mu", "beta", "stage", "norm")


class SplitBregman(Solver):
    """Split Bregman TV (see the module docstring).

    Args:
        config: :class:`SplitBregmanConfig`.
        D: ``(n_edges, n)`` sparse difference operator of the parameterisation (required).
        groups: ``(n_edges,)`` group index of every row of ``D`` (used with
            ``config.isotropic``); ``None``: every row its own group.
        offset: ``(n_edges,)`` constant ``c`` in ``TV = sum |D theta + c|`` (default 0).
        penalty: a :class:`GroupTV` (or subclass) replacing the one built from
            ``config.isotropic`` and ``groups``.

    State between outer iterations lives in plain attributes: the iterate (``_theta``,
    ``lin``, ``norm``, ``Dtheta``, ``d``, ``b``, ``mu``, ``beta``, ``stage``), the stage's
    bookkeeping (``stage_iteration``, ``best``, ``spectral``, ``objectives``, ``misfits``,
    ``rejections``), the search over stages (``search``, a
    :class:`~.stages.StageSearch`) and what the last record left to decide
    (``pending``, ``last``).
    """

    config_class = SplitBregmanConfig
    config: SplitBregmanConfig
    supports_bounds = True

    def set_bounds(self, lower: Tensor, upper: Tensor) -> None:
        """Bounds on ``theta`` (:mod:`.bounds`), kept by the inner GN/LM solve."""
        self.bounds = ThetaBounds(lower, upper)

    def __init__(self, config: SplitBregmanConfig | None = None, *, D: Tensor | None = None,
                 groups: Tensor | None = None, offset: Tensor | None = None,
                 penalty: GroupTV | None = None) -> None:
        super().__init__(config, D=D, groups=groups)
        n = int(D.shape[1]) if isinstance(D, Tensor) and D.dim() == 2 else 0
        self.D, self.groups, self.offset = check_difference_operator(D, n, groups, offset)
        self.penalty = penalty

    @property
    def theta(self) -> Tensor:
        return self._theta

    # -- set-up ----------------------------------------------------------------------------
    def _setup(self, like: Tensor) -> None:
        """Operators at ``theta``'s dtype/device, the cached model residual, the inner solver."""
        cfg = self.config
        D, groups, offset = check_difference_operator(self.D, like.numel(), self.groups,
                                                      self.offset, like.dtype, like.device)
        self.tv = self.penalty if self.penalty is not None else GroupTV(
            groups if cfg.isotropic else None, D.shape[0])
        self.c = offset if offset is not None else like.new_zeros(D.shape[0])
        self.model = CachedResidual(self.residual)
        self.diff = LinearResidual(D)
        noise = self.residual.noise_level
        self.staged = bool(cfg.continuation and noise is not None and noise > 0)
        self.level = cfg.tau * noise if self.staged else math.nan
        # the spread of ||noise|| about delta = sigma sqrt(m) (chi distribution, m data):
        # two stages whose misfits differ by less are the same to the data
        m = self.residual.data.numel()
        self.spread = noise / math.sqrt(2.0 * m) if self.staged and m > 0 else 0.0
        # auto: only for clean data with the scale-aware weight; a mu given by the user
        # asks for the penalised problem TV + mu/2 ||r||^2 itself (e.g. denoising)
        self.data_bregman = cfg.data_bregman == DataBregman.on or (
            cfg.data_bregman == DataBregman.auto and not self.staged and cfg.mu is None)
        # The inner problem has a non-zero minimum: its CGLS stops on the normal-equation
        # residual (REGINN's ||J d + r|| <= eta ||r|| could never be met there).
        dense = cfg.dense_jacobian_max_params
        self.dense = wants_dense_jacobian(self.residual, like.numel(), dense)
        if cfg.inner_solver == InnerSolver.gauss_newton:
            self.inner = GaussNewton(GaussNewtonConfig(
                max_iter=cfg.inner_max_iter, cg_max_iter=cfg.cg_max_iter, eta_min=1e-14,
                eta_max=1e-14, cg_rtol=cfg.cg_rtol, dense_jacobian_max_params=dense,
                preconditioner=GaussNewtonPreconditioner.none,
                max_step=cfg.max_step))
        else:
            self.inner = LevenbergMarquardt(LevenbergMarquardtConfig(
                max_iter=cfg.inner_max_iter, cg_max_iter=cfg.cg_max_iter, cg_rtol=cfg.cg_rtol,
                dense_jacobian_max_params=dense, max_step=cfg.max_step))
        if self.bounds is not None:     # every theta comes from the inner solve: it keeps them
            self.inner.set_bounds(self.bounds.lower, self.bounds.upper)

    def start(self, theta0: Tensor) -> IterationRecord:
        theta = theta0.detach().clone()
        self._setup(theta)
        self.lin = self.model.linearize(theta)
        if not math.isfinite(self.lin.norm):
            raise ValueError("the residual at theta0 is not finite")
        if self.dense:
            self.lin.use_dense()      # the scale estimates below are then matrix products
        self.mu, self.beta = initial_weights(self.config, self.lin, theta, self.diff, self.tv,
                                             self.residual.noise_level, self.staged,
                                             self.data_bregman)
        self._theta, self.norm, self.stage = theta, self.lin.norm, 0
        self.norm0 = self.lin.norm
        self.Dtheta = self.diff.matvec(theta) + self.c
        self.d, self.b = self.Dtheta.clone(), torch.zeros_like(self.Dtheta)
        self.e = torch.zeros_like(self.lin.r)     # data Bregman variable (stays 0 when off)
        self.search = StageSearch()
        self._begin_stage()
        return self._record(0.0, 0, math.nan, True, dual_residual=math.nan, inner_iterations=0)

    # -- stages ----------------------------------------------------------------------------
    def _begin_stage(self) -> None:
        self.stage_iteration = 0
        self.admm_residual = math.inf    # max(primal_rel, dual_rel) of the last accepted step
        self.admm_window: list[float] = []   # the same since beta last changed by the stall rule
        self.inner_rtol = math.inf       # the inner tolerance so far in this stage
        self.best = self._objective()[0]
        self.spectral: tuple[Tensor, Tensor] | None = None
        self.objectives: list[float] = []
        self.misfits: list[float] = []
        self.rejections = 0
        self.pending: str | None = None
        self.last: dict[str, Any] | None = None

    def stop_rule(self) -> Stop | None:
        """Decide what the last record left open: the stage's end test and the ``beta``
        update after an accepted iteration, the stall test after a rejected one; at a
        stage's end, the continuation."""
        if self.pending == "restored":
            return Stop(True, self.search.restore_reason)
        status = None
        if self.pending == "accepted":
            status = self._after_accepted()
        elif self.pending == "rejected" and self.rejections > self.config.max_rejections:
            status = "stalled"
        self.pending, self.last = None, None
        if status is None and self.stage_iteration >= self.config.stage_max_iter:
            status = "budget"
        return None if status is None else self._end_stage(status)

    def budget_exhausted(self) -> bool:
        # returning to an accepted earlier stage is one record beyond the budget
        return not self.search.restore_pending and self.iteration >= self.config.max_iter

    def _after_accepted(self) -> str | None:
        """Fixed-point and 'above the level' tests, then the ``beta`` update."""
        cfg, last = self.config, self.last
        assert last is not None
        self.objectives.append(last["objective"])
        tol = cfg.bregman_tol if self.data_bregman else cfg.stage_tol
        fits = not self.data_bregman or self.norm <= tol * self.norm0
        if at_fixed_point(self.objectives, last, tol, fits):
            return "converged"
        self.misfits.append(self.norm)
        if self.staged and StageSearch.out_of_reach(self.misfits, self.level, cfg.above_factor):
            return "above"
        if cfg.adapt_beta and (self.spectral is None or last["stage_iteration"] % 2 == 1):
            self._adapt_beta(last["lam_hat"], last["primal_rel"], last["dual_rel"])
        if cfg.adapt_beta and self.data_bregman:
            self._stall_rule(max(last["primal_rel"], last["dual_rel"]))
        return None

    def _stall_rule(self, admm_residual: float) -> None:
        """Data Bregman: double ``beta`` (keeping ``beta b``) when the ADMM residual has not
        decreased over ``stall_window`` accepted iterations (:func:`admm_stalled`); runs
        with a noise level end their stages by the discrepancy tests instead."""
        window = self.config.stall_window
        if window <= 0:
            return
        self.admm_window.append(admm_residual)
        if admm_stalled(self.admm_window, window):
            self._rescale_beta(2.0 * self.beta)
            self.admm_window = []

    def _rescale_beta(self, beta_new: float) -> None:
        """Change the splitting weight keeping the multiplier ``beta b`` (scaled ADMM)."""
        self.b = self.b * (self.beta / beta_new)
        self.beta = beta_new

    def _adapt_beta(self, lam_hat: Tensor, primal_rel: float, dual_rel: float) -> None:
        """Spectral estimate, else residual balancing (:func:`adapted_beta`); keeps ``beta b``."""
        beta_new = adapted_beta(self.beta, self.spectral, self.Dtheta, lam_hat, primal_rel,
                                dual_rel)
        if beta_new is not None and beta_new != self.beta:
            self._rescale_beta(beta_new)
        self.spectral = (self.Dtheta, lam_hat)

    def _end_stage(self, status: str) -> Stop | None:
        """A stage ended (``converged``, ``above``, ``budget`` or ``stalled``): stop, start
        the next stage, or leave the return to the accepted one pending."""
        cfg = self.config
        if not self.staged:
            return fixed_weight_stop(status)
        if status == "stalled":
            return Stop(False, StopReason.stalled)
        end = self.search.end_stage(self.norm, self.level, self.spread, self.mu, self.stage,
                                    cfg.growth, cfg.max_stages, self._snapshot)
        if end.next_mu is not None:
            self.mu, self.stage = end.next_mu, self.stage + 1
            self._begin_stage()
        return end.stop

    def _snapshot(self) -> dict[str, Any]:
        snap = {key: getattr(self, key if key != "theta" else "_theta") for key in _SNAPSHOT}
        snap["lin"] = self.lin             # kept alive in memory (not saved)
        return snap

    # -- one outer iteration ---------------------------------------------------------------
    def step(self) -> IterationRecord | Stop:
        if self.search.restore_pending:
            return self._restore_accepted()
        self.stage_iteration += 1
        inner = self._inner_solve()
        cg_its = sum(r.cg_iterations for r in inner.history[1:])
        damping = (inner.history[-1].damping
                   if self.config.inner_solver != InnerSolver.gauss_newton else math.nan)
        new_lin = (self.lin if torch.equal(inner.theta, self._theta)
                   else self.model.linearize(inner.theta))   # cached: the inner end point
        new_Dtheta = self.diff.matvec(inner.theta) + self.c
        data_norm = float(torch.linalg.vector_norm(new_lin.r - self.e)) if self.data_bregman \
            else new_lin.norm
        new_obj = self.tv.value(new_Dtheta) + 0.5 * self.mu * data_norm ** 2
        if self._inner_stuck(inner) or not math.isfinite(new_obj) \
                or new_obj > self.config.divergence_factor * self.best:
            return self._reject(cg_its, damping, inner.iterations)
        self.rejections = 0
        step_norm = float(torch.linalg.vector_norm(inner.theta - self._theta))
        lam_hat = self.beta * (self.b + new_Dtheta - self.d)    # intermediate multiplier
        d = self._shrink(new_Dtheta)
        b = self._bregman_update(new_Dtheta, d)
        dual = self.beta * float(torch.linalg.vector_norm(self.diff.rmatvec(d - self.d)))
        self._theta, self.lin, self.norm = inner.theta, new_lin, new_lin.norm
        self.Dtheta, self.d, self.b = new_Dtheta, d, b
        if self.data_bregman:
            self.e = self.e - new_lin.r
        self.best = min(self.best, new_obj)
        primal = float(torch.linalg.vector_norm(new_Dtheta - d))
        primal_rel = primal / max(float(torch.linalg.vector_norm(new_Dtheta)),
                                  float(torch.linalg.vector_norm(d)), 1e-300)
        dual_rel = dual / max(self.beta * float(torch.linalg.vector_norm(self.diff.rmatvec(b))),
                              1e-300)
        self.pending = "accepted"
        self.admm_residual = max(primal_rel, dual_rel)
        self.last = {"objective": new_obj, "primal": primal, "primal_rel": primal_rel,
                     "dual_rel": dual_rel, "step_norm": step_norm, "lam_hat": lam_hat,
                     "stage_iteration": self.stage_iteration - 1}
        return self._record(step_norm, cg_its, damping, True, dual_residual=dual,
                            inner_iterations=inner.iterations,
                            inner_rtol=self.inner.config.cg_rtol)

    def _inner_solve(self) -> SolveResult:
        """``inner_max_iter`` GN/LM steps on ``mu/2 ||r||^2 + beta/2 ||D theta + c - d + b||^2``."""
        self.diff.target = self.d - self.b - self.c
        data = ShiftedResidual(self.model, self.e) if self.data_bregman else self.model
        stacked = StackedResidual([data, self.diff], [self.mu, self.beta], projector_from=0)
        self.inner.config.cg_rtol = self._inner_tolerance()
        return self.inner.solve(stacked, self._theta)

    def _inner_tolerance(self) -> float:
        """The inner CGLS's relative normal-residual tolerance for this outer iteration.

        ``clip(cg_rtol_factor * admm_residual, cg_rtol, cg_rtol_max)``, never rising
        within a stage: inexact inner solves must get more exact for (inexact) ADMM and
        Bregman iterations to converge (their errors accumulate in ``b`` and ``e``)."""
        cfg = self.config
        if cfg.cg_rtol_factor == 0:
            return cfg.cg_rtol
        rule = cfg.cg_rtol_max if not math.isfinite(self.admm_residual) else \
            min(cfg.cg_rtol_max, max(cfg.cg_rtol, cfg.cg_rtol_factor * self.admm_residual))
        self.inner_rtol = min(self.inner_rtol, rule)
        return self.inner_rtol

    def _inner_stuck(self, inner: SolveResult) -> bool:
        """An inner solve whose line search found no descent although its gradient is not
        negligible against the TV force ``||D^T beta b||`` (the Gauss-Newton model is bad
        there). At the fixed point the gradient is ~0 and this is no failure."""
        return inner.iterations == 0 and inner.stop_reason == StopReason.line_search and \
            inner.history[0].extra.get("gradient_norm", math.inf) > self.config.stage_tol * max(
                self.beta * float(torch.linalg.vector_norm(self.diff.rmatvec(self.b))), 1e-300)

    def _shrink(self, Dtheta: Tensor) -> Tensor:
        """The d-step: proximal map of ``TV / beta`` at ``D theta + c + b``."""
        return self.tv.shrink(Dtheta + self.b, 1.0 / self.beta)

    def _bregman_update(self, Dtheta: Tensor, d: Tensor) -> Tensor:
        return self.b + Dtheta - d

    def _reject(self, cg_its: int, damping: float, inner_iterations: int) -> IterationRecord:
        """Keep ``theta``, ``d``, ``b`` exactly; stiffen the splitting (keeping ``beta b``),
        which conditions the inner problem better."""
        self.rejections += 1
        self.admm_residual = 0.0         # the retry solves its inner problem tightly
        self.model.restore(self.lin)
        self._rescale_beta(2.0 * self.beta)
        self.spectral = None
        self.pending = "rejected"
        return self._record(0.0, cg_its, damping, False, dual_residual=math.nan,
                            inner_iterations=inner_iterations)

    def _restore_accepted(self) -> IterationRecord:
        accepted = self.search.accepted
        assert accepted is not None
        step_norm = float(torch.linalg.vector_norm(accepted["theta"] - self._theta))
        if accepted.get("lin") is not None:
            self.model.restore(accepted["lin"])
        self.lin = accepted.get("lin")
        for key in _SNAPSHOT:
            setattr(self, key if key != "theta" else "_theta", accepted[key])
        self.search.restore_pending = False
        self.pending = "restored"
        return self._record(step_norm, 0, math.nan, True, dual_residual=math.nan,
                            inner_iterations=0, restored=1.0)

    # -- records ---------------------------------------------------------------------------
    def _objective(self) -> tuple[float, float]:
        tv_value = self.tv.value(self.Dtheta)
        return tv_value + 0.5 * self.mu * self.norm ** 2, tv_value

    def _record(self, step_norm: float, cg_iterations: int, damping: float, accepted: bool,
                **extra: float) -> IterationRecord:
        objective, tv_value = self._objective()
        return self.record(self._theta, objective, self.norm, step_norm, cg_iterations, damping,
                           accepted, tv=tv_value,
                           split_residual=float(torch.linalg.vector_norm(self.Dtheta - self.d)),
                           mu=self.mu, beta=self.beta, stage=float(self.stage), **extra,
                           **({"dense_jacobian": 1.0} if self.dense else {}))

    # -- state -----------------------------------------------------------------------------
    def _get_state(self) -> dict[str, Any]:
        last = None if self.last is None else {k: clone(v) for k, v in self.last.items()}
        search = self.search
        accepted = None if search.accepted is None else \
            {k: clone(search.accepted[k]) for k in _SNAPSHOT}
        return {"norm": self.norm, "Dtheta": clone(self.Dtheta), "d": clone(self.d),
                "b": clone(self.b), "mu": self.mu, "beta": self.beta, "stage": self.stage,
                "stage_iteration": self.stage_iteration, "best": self.best,
                "spectral": None if self.spectral is None else [clone(t) for t in self.spectral],
                "objectives": list(self.objectives), "misfits": list(self.misfits),
                "rejections": self.rejections, "direction": search.direction,
                "accepted": accepted, "pending": self.pending, "last": last,
                "restore_pending": search.restore_pending,
                "restore_reason": search.restore_reason.value,
                "admm_residual": self.admm_residual,
                "admm_window": list(self.admm_window),
                "e": clone(self.e), "norm0": self.norm0, "inner_rtol": self.inner_rtol}

    def _set_state(self, state: dict[str, Any]) -> None:
        self._theta = state["theta"].detach().clone()
        self.norm = float(state["norm"])
        self.Dtheta, self.d, self.b = (clone(state[k]) for k in ("Dtheta", "d", "b"))
        self.mu, self.beta = float(state["mu"]), float(state["beta"])
        self.stage, self.stage_iteration = int(state["stage"]), int(state["stage_iteration"])
        self.best = float(state["best"])
        spectral = state["spectral"]
        self.spectral = None if spectral is None else (clone(spectral[0]), clone(spectral[1]))
        self.objectives = [float(x) for x in state["objectives"]]
        self.misfits = [float(x) for x in state["misfits"]]
        self.rejections = int(state["rejections"])
        self.search = search = StageSearch()
        search.direction = state["direction"]
        accepted = state["accepted"]
        search.accepted = None if accepted is None else \
            {**{k: clone(v) for k, v in accepted.items()}, "lin": None}
        self.pending = state["pending"]
        last = state["last"]
        self.last = None if last is None else {k: clone(v) for k, v in last.items()}
        search.restore_pending = bool(state["restore_pending"])
        search.restore_reason = StopReason(state.get("restore_reason", "discrepancy"))
        self.admm_residual = float(state.get("admm_residual", math.inf))
        self.admm_window = [float(x) for x in state.get("admm_window", [])]
        self.e = clone(state["e"])
        self.inner_rtol = float(state["inner_rtol"])
        self.norm0 = float(state["norm0"])

    def resume(self) -> None:
        self._setup(self._theta)
        self.lin = self.model.linearize(self._theta)


def split_bregman(residual: ResidualFunction, theta0: Tensor,
                  config: SplitBregmanConfig | None = None, callbacks: Iterable[Callback] = (),
                  *, D: Tensor | None = None, groups: Tensor | None = None,
                  offset: Tensor | None = None, penalty: GroupTV | None = None) -> SolveResult:
    """``SplitBregman(config, D=D, groups=groups, offset=offset, penalty=penalty)
    .solve(residual, theta0, callbacks)``: minimise ``TV(theta) + mu/2 ||r(theta)||^2``.

    ``D`` (keyword, required) is ``parameterization.difference_operator()``; records carry
    ``tv``, ``split_residual``, ``dual_residual``, ``inner_iterations``, ``mu``, ``beta``
    and ``stage``.
    """
    if isinstance(config, Tensor):
        raise TypeError("split_bregman takes the difference operator as a keyword (the call of "
                        "every solver is solve(residual, theta0, config, callbacks)): "
                        "split_bregman(residual, theta0, config, callbacks, D=D)")
    return SplitBregman(config, D=D, groups=groups, offset=offset,
                        penalty=penalty).solve(residual, theta0, callbacks)


__all__ = ["SplitBregman", "split_bregman"]
