"""Settings of split Bregman TV: the Hydra schema ``solver=split_bregman`` and its choices.

Every default is written here once. The rules the settings steer: the outer iteration
in :mod:`.solver`, the weights ``mu`` and ``beta`` in
:mod:`.weights`, the stages in ``mu`` in :mod:`.stages`.
Measured effects of the defaults: ``docs/notes/split_bregman.md``.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

from ...settings import Choice
from ..base import Need, Needs, SolverConfig, require

#: the most products a norm estimate may take (``power_iterations``)
MAX_POWER_ITERATIONS = 1000


class InnerSolver(Choice):
    """The solver of the penalised least-squares problem of one outer iteration."""

    gauss_newton = "gauss_newton"
    levenberg_marquardt = "levenberg_marquardt"


class DataBregman(Choice):
    """Bregman iteration on the data term too (``mu/2 ||r - e||^2``, ``e <- e - r``):
    ``auto`` (on when the run has no noise level and ``mu`` is not set), ``on``, ``off``."""

    auto = "auto"
    on = "on"
    off = "off"


@dataclasses.dataclass
class SplitBregmanConfig(SolverConfig):
    """Settings of ``solver=split_bregman`` (the rules they set: :mod:`.solver`,
    :mod:`.weights`, :mod:`.stages`)."""

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
    data_bregman: DataBregman = DataBregman.auto   # auto | on | off
    mu_rel_bregman: float = 1e4     # data Bregman: mu = mu_rel_bregman / ||J(theta0)||_2^2
    tau: float = 1.0                # a stage is accepted when ||r|| <= tau * delta
    growth: float = 4.0             # mu_{k+1} = growth * mu_k
    max_stages: int = 20
    max_iter: int = 2000            # outer (split Bregman) iterations over all stages
    stage_max_iter: int = 400       # outer iterations per stage
    stage_tol: float = 1e-3         # relative ADMM primal and dual residual of a fixed point
    bregman_tol: float = 1e-4       # the same for a data-Bregman run (clean data: its fixed
                                    # point is the answer)
    inner_solver: InnerSolver = InnerSolver.gauss_newton   # gauss_newton | levenberg_marquardt
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
        require(self.mu_rel_bregman > 0,
                f"solver.mu_rel_bregman must be > 0, got {self.mu_rel_bregman}")
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
        # each iteration is a product J^T J v (a simulation's worth of work on a large body);
        # the estimate converges geometrically, so thousands only cost: a bound, not a hang
        require(1 <= self.power_iterations <= MAX_POWER_ITERATIONS,
                f"solver.power_iterations must be in [1, {MAX_POWER_ITERATIONS}] (each is a "
                f"J^T J product; default 20), got {self.power_iterations}")
        require(self.above_factor > 0,
                f"solver.above_factor must be > 0, got {self.above_factor}")
        require(self.divergence_factor > 1,
                f"solver.divergence_factor must be > 1, got {self.divergence_factor}")
        require(self.max_rejections >= 0,
                f"solver.max_rejections must be >= 0, got {self.max_rejections}")
        require(self.dense_jacobian_max_params >= 0,
                f"solver.dense_jacobian_max_params must be >= 0 (0 disables the dense "
                f"Jacobian), got {self.dense_jacobian_max_params}")

    def needs(self) -> Needs:
        """``D`` always; its row groups with ``isotropic``."""
        return Needs(Need.required, difference_groups=bool(self.isotropic))


__all__ = ["DataBregman", "InnerSolver", "SplitBregmanConfig"]
