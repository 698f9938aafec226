r"""Total-variation regularisation by split Bregman for non-linear forward models.

Minimises ``Phi_mu(theta) = TV(theta) + mu/2 ||r(theta)||^2`` with
``TV(theta) = sum_g ||(D theta + c)_g||_2``: ``r`` the residual of any problem (the solver
sees only ``r``, ``J v`` and ``J^T w``), ``D`` the parameterisation's sparse difference
operator (handed over, never built here), ``g`` the groups of rows of ``D`` (each row its
own group: anisotropic TV; ``groups`` from ``parameterization.difference_groups()`` with
``isotropic=true``: isotropic TV), ``c`` an optional constant ``offset``.

One outer iteration (split Bregman = scaled ADMM on ``d = D theta + c``)::

    theta <- argmin  mu/2 ||r(theta)||^2 + beta/2 ||D theta + c - d + b||^2   (inner solve)
    d     <- shrink(D theta + c + b, 1/beta)                                   (per group)
    b     <- b + D theta + c - d                                               (Bregman update)

* The inner solve is ``inner_max_iter`` Gauss-Newton (or Levenberg-Marquardt) steps on
  the stacked residual ``[sqrt(mu) r; sqrt(beta) (D theta + c - d + b)]``
  (:mod:`.stacked`); CGLS stops on the relative normal residual
  ``clip(cg_rtol_factor * max(primal_rel, dual_rel), cg_rtol, cg_rtol_max)`` (never rising
  within a stage). Without a noise level (and ``mu`` not set) the data are added back
  (``data_bregman``: ``mu/2 ||r - e||^2``, ``e <- e - r`` after every outer iteration),
  so the fixed point fits the data at a moderate ``mu``. The model
  residual is wrapped in :class:`~.stacked.CachedResidual`, so every distinct parameter
  vector is simulated (hence factorised) once.
* Dense Jacobian (``dense_jacobian_max_params``, as for Gauss-Newton): when the model
  residual provides ``jacobian`` and ``n`` is small, the inner solver runs on the dense
  stacked ``[sqrt(mu) J; sqrt(beta) D]`` (``J`` made once per accepted point, the
  products are matrix products) and the scale estimates at ``theta0`` use ``J`` too;
  records carry ``dense_jacobian = 1.0``.
* Weights: without a noise level (or ``continuation=false``) ``mu`` is fixed
  (``mu_rel / ||J(theta0)||_2^2`` unless set). With a noise level ``delta``: stages
  ``mu_k = mu_0 growth^k``, each run to its fixed point and warm-started from the
  previous one; the first stage whose fixed point has ``||r|| <= tau delta`` is the
  answer (if the first stage already fits, the search walks towards stronger TV and
  returns the strongest stage that still fits). A stage that lowers the misfit of the
  one before by less than ``delta / sqrt(2m)`` (the spread of the noise's own norm about
  ``delta`` over ``m`` data) ends the search too: the data cannot tell the two apart, so
  the earlier, stronger-TV stage is returned (stop reason ``plateau``). ``beta`` starts at
  ``beta_rel mu ||J||_2^2 / ||D||_2^2`` and is adapted every second iteration (spectral
  estimate, else residual balancing), keeping ``beta b``; in a data-Bregman run it also
  doubles when the ADMM residual has not decreased over ``stall_window`` iterations.
* Safeguard: an outer iteration whose objective is not finite, exceeds
  ``divergence_factor`` times the best of its stage, or whose inner solve found no
  descent, is rejected: ``theta``, ``d``, ``b`` stay exactly, ``beta`` doubles (``b``
  halves). ``max_rejections`` in a row stop the run (``stalled``).
* A stage is at its fixed point when the relative ADMM primal residual is below
  ``stage_tol`` and the relative dual residual is too, or the objective changed by less
  than ``stage_tol^2`` over the last 10 iterations (``bregman_tol`` in place of
  ``stage_tol`` for a data-Bregman run, whose fixed point is the answer). A stage
  clearly above the
  discrepancy level (misfit above ``tau delta`` by more than ``above_factor`` times its
  change over 10 iterations) ends early.

The reasons for these choices, the weights of other libraries (skimage) and measured
figures: ``docs/solvers/split_bregman.md``.

Records (one per outer iteration; 0 is ``theta0``): ``objective`` = ``Phi_mu`` of the
current stage, ``misfit`` = ``||r||``, ``cg_iterations`` of the inner solve, ``damping``
(inner LM; ``nan`` for GN), ``accepted`` (``False``: rejected) and ``extra``: ``tv``,
``split_residual`` (``||d - D theta - c||``), ``mu``, ``beta``, ``stage``,
``dual_residual``, ``inner_iterations`` (and ``restored = 1`` on the record that returns
to an earlier stage).

Stop reasons: ``discrepancy`` (the selected stage fits), ``plateau`` (a weaker-TV stage
fitted no closer than the noise's spread: the stage before it), ``tolerance`` (fixed weight:
fixed point), ``max_iter`` (outer iterations, the stage budget of a fixed-weight run, or
stages exhausted), ``stalled``, ``interrupted``.

Carried state (:meth:`SplitBregman.state_dict`): ``theta``, ``D theta + c``, ``d``,
``b``, ``mu``, ``beta``, the stage and its iteration count, the spectral pair, the
objective and misfit windows, the best objective, the rejection count, the search
direction, the accepted earlier stage, and what the last record left to decide (stage
end test and ``beta`` update run after a record, so they run first on resume).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Iterable, Optional

import torch
from torch import Tensor

from ..linalg import cgls
from ..records import Callback, IterationRecord, SolveResult, StopReason
from ..residual import ResidualFunction
from .base import Solver, SolverConfig, Stop, clone, require
from .gauss_newton import GaussNewton, GaussNewtonConfig
from .least_squares import wants_dense_jacobian
from .levenberg_marquardt import LevenbergMarquardt, LevenbergMarquardtConfig
from .stacked import CachedResidual, LinearResidual, ShiftedResidual, StackedResidual
from .total_variation import GroupTV, check_difference_operator

INNER_SOLVERS = ("gauss_newton", "levenberg_marquardt")


@dataclasses.dataclass
class SplitBregmanConfig(SolverConfig):
    """Settings of ``solver=split_bregman`` (see the module docstring for the defaults)."""

    name: str = "split_bregman"
    isotropic: bool = False         # group norm over the groups of D's rows (needs groups)
    mu: Optional[float] = None      # data weight (fixed, or first stage); None: scale-aware
    mu_rel: float = 1e6             # fixed-weight default mu = mu_rel / ||J(theta0)||_2^2
    mu_start_rel: float = 1.0       # first stage: mu_0 = mu_start_rel / (sigma ||J(theta0)||_F)
    beta: Optional[float] = None    # splitting weight at the start; None: scale-aware
    beta_rel: float = 1.0           # beta_0 = beta_rel * mu_0 * ||J||_2^2 / ||D||_2^2
    adapt_beta: bool = True         # spectral penalty update (after Xu et al. 2017) every 2 iters
    continuation: bool = True       # noise level known: discrepancy-driven stages in mu
    # Without a noise level (clean data): Bregman on the data as well ("adding back the
    # residual", Goldstein and Osher 2009, sec. 2.2): the data term is mu/2 ||r - e||^2
    # with e <- e - r after every outer iteration, so the fixed point fits the data
    # exactly (min TV subject to r = 0) whatever mu, and mu can be moderate (better
    # conditioned inner solves). auto: on when the run has no noise level and mu is not
    # set; off: a fixed mu/2 ||r||^2 (the answer is then biased by 1/mu).
    data_bregman: str = "auto"      # auto | on | off
    mu_rel_bregman: float = 1e4     # data Bregman: mu = mu_rel_bregman / ||J(theta0)||_2^2
                                    # (1e3 reached 1e-2 as fast on sparse poisson2d but then
                                    # oscillated for hundreds of iterations; docs/solvers)
    tau: float = 1.0                # a stage is accepted when ||r|| <= tau * delta
    growth: float = 4.0             # mu_{k+1} = growth * mu_k
    max_stages: int = 20
    max_iter: int = 2000            # outer (split Bregman) iterations over all stages
    stage_max_iter: int = 400       # outer iterations per stage
    stage_tol: float = 1e-3         # relative ADMM primal and dual residual of a fixed point
    bregman_tol: float = 1e-4       # the same for a data-Bregman run (clean data: its fixed
                                    # point is the answer; poisson2d dense clean: 6.4e-5,
                                    # 2.9e-5, 1.3e-5 with 5e-4, 2e-4, 1e-4 in 109, 112, 115
                                    # iterations)
    inner_solver: str = "gauss_newton"   # gauss_newton | levenberg_marquardt
    inner_max_iter: int = 1         # inner steps per outer iteration (Goldstein-Osher: one)
    cg_max_iter: int = 200          # CGLS iterations per inner step
    # Inner CGLS stops at the relative normal-equation residual
    #   cg_rtol_k = clip(cg_rtol_factor * max(primal_rel, dual_rel), cg_rtol, cg_rtol_max)
    # (the ADMM residuals of the previous outer iteration; cg_rtol_max at a stage's start):
    # loose while the splitting is far from its fixed point, tight near it.
    # cg_rtol_factor = 0: the fixed tolerance cg_rtol.
    cg_rtol: float = 1e-2
    cg_rtol_max: float = 0.3
    cg_rtol_factor: float = 10.0
    power_iterations: int = 20      # for ||J(theta0)||_2, ||J(theta0)||_F and ||D||_2
    above_factor: float = 3.0       # a stage ends early when its misfit is above the
                                    # discrepancy level by more than this times its change
                                    # over the last 10 iterations (it will not get there)
    stall_window: int = 10          # data Bregman: beta doubles when the ADMM residual has
                                    # not decreased over this many accepted iterations
                                    # (0: never)
    divergence_factor: float = 10.0  # reject an outer step whose objective grows this much
    max_rejections: int = 8
    max_step: float = 0.0           # inner steps: largest change of one parameter (0: no limit)
    dense_jacobian_max_params: int = 1000   # dense J in the inner solve when the residual
                                            # provides one and n <= this (0: never)

    def check(self) -> None:
        require(self.max_step >= 0, f"solver.max_step must be >= 0 (0: no limit), got "
                f"{self.max_step}")
        require(self.mu is None or self.mu > 0,
                f"solver.mu must be > 0 (the weight of mu/2 ||r||^2), got {self.mu}")
        require(self.beta is None or self.beta > 0,
                f"solver.beta must be > 0 (the split Bregman penalty), got {self.beta}")
        for key in ("mu_rel", "mu_start_rel", "beta_rel"):
            value = getattr(self, key)
            require(value > 0, f"solver.{key} must be > 0, got {value}")
        require(self.tau > 0, f"solver.tau must be > 0 (discrepancy ||r|| <= tau delta), got "
                f"{self.tau}")
        require(self.growth > 1, f"solver.growth must be > 1 (mu grows between stages), got "
                f"{self.growth}")
        require(self.max_stages >= 1, f"solver.max_stages must be >= 1, got {self.max_stages}")
        require(self.stage_max_iter >= 1,
                f"solver.stage_max_iter must be >= 1, got {self.stage_max_iter}")
        require(0 < self.stage_tol < 1, f"solver.stage_tol must be in (0, 1), got "
                f"{self.stage_tol}")
        require(0 < self.bregman_tol < 1, f"solver.bregman_tol must be in (0, 1), got "
                f"{self.bregman_tol}")
        require(self.stall_window >= 0,
                f"solver.stall_window must be >= 0 (0: never), got {self.stall_window}")
        require(self.data_bregman in ("auto", "on", "off"),
                f"solver.data_bregman={self.data_bregman!r}; choose auto, on or off")
        require(self.mu_rel_bregman > 0,
                f"solver.mu_rel_bregman must be > 0, got {self.mu_rel_bregman}")
        require(self.inner_solver in INNER_SOLVERS,
                f"solver.inner_solver={self.inner_solver!r}; choose one of {INNER_SOLVERS}")
        require(self.inner_max_iter >= 1,
                f"solver.inner_max_iter must be >= 1, got {self.inner_max_iter}")
        require(self.cg_max_iter >= 1, f"solver.cg_max_iter must be >= 1, got {self.cg_max_iter}")
        require(0 < self.cg_rtol < 1, f"solver.cg_rtol must be in (0, 1), got {self.cg_rtol}")
        require(self.cg_rtol <= self.cg_rtol_max < 1,
                f"need solver.cg_rtol <= solver.cg_rtol_max < 1, got {self.cg_rtol}, "
                f"{self.cg_rtol_max}")
        require(self.cg_rtol_factor >= 0,
                f"solver.cg_rtol_factor must be >= 0 (0: fixed cg_rtol), got "
                f"{self.cg_rtol_factor}")
        require(self.power_iterations >= 1,
                f"solver.power_iterations must be >= 1, got {self.power_iterations}")
        require(self.above_factor > 0,
                f"solver.above_factor must be > 0, got {self.above_factor}")
        require(self.divergence_factor > 1,
                f"solver.divergence_factor must be > 1, got {self.divergence_factor}")
        require(self.max_rejections >= 0,
                f"solver.max_rejections must be >= 0, got {self.max_rejections}")
        require(self.dense_jacobian_max_params >= 0,
                f"solver.dense_jacobian_max_params must be >= 0 (0 disables the dense "
                f"Jacobian), got {self.dense_jacobian_max_params}")


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
    ``rejections``), the continuation (``direction``, ``accepted``) and what the last
    record left to decide (``pending``, ``last``, ``restore_pending``).
    """

    config_class = SplitBregmanConfig
    config: SplitBregmanConfig

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
        self.data_bregman = cfg.data_bregman == "on" or (
            cfg.data_bregman == "auto" and not self.staged and cfg.mu is None)
        # The inner problem has a non-zero minimum: its CGLS stops on the normal-equation
        # residual (REGINN's ||J d + r|| <= eta ||r|| could never be met there).
        dense = cfg.dense_jacobian_max_params
        self.dense = wants_dense_jacobian(self.residual, like.numel(), dense)
        if cfg.inner_solver == "gauss_newton":
            self.inner = GaussNewton(GaussNewtonConfig(
                max_iter=cfg.inner_max_iter, cg_max_iter=cfg.cg_max_iter, eta_min=1e-14,
                eta_max=1e-14, cg_rtol=cfg.cg_rtol, dense_jacobian_max_params=dense,
                preconditioner="none",
                max_step=cfg.max_step))
        else:
            self.inner = LevenbergMarquardt(LevenbergMarquardtConfig(
                max_iter=cfg.inner_max_iter, cg_max_iter=cfg.cg_max_iter, cg_rtol=cfg.cg_rtol,
                dense_jacobian_max_params=dense, max_step=cfg.max_step))

    def start(self, theta0: Tensor) -> IterationRecord:
        theta = theta0.detach().clone()
        self._setup(theta)
        self.lin = self.model.linearize(theta)
        if not math.isfinite(self.lin.norm):
            raise ValueError("the residual at theta0 is not finite")
        if self.dense:
            self.lin.use_dense()      # the scale estimates below are then matrix products
        self.mu, self.beta = self._initial_weights(theta)
        self._theta, self.norm, self.stage = theta, self.lin.norm, 0
        self.norm0 = self.lin.norm
        self.Dtheta = self.diff.matvec(theta) + self.c
        self.d, self.b = self.Dtheta.clone(), torch.zeros_like(self.Dtheta)
        self.e = torch.zeros_like(self.lin.r)     # data Bregman variable (stays 0 when off)
        self.direction: str | None = None        # continuation: 'weaker' | 'stronger'
        # the stage to return to: the strongest-TV stage that fits (direction 'stronger'),
        # the one before the current stage (direction 'weaker': a plateau returns to it)
        self.accepted: dict[str, Any] | None = None
        self.restore_pending = False
        self.restore_reason = StopReason.discrepancy   # why a restored stage is the answer
        self._begin_stage()
        return self._record(0.0, 0, math.nan, True, dual_residual=math.nan, inner_iterations=0)

    def _initial_weights(self, theta: Tensor) -> tuple[float, float]:
        """Scale-aware ``mu`` and ``beta``: Jacobian products at ``theta0``, no factorisation."""
        cfg, lin = self.config, self.lin
        self._gradient0: Tensor | None = None
        self._j_norm_sq0: float | None = None
        if cfg.mu is not None:
            mu = float(cfg.mu)
        elif self.staged:
            noise = self.residual.noise_level
            sigma = noise / math.sqrt(max(lin.r.numel(), 1))
            j_frob = math.sqrt(_frobenius_norm_sq(lin.jvp, theta.numel(), theta,
                                                  cfg.power_iterations))
            if not j_frob > 0:
                self._jacobian_norm_sq()   # raises: the Jacobian is zero
            mu = cfg.mu_start_rel / (sigma * j_frob)
            critical = _critical_mu(self.diff, self.tv, self._gradient_at_start())
            if critical is not None:
                mu = max(mu, critical)   # weaker than critical: the field would stay constant
        else:
            mu = (cfg.mu_rel_bregman if self.data_bregman else cfg.mu_rel) \
                / self._jacobian_norm_sq()
        if cfg.beta is not None:
            beta = float(cfg.beta)
        else:
            d_norm_sq = _power_norm_sq(self.diff.matvec, self.diff.rmatvec,
                                       torch.cos(torch.arange(theta.numel(), dtype=theta.dtype,
                                                              device=theta.device)) + 2.0,
                                       cfg.power_iterations)
            beta = cfg.beta_rel * mu * self._jacobian_norm_sq() / max(d_norm_sq, 1e-300)
        return mu, beta

    def _gradient_at_start(self) -> Tensor:
        if self._gradient0 is None:
            self._gradient0 = self.lin.vjp(self.lin.r)
        return self._gradient0

    def _jacobian_norm_sq(self) -> float:
        """``||J(theta0)||_2^2`` by power iteration (once)."""
        if self._j_norm_sq0 is None:
            g = self._gradient_at_start()
            start = g if float(torch.linalg.vector_norm(g)) > 0 else torch.ones_like(g)
            self._j_norm_sq0 = _power_norm_sq(self.lin.jvp, self.lin.vjp, start,
                                              self.config.power_iterations)
            if not self._j_norm_sq0 > 0:
                raise ValueError("the Jacobian at theta0 is zero (the data do not depend on "
                                 "theta): no scale-aware weight exists; set solver.mu and "
                                 "solver.beta")
        return self._j_norm_sq0

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
            return Stop(True, self.restore_reason)
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
        return not self.restore_pending and self.iteration >= self.config.max_iter

    def _after_accepted(self) -> str | None:
        """Fixed-point and 'above the level' tests, then the ``beta`` update."""
        cfg, last = self.config, self.last
        assert last is not None
        new_obj = last["objective"]
        self.objectives.append(new_obj)
        tol = cfg.bregman_tol if self.data_bregman else cfg.stage_tol
        stagnant = len(self.objectives) > 10 and \
            abs(self.objectives[-11] - new_obj) <= tol ** 2 * abs(new_obj)
        fits = not self.data_bregman or self.norm <= tol * self.norm0
        if fits and last["primal_rel"] <= tol and (last["dual_rel"] <= tol or stagnant):
            return "converged"
        if last["primal"] == 0.0 and last["step_norm"] == 0.0:
            return "converged"           # nothing moves (e.g. a constant field)
        self.misfits.append(self.norm)
        if self.staged and len(self.misfits) > 10 and self.misfits[-1] - self.level > \
                cfg.above_factor * abs(self.misfits[-1] - self.misfits[-11]):
            return "above"
        if cfg.adapt_beta and (self.spectral is None or last["stage_iteration"] % 2 == 1):
            self._adapt_beta(last["lam_hat"], last["primal_rel"], last["dual_rel"])
        if cfg.adapt_beta and self.data_bregman:
            self._stall_rule(max(last["primal_rel"], last["dual_rel"]))
        return None

    def _stall_rule(self, admm_residual: float) -> None:
        """Double ``beta`` (keeping ``beta b``) when the ADMM residual has not decreased over
        ``stall_window`` accepted iterations.

        ADMM on a non-convex data term converges for a large enough penalty (Wang, Yin and
        Zeng 2019); with inexact inner solves and data Bregman, a too small ``beta`` that
        neither the spectral estimate (uncorrelated changes) nor residual balancing (both
        residuals within 10x) moves lets the iteration drift for hundreds of iterations
        (poisson2d dense clean: ``docs/solvers/split_bregman.md``). Runs with a noise
        level end their stages by the discrepancy tests instead and are left alone."""
        window = self.config.stall_window
        if window <= 0:
            return
        self.admm_window.append(admm_residual)
        if len(self.admm_window) > window and self.admm_window[-1] >= self.admm_window[-1 - window]:
            self._rescale_beta(2.0 * self.beta)
            self.admm_window = []

    def _rescale_beta(self, beta_new: float) -> None:
        """Change the splitting weight keeping the multiplier ``beta b`` (scaled ADMM)."""
        self.b = self.b * (self.beta / beta_new)
        self.beta = beta_new

    def _adapt_beta(self, lam_hat: Tensor, primal_rel: float, dual_rel: float) -> None:
        """Spectral (Barzilai-Borwein) estimate, else residual balancing; keeps ``beta b``."""
        beta_new = None
        if self.spectral is not None:
            beta_new = _spectral_beta(self.beta, self.Dtheta - self.spectral[0],
                                      -(lam_hat - self.spectral[1]))
            if beta_new is None and max(primal_rel, dual_rel) > 10.0 * min(primal_rel,
                                                                           dual_rel):
                # No reliable curvature: residual balancing (Boyd et al. 2011, 3.4.1, on
                # relative residuals as Wohlberg 2017).
                beta_new = self.beta * (2.0 if primal_rel > dual_rel else 0.5)
        if beta_new is not None and beta_new != self.beta:
            self._rescale_beta(beta_new)
        self.spectral = (self.Dtheta, lam_hat)

    def _end_stage(self, status: str) -> Stop | None:
        """A stage ended (``converged``, ``above``, ``budget`` or ``stalled``): stop, start
        the next stage, or schedule the return to the accepted earlier one."""
        cfg = self.config
        if not self.staged:
            if status == "converged":
                return Stop(True, StopReason.tolerance)
            return Stop(False, StopReason.stalled if status == "stalled" else StopReason.max_iter)
        if status == "stalled":
            return Stop(False, StopReason.stalled)
        ok = self.norm <= self.level
        if self.direction is None:
            self.direction = "weaker" if not ok else "stronger"
        went_too_far = False
        if self.direction == "weaker":
            if ok:
                return Stop(True, StopReason.discrepancy)
            if self.accepted is not None and self.accepted["norm"] - self.norm < self.spread:
                # weaker TV fitted the data no closer than the noise's spread: the stage
                # before is the answer
                self.restore_pending, self.restore_reason = True, StopReason.plateau
                return None
            # the stage to return to on a plateau (its linearisation is not kept: memory)
            self.accepted = {**self._snapshot(), "lin": None}
            mu_next = self.mu * cfg.growth
        elif not ok:
            went_too_far = True
        else:
            self.accepted = self._snapshot()
            mu_next = self.mu / cfg.growth
        if not went_too_far and self.stage + 1 < cfg.max_stages:
            self.mu, self.stage = mu_next, self.stage + 1
            self._begin_stage()
            return None
        if self.direction == "stronger" and self.accepted is not None:
            if went_too_far:
                # The last stage fitted the data worse than the noise: back to the one before.
                self.restore_pending = True
                return None
            return Stop(True, StopReason.discrepancy)
        return Stop(False, StopReason.max_iter)

    def _snapshot(self) -> dict[str, Any]:
        snap = {key: getattr(self, key if key != "theta" else "_theta") for key in _SNAPSHOT}
        snap["lin"] = self.lin             # kept alive in memory (not saved)
        return snap

    # -- one outer iteration ---------------------------------------------------------------
    def step(self) -> IterationRecord | Stop:
        if self.restore_pending:
            return self._restore_accepted()
        self.stage_iteration += 1
        inner = self._inner_solve()
        cg_its = sum(r.cg_iterations for r in inner.history[1:])
        damping = (inner.history[-1].damping if self.config.inner_solver != "gauss_newton"
                   else math.nan)
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
        accepted = self.accepted
        assert accepted is not None
        step_norm = float(torch.linalg.vector_norm(accepted["theta"] - self._theta))
        if accepted.get("lin") is not None:
            self.model.restore(accepted["lin"])
        self.lin = accepted.get("lin")
        for key in _SNAPSHOT:
            setattr(self, key if key != "theta" else "_theta", accepted[key])
        self.restore_pending = False
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
        accepted = None if self.accepted is None else \
            {k: clone(self.accepted[k]) for k in _SNAPSHOT}
        return {"norm": self.norm, "Dtheta": clone(self.Dtheta), "d": clone(self.d),
                "b": clone(self.b), "mu": self.mu, "beta": self.beta, "stage": self.stage,
                "stage_iteration": self.stage_iteration, "best": self.best,
                "spectral": None if self.spectral is None else [clone(t) for t in self.spectral],
                "objectives": list(self.objectives), "misfits": list(self.misfits),
                "rejections": self.rejections, "direction": self.direction,
                "accepted": accepted, "pending": self.pending, "last": last,
                "restore_pending": self.restore_pending, "restore_reason": self.restore_reason.value,
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
        self.direction = state["direction"]
        accepted = state["accepted"]
        self.accepted = None if accepted is None else \
            {**{k: clone(v) for k, v in accepted.items()}, "lin": None}
        self.pending = state["pending"]
        last = state["last"]
        self.last = None if last is None else {k: clone(v) for k, v in last.items()}
        self.restore_pending = bool(state["restore_pending"])
        self.restore_reason = StopReason(state.get("restore_reason", "discrepancy"))
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


# -- scale estimates and the spectral penalty ------------------------------------------------
def _power_norm_sq(matvec, rmatvec, v0: Tensor, iterations: int) -> float:
    """Largest eigenvalue of ``A^T A`` by power iteration (products only)."""
    v = v0 / torch.linalg.vector_norm(v0)
    estimate = 0.0
    for _ in range(iterations):
        w = rmatvec(matvec(v))
        norm = float(torch.linalg.vector_norm(w))
        if not math.isfinite(norm) or norm == 0.0:
            return estimate
        estimate = norm
        v = w / norm
    return estimate


def _spectral_beta(beta: float, dH: Tensor, dlam_hat: Tensor, correlation: float = 0.2,
                   max_factor: float = 10.0) -> float | None:
    """Spectral (Barzilai-Borwein) penalty from the data side of adaptive ADMM.

    Xu, Figueiredo and Goldstein (AISTATS 2017, eqs. 23-26) estimate the curvature of
    the theta-subproblem along ``D`` from the change of ``D theta`` (``dH``) and of the
    intermediate multiplier (``dlam_hat``, sign-adjusted so that their inner product is
    positive for a convex data term), with the hybrid steepest-descent/minimum-gradient
    rule, and trust it when the two changes are correlated (> ``correlation``). The paper
    takes the geometric mean with the same estimate for the TV side; that one is left
    out here: TV is piecewise linear (anisotropic: curvature 0 or infinite), and for
    isotropic groups near zero it is unbounded; in tests it drove beta to ~100 mu for
    denoising (best: ~2 mu), where split Bregman crawls. One update changes beta by at most
    ``max_factor``; ``None`` when the estimate is not reliable.
    """
    xy = float(torch.dot(dH, dlam_hat))
    xx = float(torch.dot(dH, dH))
    yy = float(torch.dot(dlam_hat, dlam_hat))
    if xy <= 0 or xx == 0 or yy == 0 or xy / math.sqrt(xx * yy) <= correlation:
        return None
    steepest = yy / xy
    minimum_gradient = xy / xx
    new = minimum_gradient if 2 * minimum_gradient > steepest \
        else steepest - minimum_gradient / 2
    return float(min(max(new, beta / max_factor), beta * max_factor))


def _frobenius_norm_sq(matvec, n: int, like: Tensor, probes: int) -> float:
    """Hutchinson estimate of ``||A||_F^2 = E ||A v||^2`` (Rademacher ``v``, seeded)."""
    generator = torch.Generator().manual_seed(0)
    total = 0.0
    for _ in range(probes):
        v = (torch.randint(0, 2, (n,), generator=generator) * 2 - 1).to(like)
        total += float(torch.linalg.vector_norm(matvec(v))) ** 2
    return total / probes


def _critical_mu(diff: LinearResidual, tv: GroupTV, gradient: Tensor) -> float | None:
    """Weight below which TV keeps the field constant: ``1 / ||w||_*``, ``D^T w = J^T r``.

    ``w`` is the minimum-norm least-squares solution (CGLS on ``D^T`` from zero); the
    component of the gradient along the null space of ``D`` (the mean level) is not
    regularised by TV and drops out. Returns ``None`` when the gradient has no part TV
    acts on.
    """
    n_edges = diff.size
    # a floor on mu needs a few digits: 1e-3 gives ||w||_* to 1e-4 relative on poisson2d
    # N = 64 in 150 CGLS iterations where 1e-8 took 250 (15 against 26 ms)
    result = cgls(diff.rmatvec, diff.matvec, gradient, n_edges, residual_target=0.0,
                  max_iter=max(50, min(10 * n_edges, 5000)), normal_rtol=1e-3)
    dual = tv.dual_norm(result.x)
    if not (dual > 0 and math.isfinite(dual)):
        return None
    return 1.0 / dual



__all__ = ["INNER_SOLVERS", "SplitBregman", "SplitBregmanConfig", "split_bregman"]
