"""Levenberg-Marquardt: rejected steps, settings, exact resume."""

import dataclasses

import pytest
import torch

from torchfit.problems import Spring1D, Spring1DConfig
from torchfit.solvers import (LevenbergMarquardt, LevenbergMarquardtConfig, ResidualFunction,
                              levenberg_marquardt)

from helpers.solver_resume import check_resume, fresh, roundtrip, run_with_snapshots
from helpers.solver_runs import CountingResidual, distinct


def test_levenberg_marquardt_rejected_step_keeps_theta_and_factorization():
    problem = Spring1D()
    problem.equilibrium.clear_cache()
    residual = CountingResidual(problem.residual())
    # almost no damping: the first (Gauss-Newton-like) step overshoots and is rejected
    result = levenberg_marquardt(residual, problem.theta0,
                                 LevenbergMarquardtConfig(damping_init=1e-12, max_iter=6))
    rejected = [r for r in result.history if not r.accepted]
    assert rejected
    history = result.history
    for before, after in zip(history[:-1], history[1:]):
        if not after.accepted:
            assert torch.equal(after.theta, before.theta)
            assert after.misfit == before.misfit
            assert after.step_norm == 0.0
        # every iteration evaluates exactly one new point: one factorisation, no more
        assert after.factorizations - before.factorizations == 1
    assert result.factorizations == distinct(residual.points)
    # a rejection makes the next step more damped
    for rejected_step, next_step in zip(history[1:-1], history[2:]):
        if not rejected_step.accepted:
            assert next_step.damping > rejected_step.damping




@pytest.mark.parametrize("noise", [0.0, 1e-4])
@pytest.mark.parametrize("config", [
    LevenbergMarquardtConfig(damping_init=1e-12),          # rejected steps, growth factor
    LevenbergMarquardtConfig(geodesic_acceleration=True, damping_update="nielsen",
                             preconditioner="difference", cg_max_iter=5),
], ids=["rejections", "geodesic-preconditioned"])
def test_resume_from_any_iteration_is_bit_identical(noise, config):
    problem = Spring1D(Spring1DConfig(n=16, noise=noise))
    D = problem.parameterization.difference_operator()
    full, snapshots = run_with_snapshots(LevenbergMarquardt(config, D=D), fresh(problem)(),
                                         problem.theta0, set(range(0, 40, 2)))
    assert any(not r.accepted for r in full.history)
    for k, (state, _) in snapshots.items():
        if config.preconditioner == "difference" and k > 2:
            assert state["laplacian_active"]
        resumed = LevenbergMarquardt(config, D=D).solve(fresh(problem)(), problem.theta0,
                                                        state=roundtrip(state))
        # noise-free and converged, the geodesic probe repeats a point of the previous
        # (rejected) iteration, which the simulator's cache serves in the uninterrupted run
        check_resume(full, resumed, k, counters=noise > 0 or not config.geodesic_acceleration)


@pytest.mark.parametrize("solver", ["levenberg_marquardt", "gauss_newton"])
def test_max_step_clips_every_component_and_still_converges(solver):
    """A badly scaled linear least-squares problem: the unlimited first step moves one
    parameter by 50; with max_step = 1 no component of any step exceeds 1, the well
    observed parameter still converges, and so does the weak one, 1 per iteration."""
    from torchfit.solvers import SOLVERS

    A = torch.tensor([[1.0, 0.0], [0.0, 0.02], [1.0, 0.0]], dtype=torch.float64)
    truth = torch.tensor([0.5, 20.0], dtype=torch.float64)
    residual = ResidualFunction(lambda t: A @ t, A @ truth)
    entry = SOLVERS[solver]
    config = entry.config_class(max_iter=60, max_step=1.0, **(
        {"rtol": 0.0, "gtol": 0.0} if solver == "levenberg_marquardt" else {}))
    seen = []
    result = entry.solver_class(config).solve(residual, torch.zeros(2, dtype=torch.float64),
                                              [lambda r: seen.append(r.theta.clone())])
    steps = torch.stack(seen).diff(dim=0).abs()
    assert float(steps.max()) <= 1.0 + 1e-12
    assert float(steps[:, 0].max()) > 0.4               # the well observed one moves at once
    assert torch.allclose(result.theta, truth, atol=1e-6)


@pytest.mark.parametrize("solver", ["levenberg_marquardt", "gauss_newton"])
def test_max_step_scales_a_clipped_step_that_would_not_descend(solver):
    """Two nearly dependent columns: the step is large along a nearly cancelling pair,
    and clipping each component to 1 makes the linear model predict an increase. LM
    then raises its damping and solves again without a trial simulation; Gauss-Newton's
    CGLS stops on the box (a trust region), so its step is never clipped: no iteration
    is rejected and both reach the truth. Before, LM spent 11 of 30 iterations on rejected
    trials and ended halfway (15.4, -14.4), and Gauss-Newton stopped at its first step
    ('tolerance': the clipped step had no descent)."""
    from torchfit.solvers import SOLVERS

    A = torch.tensor([[1.0, 1.0], [1.0, 1.001], [0.0, 0.0]], dtype=torch.float64)
    truth = torch.tensor([30.0, -29.0], dtype=torch.float64)
    residual = ResidualFunction(lambda t: A @ t, A @ truth)
    entry = SOLVERS[solver]
    config = entry.config_class(max_iter=40, max_step=1.0, **(
        {"damping_init": 1e-8, "rtol": 0.0, "gtol": 0.0} if solver == "levenberg_marquardt"
        else {}))
    result = entry.solver_class(config).solve(residual, torch.zeros(2, dtype=torch.float64))
    assert all(r.accepted for r in result.history)
    steps = torch.stack([r.theta for r in result.history]).diff(dim=0).abs()
    assert float(steps.max()) <= 1.0 + 1e-12
    assert torch.allclose(result.theta, truth, atol=1e-6)


def test_a_step_the_model_says_does_not_descend_costs_no_simulation(monkeypatch):
    """A step whose linear model predicts no decrease cannot have a positive gain ratio:
    it is rejected without simulating the trial point."""
    problem = Spring1D(Spring1DConfig(n=16))
    residual = CountingResidual(problem.residual())
    solver = LevenbergMarquardt(LevenbergMarquardtConfig(max_iter=3))

    def uphill(inner, damping, normal):           # the step reversed: J d points uphill
        return dataclasses.replace(inner, x=-inner.x, Ax=-inner.Ax), damping

    monkeypatch.setattr(solver, "_limit_step", uphill)
    solver.config.max_step = 1e9                 # so that _limit_step is called
    result = solver.solve(residual, problem.theta0)
    assert [r.accepted for r in result.history] == [True, False, False, False]
    assert len(residual.points) == 1             # theta0 only: no trial was simulated
    assert all(r.extra["gain_ratio"] == -1.0 for r in result.history[1:])


@pytest.mark.parametrize("solver", ["levenberg_marquardt", "gauss_newton"])
def test_a_trial_the_simulation_cannot_tell_apart_ends_the_fit_at_its_resolution(solver):
    """A forward model of finite resolution (a Newton warm-started at the current point
    returns it unchanged for a small enough step): here outputs rounded to 2^-12, with
    exact derivatives. Once a trial's misfit is bit-identical to the current one, more
    damping (or a shorter line-search step) only repeats it: the fit stops
    ('resolution', converged) at that first such trial. Before, LM doubled its damping
    until 'stalled' (12 iterations, 9 rejected) and Gauss-Newton ended 'line_search'
    (not converged)."""
    from torchfit.solvers import SOLVERS

    A = torch.tensor([[1.0, 0.3], [0.2, 1.0], [0.5, -0.4]], dtype=torch.float64)
    quantum = 2.0 ** -12

    def forward(theta):
        y = A @ theta
        return y + (torch.round(y / quantum) * quantum - y).detach()

    data = A @ torch.tensor([0.7, -1.3], dtype=torch.float64) + torch.tensor(
        [1e-3, -2e-3, 1.5e-3], dtype=torch.float64)          # no exact fit: the misfit stays
    residual = ResidualFunction(forward, data)
    entry = SOLVERS[solver]
    config = entry.config_class(max_iter=200, rtol=0.0, **(
        {"gtol": 0.0} if solver == "levenberg_marquardt" else {}))
    result = entry.solver_class(config).solve(residual, torch.zeros(2, dtype=torch.float64))
    assert result.stop_reason == "resolution" and result.converged
    best = torch.linalg.lstsq(A, data[:, None]).solution[:, 0]
    assert float((result.theta - best).abs().max()) < 10 * quantum
    rejected = sum(not r.accepted for r in result.history)
    assert rejected == 0 and result.iterations <= 4, (rejected, result.iterations)
