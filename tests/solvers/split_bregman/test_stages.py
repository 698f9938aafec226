"""Split Bregman's stages (torchfit.solvers.split_bregman.stages): the search towards
stronger TV, the plateau stop, and the stage rules on their own."""
from __future__ import annotations

import math

import torch

from torchfit.problems import Spring1D, Spring1DConfig
from torchfit.records import StopReason
from torchfit.solvers import SplitBregmanConfig, split_bregman
from torchfit.solvers.base import Stop
from torchfit.solvers.split_bregman.stages import (StageEnd, StageSearch, at_fixed_point,
                                                   fixed_weight_stop)

from helpers.solver_runs import underestimated_noise




def test_stronger_tv_is_searched_when_the_first_stage_already_fits_the_noise():
    problem = Spring1D(n=32, noise=1e-4)
    config = SplitBregmanConfig(mu=1e7, stage_tol=1e-2)
    result = split_bregman(problem.residual(), problem.theta0, config,
                           D=problem.parameterization.difference_operator())
    assert result.stop_reason == "discrepancy"
    stages = [int(r.extra["stage"]) for r in result.history]
    assert max(stages) >= 1
    mus = [r.extra["mu"] for r in result.history]
    assert min(mus) < 1e7                                   # went towards stronger TV
    assert result.history[-1].misfit <= config.tau * problem.noise_level




def test_a_stage_that_fits_no_closer_than_the_noise_spread_returns_the_one_before():
    """With a noise level 20 % too small the misfit never reaches ``tau delta``. The
    search used to walk on through weaker and weaker TV (stop ``max_iter`` at stage 19,
    or ``stalled``); now the first stage that lowers the misfit by less than
    ``delta / sqrt(2m)`` ends it, and the stage before it is the answer."""
    problem = Spring1D(Spring1DConfig(n=16, noise=1e-4))
    residual = underestimated_noise(problem)()
    config = SplitBregmanConfig(max_iter=600)
    result = split_bregman(residual, problem.theta0, config,
                           D=problem.parameterization.difference_operator())
    assert result.stop_reason == "plateau" and result.converged
    history = result.history
    last = history[-1]
    assert last.extra["restored"] == 1.0
    stage_end = {}                       # the last record of every stage before the return
    for record in history[:-1]:
        stage_end[int(record.extra["stage"])] = record
    plateau_stage = max(stage_end)
    answer = stage_end[plateau_stage - 1]
    assert int(last.extra["stage"]) == plateau_stage - 1
    assert torch.equal(last.theta, answer.theta) and last.misfit == answer.misfit
    spread = residual.noise_level / math.sqrt(2 * residual.data.numel())
    assert 0 <= answer.misfit - stage_end[plateau_stage].misfit < spread
    assert plateau_stage <= 4                 # a few stages, not the twenty of max_stages
    assert last.misfit > config.tau * residual.noise_level   # no stage met the level
    # the earlier stages did lower the misfit by more than the spread
    for k in range(1, plateau_stage):
        assert stage_end[k - 1].misfit - stage_end[k].misfit >= spread


# -- the rules on their own ----------------------------------------------------------------
def step(primal_rel=1e-4, dual_rel=1e-4, primal=1.0, step_norm=1.0):
    return {"primal_rel": primal_rel, "dual_rel": dual_rel, "primal": primal,
            "step_norm": step_norm}


def test_a_fixed_point_needs_both_admm_residuals_or_a_stagnant_objective():
    tol = 1e-3
    assert at_fixed_point([5.0], step(), tol, fits=True)
    assert not at_fixed_point([5.0], step(), tol, fits=False)          # data Bregman: misfit
    assert not at_fixed_point([5.0], step(dual_rel=1e-2), tol, fits=True)
    assert not at_fixed_point([5.0], step(primal_rel=1e-2), tol, fits=True)
    # the objective changed by at most tol^2 (relative) over the last 10 iterations
    flat = [5.0] * 10 + [5.0 * (1 + 0.9 * tol ** 2)]
    assert at_fixed_point(flat, step(dual_rel=1e-2), tol, fits=True)
    moving = [5.0] * 10 + [5.0 * (1 + 2 * tol ** 2)]
    assert not at_fixed_point(moving, step(dual_rel=1e-2), tol, fits=True)
    assert not at_fixed_point(flat[1:], step(dual_rel=1e-2), tol, fits=True)   # 10 only
    # nothing moves (a constant field): the fixed point whatever the residuals
    assert at_fixed_point([5.0], step(1.0, 1.0, primal=0.0, step_norm=0.0), tol, fits=False)


def test_without_stages_a_stage_end_is_the_run_end():
    assert fixed_weight_stop("converged") == (True, StopReason.tolerance)
    assert fixed_weight_stop("budget") == (False, StopReason.max_iter)
    assert fixed_weight_stop("stalled") == (False, StopReason.stalled)


def test_a_stage_far_above_the_level_is_out_of_reach():
    creeping = [2.0 - 1e-3 * k for k in range(11)]
    assert StageSearch.out_of_reach(creeping, level=1.0, above_factor=3.0)
    assert not StageSearch.out_of_reach(creeping[1:], level=1.0, above_factor=3.0)
    falling = [2.0 - 0.1 * k for k in range(11)]              # 1 above, changing by 1
    assert not StageSearch.out_of_reach(falling, level=0.5, above_factor=3.0)


def snapshot(norm):
    return lambda: {"norm": norm, "lin": object(), "mu": None}


def test_the_search_towards_weaker_tv_and_its_plateau():
    search = StageSearch()
    end = search.end_stage(2.0, 1.0, 0.1, 10.0, 0, 4.0, 20, snapshot(2.0))
    assert end == StageEnd(next_mu=40.0) and search.direction == "weaker"
    assert search.accepted["norm"] == 2.0 and search.accepted["lin"] is None
    end = search.end_stage(1.5, 1.0, 0.1, 40.0, 1, 4.0, 20, snapshot(1.5))
    assert end == StageEnd(next_mu=160.0) and search.accepted["norm"] == 1.5
    # lowered the misfit by less than the spread: back to the stage before
    end = search.end_stage(1.45, 1.0, 0.1, 160.0, 2, 4.0, 20, snapshot(1.45))
    assert end == StageEnd() and search.restore_pending
    assert search.restore_reason is StopReason.plateau and search.accepted["norm"] == 1.5
    fits = StageSearch()
    fits.direction = "weaker"
    assert fits.end_stage(0.9, 1.0, 0.1, 1.0, 3, 4.0, 20, snapshot(0.9)) == \
        StageEnd(Stop(True, StopReason.discrepancy))
    last = StageSearch()
    assert last.end_stage(2.0, 1.0, 0.1, 1.0, 19, 4.0, 20, snapshot(2.0)) == \
        StageEnd(Stop(False, StopReason.max_iter))               # no stage left


def test_the_search_towards_stronger_tv_returns_the_strongest_that_fits():
    search = StageSearch()
    end = search.end_stage(0.5, 1.0, 0.1, 16.0, 0, 4.0, 20, snapshot(0.5))
    assert end == StageEnd(next_mu=4.0) and search.direction == "stronger"
    assert search.accepted["lin"] is not None                 # kept: the return is likely
    end = search.end_stage(0.8, 1.0, 0.1, 4.0, 1, 4.0, 20, snapshot(0.8))
    assert end == StageEnd(next_mu=1.0) and search.accepted["norm"] == 0.8
    end = search.end_stage(1.2, 1.0, 0.1, 1.0, 2, 4.0, 20, snapshot(1.2))   # too far
    assert end == StageEnd() and search.restore_pending
    assert search.restore_reason is StopReason.discrepancy and search.accepted["norm"] == 0.8
    out_of_stages = StageSearch()
    out_of_stages.end_stage(0.5, 1.0, 0.1, 16.0, 0, 4.0, 2, snapshot(0.5))
    assert out_of_stages.end_stage(0.6, 1.0, 0.1, 4.0, 1, 4.0, 2, snapshot(0.6)) == \
        StageEnd(Stop(True, StopReason.discrepancy))
