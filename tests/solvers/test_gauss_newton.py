"""Gauss-Newton: cost model, settings, exact resume (shared behaviour: test_base.py)."""
import math

import pytest

from torchfit.problems import Spring1D, Spring1DConfig
from torchfit.solvers import (GaussNewton, GaussNewtonConfig, LevenbergMarquardtConfig,
                              SolverConfigError, gauss_newton, levenberg_marquardt)

from conftest import CountingResidual, distinct
from resume import check_resume, fresh, roundtrip, run_with_snapshots



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
