"""The metrics callback: the metrics of PROBLEMS.md at every iteration, at no solver cost."""
from __future__ import annotations

import pytest
import torch

from torchfit.linalg import counting
from torchfit.reporting.metrics import MetricsCallback
from torchfit.problems import build_problem
from torchfit.solvers import LevenbergMarquardtConfig, gauss_newton, levenberg_marquardt

PROBLEM_METRICS = ("misfit", "u_err_inf", "u_err_2", "k_err_inf", "k_err_2", "k_err_rel")


class CountedMetrics(MetricsCallback):
    """The metrics callback, counting what each of its calls costs."""

    def __init__(self, problem):
        super().__init__(problem)
        self.costs: list[tuple[int, int]] = []

    def __call__(self, record):
        with counting() as c:
            super().__call__(record)
        self.costs.append((c.factorizations, c.solves))


@pytest.mark.parametrize("solver,config", [
    (gauss_newton, None),
    # a large initial damping and a slow decrease force rejected steps
    (levenberg_marquardt, LevenbergMarquardtConfig(damping_init=1e-4, decrease=0.1)),
])
def test_metrics_callback_costs_no_factorisation(solver, config):
    problem = build_problem("spring1d", {"noise": 1e-4})
    plain = solver(problem.residual(), problem.theta0, config)
    metrics = CountedMetrics(problem)
    seen: list[dict] = []
    with_metrics = solver(problem.residual(), problem.theta0, config,
                          [metrics, lambda rec: seen.append(dict(rec.extra))])
    assert metrics.costs and all(cost == (0, 0) for cost in metrics.costs)
    # the solver's own cost and path are unchanged
    assert with_metrics.factorizations == plain.factorizations
    assert with_metrics.solves == plain.solves
    assert with_metrics.iterations == plain.iterations
    assert torch.equal(with_metrics.theta, plain.theta)
    # later callbacks see the metrics, and the misfit agrees with the solver's
    for rec, extra in zip(with_metrics.history, seen):
        assert set(PROBLEM_METRICS) <= set(extra)
        assert extra["misfit"] == pytest.approx(rec.misfit, rel=1e-12)
