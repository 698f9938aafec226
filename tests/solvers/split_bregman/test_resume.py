"""Split Bregman's exact resume: bit-identical continuation across stage changes, the
return to an accepted stage, rejected steps, inner Levenberg-Marquardt, isotropic TV."""
from __future__ import annotations

import pytest
import torch

from torchfit.problems import Spring1D, Spring1DConfig
from torchfit.solvers import SplitBregman, SplitBregmanConfig

from helpers.solver_resume import check_resume, fresh, roundtrip, run_with_snapshots
from helpers.solver_runs import FlakyResidual, underestimated_noise




def _resume_all(make, residual_factory, theta0, every=5, limit=600, extra=None, prepare=None):
    full, snapshots = run_with_snapshots(make(), residual_factory(), theta0,
                                         set(range(0, limit, every)), extra)
    assert len(snapshots) >= 3
    for k, (state, info) in snapshots.items():
        residual = residual_factory() if prepare is None else prepare(info)
        resumed = make().solve(residual, theta0, state=roundtrip(state))
        check_resume(full, resumed, k)
    return full, snapshots


@pytest.mark.parametrize("noise_factor, stop", [(1.0, "discrepancy"), (0.8, "plateau")])
def test_resume_across_stage_changes_is_bit_identical(noise_factor, stop):
    """Also through the return to the stage before a plateau (noise level too small)."""
    problem = Spring1D(Spring1DConfig(n=16, noise=1e-4))
    D = problem.parameterization.difference_operator()
    residual = fresh(problem) if noise_factor == 1.0 else \
        underestimated_noise(problem, noise_factor)
    full, snapshots = _resume_all(lambda: SplitBregman(SplitBregmanConfig(max_iter=200), D=D),
                                  residual, problem.theta0, every=14)
    assert full.stop_reason == stop
    stages = {k: state["stage"] for k, (state, _) in snapshots.items()}
    assert len(set(stages.values())) >= 3                   # snapshots in three stages


def test_resume_noise_free_fixed_weight_is_bit_identical():
    problem = Spring1D(Spring1DConfig(n=16))
    D = problem.parameterization.difference_operator()
    # data Bregman (clean data) at the weight whose fixed point this chain reaches in ~140
    # iterations; what is tested is the bit-identical resume, not the default weight
    config = SplitBregmanConfig(max_iter=200, mu_rel_bregman=1e3)
    full, _ = _resume_all(lambda: SplitBregman(config, D=D), fresh(problem), problem.theta0,
                          every=12)
    assert full.stop_reason == "tolerance"


def test_resume_with_inner_levenberg_marquardt_isotropic_and_offset():
    problem = Spring1D(Spring1DConfig(n=12, noise=1e-4))
    D = problem.parameterization.difference_operator()
    groups = torch.arange(D.shape[0]) // 2
    offset = torch.full((D.shape[0],), 1e-3, dtype=torch.float64)
    config = SplitBregmanConfig(max_iter=60, inner_solver="levenberg_marquardt", isotropic=True)
    _resume_all(lambda: SplitBregman(config, D=D, groups=groups, offset=offset),
                fresh(problem), problem.theta0, every=7)


def test_resume_when_returning_to_an_accepted_earlier_stage():
    """The search towards stronger TV overshoots and returns (a 'restored' record); the
    accepted earlier stage is part of the state."""
    problem = Spring1D(Spring1DConfig(n=16, noise=1e-4))
    D = problem.parameterization.difference_operator()
    config = SplitBregmanConfig(mu=1e7, stage_tol=3e-2)
    full, snapshots = _resume_all(lambda: SplitBregman(config, D=D), fresh(problem),
                                  problem.theta0, every=13)
    assert full.history[-1].extra.get("restored") == 1.0
    assert any(state["accepted"] is not None for state, _ in snapshots.values())
    # resumed from the 'restored' record itself: nothing left but the stop
    last = full.history[-1].iteration
    _, at_end = run_with_snapshots(SplitBregman(config, D=D), fresh(problem)(),
                                   problem.theta0, {last})
    done = SplitBregman(config, D=D).solve(fresh(problem)(), problem.theta0,
                                           state=roundtrip(at_end[last][0]))
    assert done.history == [] and done.stop_reason == "discrepancy"
    assert torch.equal(done.theta, full.theta)


def test_resume_after_rejected_outer_steps_is_bit_identical():
    problem = Spring1D(n=16, noise=1e-4)
    D = problem.parameterization.difference_operator()
    holder = {}

    def residual_factory():
        holder["r"] = FlakyResidual(fresh(problem)(), start=20, stop=20 + 2 * 13)
        return holder["r"]

    def prepare(count):
        # the resumed run re-linearises once at the saved theta: the failure window of
        # this residual counts linearisations, so it continues one before
        residual = FlakyResidual(fresh(problem)(), start=20, stop=20 + 2 * 13)
        residual.count = count - 1
        return residual

    full, snapshots = run_with_snapshots(
        SplitBregman(SplitBregmanConfig(max_iter=60), D=D), residual_factory(), problem.theta0,
        set(range(61)), extra=lambda: holder["r"].count)
    rejected = [r.iteration for r in full.history if not r.accepted]
    assert len(rejected) == 2
    tested = 0
    for k, (state, count) in snapshots.items():
        if 20 <= count < 20 + 2 * 13 or k < rejected[0] - 2 or k > rejected[-1] + 3:
            continue          # a failing re-linearisation, or far from the rejections
        resumed = SplitBregman(SplitBregmanConfig(max_iter=60), D=D).solve(
            prepare(count), problem.theta0, state=roundtrip(state))
        check_resume(full, resumed, k)
        tested += 1
    assert tested >= 3
