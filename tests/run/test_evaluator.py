"""The run's evaluator: one simulation per recorded iteration, the metrics of docs/problems.md at
no solver cost, and observers that add no simulation."""
from __future__ import annotations

import pytest
import torch

from helpers.runs import QUIET
from helpers.simulations import SimulationCounter
from torchfit.linalg import counting
from torchfit.problems import build_problem
from torchfit.run import FitOptions, fit
from torchfit.run.evaluator import Evaluator
from torchfit.solvers import LevenbergMarquardtConfig, gauss_newton, levenberg_marquardt

PROBLEM_METRICS = ("misfit", "u_err_inf", "u_err_2", "k_err_inf", "k_err_2", "k_err_rel")


class CountedEvaluator(Evaluator):
    """The evaluator, counting what each of its calls costs."""

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
def test_an_evaluation_costs_no_factorisation(solver, config):
    problem = build_problem("spring1d", {"noise": 1e-4})
    plain = solver(problem.residual(), problem.theta0, config)
    evaluator = CountedEvaluator(problem)
    seen: list[dict] = []
    with_metrics = solver(problem.residual(), problem.theta0, config,
                          [evaluator, lambda rec: seen.append(dict(rec.extra))])
    assert evaluator.costs and all(cost == (0, 0) for cost in evaluator.costs)
    # the solver's own cost and path are unchanged
    assert with_metrics.factorizations == plain.factorizations
    assert with_metrics.solves == plain.solves
    assert with_metrics.iterations == plain.iterations
    assert torch.equal(with_metrics.theta, plain.theta)
    # later callbacks see the metrics, and the misfit agrees with the solver's
    for rec, extra in zip(with_metrics.history, seen):
        assert set(PROBLEM_METRICS) <= set(extra)
        assert extra["misfit"] == pytest.approx(rec.misfit, rel=1e-12)
    # the end of the run reads the last record's evaluation
    assert evaluator.final(with_metrics.theta) is evaluator.last
    assert evaluator.simulations == len(with_metrics.history)


def test_an_observer_is_fed_the_evaluation_of_its_record():
    problem = build_problem("spring1d", {"n": 8})
    evaluator = Evaluator(problem)
    seen = []
    result = gauss_newton(problem.residual(), problem.theta0, None,
                          [evaluator, evaluator.feed(seen.append)])
    assert [e.record for e in seen] == result.history
    assert all(torch.equal(e.theta, r.theta) for e, r in zip(seen, result.history))
    with pytest.raises(RuntimeError, match="before the run evaluated"):
        Evaluator(problem).feed(seen.append)(result.history[0])


#: problems whose observers all read the state: spring1d (metrics, progress, TensorBoard),
#: poisson2d (field images), membrane2d (frames, meshes, field images), a dynamic chain
#: (per-time errors); (problem, settings, solver)
RUNS = {
    "spring1d": ("spring1d", {"n": 16, "noise": 1e-4}, {"name": "levenberg_marquardt",
                                                       "damping_init": 1e-4, "decrease": 0.1}),
    "poisson2d": ("poisson2d", {"N": 8, "noise": 1e-3}, {"name": "split_bregman",
                                                         "max_iter": 6}),
    "membrane2d": ("membrane2d", {"nx": 8, "ny": 4}, {"name": "levenberg_marquardt",
                                                      "max_iter": 3}),
    "dynamic": ("spring1d", {"dynamic": True, "n": 6, "frames": 4, "duration": 0.5},
                {"name": "gauss_newton", "max_iter": 2}),
}


@pytest.mark.parametrize("name", sorted(RUNS))
def test_one_simulation_per_recorded_iteration_and_none_by_observers(tmp_path, name):
    kind, settings, solver = RUNS[name]
    counts, results = {}, {}
    for where in ("files", "none"):
        problem = build_problem(kind, settings)
        counts[where] = SimulationCounter(problem)
        results[where] = fit(problem, solver, options=FitOptions(progress=where == "files",
                                                                  snapshot_iterations=[1]),
                             run_dir=tmp_path / "run" if where == "files" else None)
    with_files, counted = results["files"], counts["files"]
    assert counted.per_record == {i: 1 for i in range(len(with_files.history))}
    assert counted.observers == 0 and counted.end == 0      # the end reads the last record's
    # every observer (TensorBoard, images, the problem's outputs, files) adds no simulation
    assert counted.total == counts["none"].total
    assert torch.equal(with_files.theta, results["none"].theta)
    assert with_files.history[-1]["misfit"] == with_files.metrics["misfit"]


def test_a_resumed_run_that_records_nothing_evaluates_its_end_once(tmp_path):
    problem = build_problem("spring1d", {"n": 8})
    fit(problem, {"name": "gauss_newton", "max_iter": 2}, run_dir=tmp_path, options=QUIET)
    (tmp_path / "result.json").unlink()          # as if killed before its end
    problem = build_problem("spring1d", {"n": 8})
    counted = SimulationCounter(problem)
    again = fit(problem, {"name": "gauss_newton", "max_iter": 2}, run_dir=tmp_path,
                resume=True, options=QUIET)
    assert again.resumed_from == 2 and not counted.per_record
    assert counted.end == 1 and counted.observers == 0


def test_the_counter_sees_an_observer_that_simulates():
    problem = build_problem("spring1d", {"n": 4})
    counted = SimulationCounter(problem)
    scope = {"__name__": "torchfit.reporting.an_observer", "problem": problem}
    exec("def observe(theta):\n    return problem.simulate(problem.field(theta))", scope)
    scope["observe"](problem.theta0)
    Evaluator(problem).evaluate(problem.theta0)
    assert (counted.observers, counted.end, counted.total) == (1, 1, 2)
