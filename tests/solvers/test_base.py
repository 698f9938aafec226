"""The shared solver base: config validation and choices, the loop, the stop rules, exact
resume."""
import dataclasses
import json
import math
import typing

import pytest
import torch

from torchfit.problems import Spring1D, Spring1DConfig
from torchfit.solvers import (SOLVERS, GaussNewton, GaussNewtonConfig, LevenbergMarquardt,
                              LevenbergMarquardtConfig, ResidualFunction, SolverConfig,
                              SolverConfigError, SplitBregman, SplitBregmanConfig, StopReason,
                              gauss_newton, levenberg_marquardt)
from torchfit.solvers.gauss_newton import GaussNewtonPreconditioner
from torchfit.solvers.levenberg_marquardt import DampingUpdate, LevenbergMarquardtPreconditioner
from torchfit.solvers.split_bregman.settings import DataBregman, InnerSolver

from helpers.solver_resume import check_resume, fresh, roundtrip, run_with_snapshots

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
    (SplitBregmanConfig(inner_solver=3), r"solver\.inner_solver=3 is not a inner_solver choice; "
                                         r"choose one of gauss_newton, levenberg_marquardt"),
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


# -- choices -------------------------------------------------------------------------------
CHOICES = [(GaussNewtonConfig, "preconditioner", GaussNewtonPreconditioner),
           (LevenbergMarquardtConfig, "preconditioner", LevenbergMarquardtPreconditioner),
           (LevenbergMarquardtConfig, "damping_update", DampingUpdate),
           (SplitBregmanConfig, "inner_solver", InnerSolver),
           (SplitBregmanConfig, "data_bregman", DataBregman)]


@pytest.mark.parametrize("config_class, field, choice", CHOICES)
def test_choice_settings_are_enums_named_with_their_choices(config_class, field, choice):
    assert typing.get_type_hints(config_class)[field] is choice
    for member in choice:
        config = config_class(**{field: member.value})      # YAML and CLI give the text
        config.validate()
        assert getattr(config, field) is member and getattr(config, field) == member.value
    listed = ", ".join(member.value for member in choice)
    with pytest.raises(SolverConfigError, match=rf"solver\.{field}=bogus is not a {field} "
                                                rf"choice; choose one of {listed}$"):
        config_class(**{field: "bogus"}).validate()


@pytest.mark.parametrize("config_class, field, choice", CHOICES)
def test_hydra_rejects_a_bad_choice_at_composition(config_class, field, choice):
    omegaconf = pytest.importorskip("omegaconf")
    schema = omegaconf.OmegaConf.structured(config_class)
    with pytest.raises(omegaconf.errors.ValidationError) as error:
        omegaconf.OmegaConf.merge(schema, {field: "bogus"})
    for member in choice:
        assert member.value in str(error.value)
    merged = omegaconf.OmegaConf.merge(schema, {field: list(choice)[-1].value})
    assert getattr(merged, field) == list(choice)[-1].value


def test_saved_settings_and_states_keep_plain_text():
    """The checkpoint compares the settings as JSON and stores the solver state with
    torch.save: choices dump as their text, and the state holds plain strings."""
    config = LevenbergMarquardtConfig(preconditioner="difference", damping_update="nielsen")
    config.validate()
    settings = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
    assert json.loads(json.dumps(settings))["preconditioner"] == "difference"
    assert json.dumps(settings) == json.dumps({**settings, "preconditioner": "difference",
                                               "damping_update": "nielsen"})
    assert str(config.damping_update) == "nielsen" and f"{config.preconditioner}" == "difference"


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
    assert result.stop_reason is StopReason.interrupted
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
            plain = [v for v in state.values() if isinstance(v, str)]
            assert all(type(v) is str for v in plain), plain      # no enum in a state
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


