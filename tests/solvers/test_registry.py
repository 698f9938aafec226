"""The registry: every solver by config name, what a config needs of the parameterisation,
and :func:`torchfit.solvers.build` acting on it."""
from pathlib import Path

import pytest
import torch

from torchfit.problems import Spring1D
from torchfit.solvers import (SOLVERS, GaussNewtonConfig, LevenbergMarquardtConfig, Need, Needs,
                              Solver, SolverConfigError, SolverEntry, SplitBregman,
                              SplitBregmanConfig, build, gauss_newton, levenberg_marquardt,
                              split_bregman)

from helpers.solver_resume import fresh

REPO = Path(__file__).resolve().parents[2]
LEAST_SQUARES = ("gauss_newton", "levenberg_marquardt")


def test_registry_entries():
    assert set(SOLVERS) == {"gauss_newton", "levenberg_marquardt", "split_bregman"}
    for name, entry in SOLVERS.items():
        assert isinstance(entry, SolverEntry)
        assert issubclass(entry.solver_class, Solver)
        assert entry.solver_class.config_class is entry.config_class
        assert (REPO / "conf" / "solver" / f"{name}.yaml").is_file()
        assert entry.config_class().name == name
    for name in LEAST_SQUARES:
        entry = SOLVERS[name]
        assert entry.config_class().needs().difference_operator is not Need.required
        assert entry.config_class(preconditioner="difference").needs() == Needs(Need.required)
        assert not entry.config_class(preconditioner="difference").needs().difference_groups
        assert entry.config_class(preconditioner="none").needs() == Needs()
    assert GaussNewtonConfig().needs() == Needs(Need.if_offered)      # preconditioner=auto
    assert LevenbergMarquardtConfig().needs() == Needs()
    assert SplitBregmanConfig().needs() == Needs(Need.required)
    assert not SplitBregmanConfig().needs().difference_groups
    assert SplitBregmanConfig(isotropic=True).needs() == Needs(Need.required, True)
    for function in (gauss_newton, levenberg_marquardt, split_bregman):
        assert not hasattr(function, "needs_difference_operator")


def test_registered_with_its_config():
    entry = SOLVERS["split_bregman"]
    assert entry.config_class is SplitBregmanConfig and entry.solver_class is SplitBregman
    assert SplitBregmanConfig().needs().difference_operator is Need.required
    assert (REPO / "conf" / "solver" / "split_bregman.yaml").is_file()


def test_build_as_the_run_orchestration_does():
    problem = Spring1D(n=6)
    param = problem.parameterization
    for name, section in (("levenberg_marquardt", {"preconditioner": "difference"}),
                          ("gauss_newton", {}), ("split_bregman", {"max_iter": 3})):
        config = SOLVERS[name].config_class(**section)
        solver = build(config, difference_operator=param.difference_operator,
                       difference_groups=param.difference_groups)
        assert isinstance(solver, SOLVERS[name].solver_class)
        result = solver.solve(fresh(problem)(), problem.theta0)
        assert torch.isfinite(result.theta).all()


class Offered:
    """A parameterisation's operators, counting the calls."""

    def __init__(self, n: int = 6) -> None:
        self.param = Spring1D(n=n).parameterization
        self.calls: list[str] = []

    def difference_operator(self):
        self.calls.append("D")
        return self.param.difference_operator()

    def difference_groups(self):
        self.calls.append("groups")
        return torch.arange(self.param.n_params - 1) // 2


@pytest.mark.parametrize("section, calls, has_D", [
    ({"name": "gauss_newton"}, ["D"], True),                               # auto: if offered
    ({"name": "gauss_newton", "preconditioner": "none"}, [], False),
    ({"name": "gauss_newton", "preconditioner": "difference"}, ["D"], True),
    ({"name": "levenberg_marquardt"}, [], False),
    ({"name": "levenberg_marquardt", "preconditioner": "difference"}, ["D"], True),
    ({"name": "split_bregman"}, ["D"], True),
    ({"name": "split_bregman", "isotropic": True}, ["D", "groups"], True),
])
def test_build_calls_only_the_operators_the_settings_use(section, calls, has_D):
    offered = Offered()
    config = SOLVERS[section["name"]].config_class(**section)
    solver = build(config, difference_operator=offered.difference_operator,
                   difference_groups=offered.difference_groups)
    assert offered.calls == calls
    assert (solver.D is not None) == has_D
    assert (solver.groups is not None) == ("groups" in calls)


def test_build_without_the_operators():
    # preconditioner=auto runs without D where the parameterisation has none
    assert build(GaussNewtonConfig()).D is None
    for config in (SplitBregmanConfig(), LevenbergMarquardtConfig(preconditioner="difference")):
        with pytest.raises(SolverConfigError,
                           match=rf"^solver={config.name} needs the difference operator D of "
                                 r"the parameterisation, but custom's \(Chain\) has none$"):
            build(config, offered_by="custom's (Chain)")
    # isotropic TV where the parameterisation has no groups: every row its own group
    offered = Offered()
    solver = build(SplitBregmanConfig(isotropic=True),
                   difference_operator=offered.difference_operator)
    assert solver.groups is None


def test_build_validates_first():
    with pytest.raises(SolverConfigError, match=r"solver\.tau"):
        build(GaussNewtonConfig(tau=0.5))
    with pytest.raises(SolverConfigError, match=r"solver\.preconditioner=bogus"):
        build(LevenbergMarquardtConfig(preconditioner="bogus"))     # before the missing D
    with pytest.raises(SolverConfigError, match=r"solver='newton' is not a solver; choose one "
                                                r"of \['gauss_newton'"):
        build(GaussNewtonConfig(name="newton"))
