"""Gauss-Newton: cost model, settings, exact resume (shared behaviour: test_base.py)."""
import math

import pytest

from torchfit.problems import Spring1D, Spring1DConfig
from torchfit.solvers import (GaussNewton, GaussNewtonConfig, LevenbergMarquardtConfig,
                              SolverConfigError, gauss_newton, levenberg_marquardt)

from helpers.solver_resume import check_resume, fresh, roundtrip, run_with_snapshots
from helpers.solver_runs import CountingResidual, distinct



def test_gauss_newton_step_costs_one_factorization_per_point_and_2m_plus_2_solves():
    problem = Spring1D()
    residual = CountingResidual(problem.residual())
    problem.equilibrium.clear_cache()
    result = gauss_newton(residual, problem.theta0, GaussNewtonConfig(max_iter=8))
    assert result.factorizations == distinct(residual.points) == len(residual.points)
    history = result.history
    for before, after in zip(history[:-1], history[1:]):
        m = after.cg_iterations
        assert m >= 1
        steps_tried = round(-math.log2(after.extra["step_length"])) + 1
        assert after.factorizations - before.factorizations == steps_tried
        assert after.solves - before.solves <= 2 * m + 2 + (steps_tried - 1)
    # full steps (no backtracking) cost exactly one factorisation and at most 2m + 2 solves
    full = [(b, a) for b, a in zip(history[:-1], history[1:]) if a.extra["step_length"] == 1.0]
    assert full
    for before, after in full:
        assert after.factorizations - before.factorizations == 1
        assert after.solves - before.solves <= 2 * after.cg_iterations + 2


@pytest.mark.parametrize("config, match", [
    (GaussNewtonConfig(tau=0.9), "solver.tau"),
    (GaussNewtonConfig(eta_max=1.5), "eta_max"),
    (GaussNewtonConfig(cg_max_iter=0), "cg_max_iter"),
    (LevenbergMarquardtConfig(damping_init=0.0), "damping_init"),
    (LevenbergMarquardtConfig(decrease=2.0), "decrease"),
    (LevenbergMarquardtConfig(preconditioner="ilu"), "solver.preconditioner"),
    (LevenbergMarquardtConfig(damping_update="fletcher"), "solver.damping_update"),
    (LevenbergMarquardtConfig(geodesic_step=0.0), "solver.geodesic_step"),
    (LevenbergMarquardtConfig(preconditioner_shift=0.0), "preconditioner_shift"),
    (LevenbergMarquardtConfig(preconditioner_probes=0), "preconditioner_probes"),
    # the difference preconditioner without the difference operator D
    (LevenbergMarquardtConfig(preconditioner="difference"), "needs the difference operator D"),
])
def test_bad_solver_settings_are_named(config, match):
    problem = Spring1D(n=4)
    solver = gauss_newton if isinstance(config, GaussNewtonConfig) else levenberg_marquardt
    with pytest.raises(SolverConfigError, match=match):
        solver(fresh(problem)(), problem.theta0, config)



@pytest.mark.parametrize("noise", [0.0, 1e-4])
@pytest.mark.parametrize("preconditioner", ["none", "difference"])
def test_resume_from_any_iteration_is_bit_identical(noise, preconditioner):
    problem = Spring1D(Spring1DConfig(n=16, noise=noise))
    D = problem.parameterization.difference_operator()
    config = GaussNewtonConfig(preconditioner=preconditioner)
    full, snapshots = run_with_snapshots(GaussNewton(config, D=D), fresh(problem)(),
                                         problem.theta0, set(range(20)))
    assert full.iterations >= 4 and len(snapshots) == full.iterations + 1
    for k, (state, _) in snapshots.items():
        resumed = GaussNewton(config, D=D).solve(fresh(problem)(), problem.theta0,
                                                 state=roundtrip(state))
        check_resume(full, resumed, k)


@pytest.mark.parametrize("seed", [0, 3, 9])
def test_max_step_is_a_trust_region_for_cgls_not_a_clip_afterwards(seed):
    """An ill-posed exponential model ``y = exp(3 A theta)`` (20 parameters, singular
    values 1 to 1e-4) with noise and ``max_step=1``. Far from the truth the linear model
    cannot reach REGINN's target, so an unbounded CGLS runs to its cap on small singular
    values and clipping that step leaves it useless: Gauss-Newton then ended at
    ``max_iter`` with a misfit 20 to 1,700 times the noise and relative errors 7-19
    (seeds 0, 3, 9). CGLS now stops on the box's boundary (Steihaug): the discrepancy
    principle is reached in a few iterations and the error is below 0.6."""
    import torch

    from torchfit.residual import ResidualFunction

    g = torch.Generator().manual_seed(seed)
    n, m = 20, 60
    q, _ = torch.linalg.qr(torch.randn(m, n, generator=g, dtype=torch.float64))
    w, _ = torch.linalg.qr(torch.randn(n, n, generator=g, dtype=torch.float64))
    A = q * torch.logspace(0, -4, n, dtype=torch.float64) @ w.T
    truth = 1.5 * torch.randn(n, generator=g, dtype=torch.float64)

    def forward(theta):
        return torch.exp(3 * A @ theta)

    noise = 1e-3 * torch.randn(m, generator=g, dtype=torch.float64)
    delta = float(noise.norm())
    residual = ResidualFunction(forward, forward(truth) + noise, noise_level=delta)
    config = GaussNewtonConfig(max_iter=30, max_step=1.0, dense_jacobian_max_params=0)
    seen = []
    result = GaussNewton(config).solve(residual, torch.zeros(n, dtype=torch.float64),
                                       [lambda r: seen.append(r)])
    assert result.stop_reason == "discrepancy"
    assert len(result.history) <= 10
    assert seen[-1].misfit <= config.tau * delta
    assert float((result.theta - truth).norm() / truth.norm()) < 0.6
    steps = torch.stack([r.theta for r in seen]).diff(dim=0).abs()
    assert float(steps.max()) <= 1.0 + 1e-12
    # each inner solve ends at REGINN's target or on the box, never at the CGLS cap
    assert all(r.cg_iterations < config.cg_max_iter for r in seen[1:])
