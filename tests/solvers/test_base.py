"""The shared solver base: config validation, the loop, the stop rules, the registry,
exact resume, the import graph of the package."""
import dataclasses
import math
import typing
from pathlib import Path

import pytest
import torch

from torchfit.problems import Spring1D, Spring1DConfig
from torchfit.solvers import (SOLVERS, GaussNewton, GaussNewtonConfig, LevenbergMarquardt,
                              LevenbergMarquardtConfig, ResidualFunction, Solver, SolverConfig,
                              SolverConfigError, SolverEntry, SplitBregman, SplitBregmanConfig,
                              gauss_newton, levenberg_marquardt, split_bregman)

from resume import check_resume, fresh, roundtrip, run_with_snapshots

REPO = Path(__file__).resolve().parents[2]
CONFIGS = (GaussNewtonConfig, LevenbergMarquardtConfig, SplitBregmanConfig)
LEAST_SQUARES = {"gauss_newton": gauss_newton, "levenberg_marquardt": levenberg_marquardt}


def numeric_fields(config_class):
    hints = typing.get_type_hints(config_class)
    for field in dataclasses.fields(config_class):
        kind = hints[field.name]
        if kind in (int, float) or kind == typing.Optional[float]:
            yield field.name


# -- config validation -----------------------------------------------------------------------
@pytest.mark.parametrize("config_class, field, value", [
    (cls, field, value) for cls in CONFIGS for field in numeric_fields(cls)
    for value in (math.inf, -math.inf, math.nan)])
def test_every_numeric_field_must_be_finite(config_class, field, value):
    config = config_class(**{field: value})
    with pytest.raises(SolverConfigError, match=rf"solver\.{field}=") as error:
        config.validate()
    assert "\n" not in str(error.value)


def test_the_infinite_settings_that_used_to_pass_are_rejected():
    """growth=inf crashed 46 iterations later, tau=inf reported theta0 as converged,
    damping_init=inf rejected every step and exited 0."""
    for config in (SplitBregmanConfig(growth=math.inf), GaussNewtonConfig(tau=math.inf),
                   LevenbergMarquardtConfig(damping_init=math.inf)):
        with pytest.raises(SolverConfigError, match="finite"):
            config.validate()


@pytest.mark.parametrize("config, match", [
    (GaussNewtonConfig(max_iter=-1), r"solver\.max_iter=-1"),
    (GaussNewtonConfig(max_iter=2.5), r"solver\.max_iter=2\.5.*integer"),
    (LevenbergMarquardtConfig(cg_max_iter=True), r"solver\.cg_max_iter=True.*integer"),
    (LevenbergMarquardtConfig(geodesic_acceleration=1), r"solver\.geodesic_acceleration=1.*true"),
    (SplitBregmanConfig(isotropic="yes"), r"solver\.isotropic=yes.*true or false"),
    (SplitBregmanConfig(mu=True), r"solver\.mu=True.*number"),
    (SplitBregmanConfig(inner_solver=3), r"solver\.inner_solver=3.*string"),
    (GaussNewtonConfig(tau="1.5"), r"solver\.tau=1\.5: must be a number"),
])
def test_types_are_checked(config, match):
    with pytest.raises(SolverConfigError, match=match):
        config.validate()


@pytest.mark.parametrize("config_class", CONFIGS)
def test_defaults_are_valid_and_plain_dataclasses(config_class):
    config = config_class()
    config.validate()
    assert isinstance(config, SolverConfig) and dataclasses.is_dataclass(config)
    assert config.name == next(name for name, e in SOLVERS.items() if e.config_class is config_class)
    # optional numbers are valid when set
    if config_class is SplitBregmanConfig:
        config_class(mu=1.0, beta=2).validate()


def test_a_solver_validates_its_config_and_rejects_another_solvers():
    with pytest.raises(SolverConfigError, match="solver.tau"):
        GaussNewton(GaussNewtonConfig(tau=math.nan))
    with pytest.raises(TypeError, match="GaussNewtonConfig"):
        GaussNewton(LevenbergMarquardtConfig())


# -- registry --------------------------------------------------------------------------------
def test_registry_entries():
    assert set(SOLVERS) == {"gauss_newton", "levenberg_marquardt", "split_bregman"}
    for name, entry in SOLVERS.items():
        assert isinstance(entry, SolverEntry)
        assert issubclass(entry.solver_class, Solver)
        assert entry.solver_class.config_class is entry.config_class
        assert (REPO / "conf" / "solver" / f"{name}.yaml").is_file()
    for name in LEAST_SQUARES:
        entry = SOLVERS[name]
        assert not entry.needs_difference_operator(entry.config_class())
        assert entry.needs_difference_operator(entry.config_class(preconditioner="difference"))
        assert not entry.uses_groups(entry.config_class(preconditioner="difference"))
    sb = SOLVERS["split_bregman"]
    assert sb.needs_difference_operator(SplitBregmanConfig())
    assert not sb.uses_groups(SplitBregmanConfig())
    assert sb.uses_groups(SplitBregmanConfig(isotropic=True))
    for function in (gauss_newton, levenberg_marquardt, split_bregman):
        assert not hasattr(function, "needs_difference_operator")


def test_registry_use_as_the_run_orchestration_does():
    problem = Spring1D(n=6)
    for name, section in (("levenberg_marquardt", {"preconditioner": "difference"}),
                          ("gauss_newton", {}), ("split_bregman", {"max_iter": 3})):
        entry = SOLVERS[name]
        config = entry.config_class(**section)
        config.validate()
        D = problem.parameterization.difference_operator() \
            if entry.needs_difference_operator(config) else None
        groups = problem.parameterization.difference_groups() if entry.uses_groups(config) \
            else None
        result = entry.solver_class(config, D=D, groups=groups).solve(fresh(problem)(),
                                                                      problem.theta0)
        assert torch.isfinite(result.theta).all()


# -- the loop and the shared stop rules ----------------------------------------------------
def first_iteration_below(problem, result, threshold):
    for record in result.history:
        if problem.metrics(record.theta)["k_err_rel"] <= threshold:
            return record.iteration
    return None


@pytest.mark.parametrize("name", sorted(LEAST_SQUARES))
def test_dense_noise_free_recovers_truth_within_15_iterations(name):
    problem = Spring1D()
    result = LEAST_SQUARES[name](fresh(problem)(), problem.theta0)
    assert result.converged, result.stop_reason
    assert problem.metrics(result.theta)["k_err_rel"] <= 1e-7
    reached = first_iteration_below(problem, result, 1e-7)
    assert reached is not None and reached <= 15


@pytest.mark.parametrize("name", sorted(LEAST_SQUARES))
def test_noisy_dense_stops_by_discrepancy(name):
    problem = Spring1D(noise=1e-4)
    residual = problem.residual()
    result = LEAST_SQUARES[name](residual, problem.theta0)
    assert result.stop_reason == "discrepancy"
    assert result.history[-1].misfit <= 1.5 * problem.noise_level
    # the iteration before the stop had not yet reached the discrepancy level
    assert result.history[-2].misfit > 1.5 * problem.noise_level
    assert problem.metrics(result.theta)["k_err_rel"] <= 0.05


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
    for solver in LEAST_SQUARES.values():
        result = solver(ResidualFunction(forward, data, gauge=gauge), theta0)
        assert result.converged
        assert float(result.theta.mean()) == pytest.approx(0.3, abs=1e-12)
        assert torch.allclose(result.theta - result.theta.mean(), truth - truth.mean(), atol=1e-6)


@pytest.mark.parametrize("make", [GaussNewton, LevenbergMarquardt])
def test_callback_can_stop_and_sees_every_iteration(make):
    problem = Spring1D(n=8)
    seen = []

    def callback(record):
        seen.append(record.iteration)
        return record.iteration == 2

    result = make().solve(fresh(problem)(), problem.theta0, [callback])
    assert result.stop_reason == "interrupted" and seen == [0, 1, 2]
    assert result.iterations == 2 and not result.converged


# -- state and resume ----------------------------------------------------------------------
def test_state_dict_needs_a_run():
    with pytest.raises(RuntimeError, match="before solve"):
        GaussNewton().state_dict()


def test_state_dict_is_plain_and_weights_only_loadable():
    problem = Spring1D(Spring1DConfig(n=8, noise=1e-4))
    D = problem.parameterization.difference_operator()
    for solver in (GaussNewton(GaussNewtonConfig(preconditioner="difference"), D=D),
                   LevenbergMarquardt(LevenbergMarquardtConfig(preconditioner="difference",
                                                               cg_max_iter=2), D=D),
                   SplitBregman(SplitBregmanConfig(max_iter=30), D=D)):
        states = []
        solver.solve(fresh(problem)(), problem.theta0,
                     [lambda record, s=solver: states.append(s.state_dict())])
        for state in states:
            loaded = roundtrip(state)
            assert loaded.keys() == state.keys()
            for key in ("iteration", "theta", "wall_time", "factorizations", "solves"):
                assert key in loaded
        assert [s["iteration"] for s in states] == list(range(len(states)))


@pytest.mark.parametrize("make", [
    lambda D: GaussNewton(GaussNewtonConfig(max_iter=6, rtol=0.0, gtol=0.0)),
    lambda D: LevenbergMarquardt(LevenbergMarquardtConfig(max_iter=6, damping_init=1e-12,
                                                           rtol=0.0, gtol=0.0)),
    lambda D: SplitBregman(SplitBregmanConfig(max_iter=6), D=D),
])
def test_max_iter_is_the_budget_of_the_whole_run(make):
    problem = Spring1D(n=8)
    D = problem.parameterization.difference_operator()
    full, snapshots = run_with_snapshots(make(D), fresh(problem)(), problem.theta0, {3, 6})
    assert full.stop_reason == "max_iter" and full.iterations == 6
    resumed = make(D).solve(fresh(problem)(), problem.theta0,
                            state=roundtrip(snapshots[3][0]))
    check_resume(full, resumed, 3)
    assert [r.iteration for r in resumed.history] == [4, 5, 6]
    # resumed at the end of the budget: nothing left to do, nothing emitted
    done = make(D).solve(fresh(problem)(), problem.theta0, state=roundtrip(snapshots[6][0]))
    assert done.history == [] and done.iterations == 6 and done.stop_reason == "max_iter"
    assert torch.equal(done.theta, full.theta)
    assert (done.factorizations, done.solves) == (full.factorizations, full.solves)


def test_resume_continues_the_clock():
    problem = Spring1D(n=8)
    full, snapshots = run_with_snapshots(GaussNewton(), fresh(problem)(), problem.theta0, {2})
    state = roundtrip(snapshots[2][0])
    state["wall_time"] = 1000.0
    resumed = GaussNewton().solve(fresh(problem)(), problem.theta0, state=state)
    assert all(r.wall_time >= 1000.0 for r in resumed.history) and resumed.wall_time >= 1000.0


