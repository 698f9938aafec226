"""Gauss-Newton and Levenberg-Marquardt on spring1d and on synthetic residuals."""
import ast
import math
from pathlib import Path

import pytest
import torch

from torchfit.problems import Spring1D
from torchfit.solvers import (GaussNewtonConfig, LevenbergMarquardtConfig, ResidualFunction,
                              SolverConfigError, gauss_newton, levenberg_marquardt)

from conftest import CountingResidual

SOLVERS = {"gauss_newton": gauss_newton, "levenberg_marquardt": levenberg_marquardt}


def first_iteration_below(problem, result, threshold):
    for record in result.history:
        if problem.metrics(record.theta)["k_err_rel"] <= threshold:
            return record.iteration
    return None


@pytest.mark.parametrize("name", sorted(SOLVERS))
def test_dense_noise_free_recovers_truth_within_15_iterations(name):
    problem = Spring1D()
    result = SOLVERS[name](problem.residual(), problem.theta0)
    assert result.converged, result.stop_reason
    assert problem.metrics(result.theta)["k_err_rel"] <= 1e-7
    reached = first_iteration_below(problem, result, 1e-7)
    assert reached is not None and reached <= 15


@pytest.mark.parametrize("name", sorted(SOLVERS))
def test_noisy_dense_stops_by_discrepancy(name):
    problem = Spring1D(noise=1e-4)
    residual = problem.residual()
    result = SOLVERS[name](residual, problem.theta0)
    assert result.stop_reason == "discrepancy"
    assert result.history[-1].misfit <= 1.5 * problem.noise_level
    # the iteration before the stop had not yet reached the discrepancy level
    assert result.history[-2].misfit > 1.5 * problem.noise_level
    assert problem.metrics(result.theta)["k_err_rel"] <= 0.05




def distinct(points):
    unique: list[torch.Tensor] = []
    for p in points:
        if not any(torch.equal(p, q) for q in unique):
            unique.append(p)
    return len(unique)


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


def test_gauge_direction_is_never_moved_along():
    """A scale-free residual: r depends on theta only through theta - mean(theta)."""
    torch.manual_seed(1)
    a = torch.randn(30, 6)
    truth = torch.randn(6)

    def forward(theta):
        centred = theta - theta.mean()
        return a @ torch.exp(centred)

    data = forward(truth)
    gauge = lambda theta: torch.full_like(theta, 1 / math.sqrt(theta.numel()))  # noqa: E731
    theta0 = torch.full((6,), 0.3)
    for solver in SOLVERS.values():
        result = solver(ResidualFunction(forward, data, gauge=gauge), theta0)
        assert result.converged
        assert float(result.theta.mean()) == pytest.approx(0.3, abs=1e-12)
        assert torch.allclose(result.theta - result.theta.mean(), truth - truth.mean(), atol=1e-6)


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
        solver(problem.residual(), problem.theta0, config)


def test_callback_can_stop_and_sees_every_iteration():
    problem = Spring1D(n=8)
    seen = []

    def callback(record):
        seen.append(record.iteration)
        return record.iteration == 2

    result = gauss_newton(problem.residual(), problem.theta0, callbacks=[callback])
    assert result.stop_reason == "interrupted" and seen == [0, 1, 2]


def test_solvers_import_nothing_from_physics_mesh_or_problems():
    package = Path(__file__).resolve().parents[2] / "torchfit" / "solvers"
    for source in package.glob("*.py"):
        tree = ast.parse(source.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                module = ("." * node.level) + (node.module or "")
                assert not any(part in module for part in ("physics", "mesh", "problems")), \
                    f"{source.name} imports {module}"
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    assert not any(p in alias.name for p in ("physics", "mesh", "problems"))
