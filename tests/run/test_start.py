"""Where a fit starts: ``init=`` an earlier run (directory, params.pt or a tensor), and what
it refuses."""
from __future__ import annotations

import pytest
import torch

from helpers.runs import QUIET
from torchfit.problems import build_problem
from torchfit.reporting.results import save_params
from torchfit.run import FitConfigError, ResumeError, fit, initial_theta



def test_init_starts_where_an_earlier_run_ended_and_a_resume_must_repeat_it(tmp_path):
    settings = {"n": 16, "noise": 1e-4, "seed": 1}
    first = fit(build_problem("spring1d", settings), {"name": "gauss_newton", "max_iter": 1},
                run_dir=tmp_path / "first", options=QUIET)
    problem = build_problem("spring1d", settings)
    second = fit(problem, "gauss_newton", run_dir=tmp_path / "second", options=QUIET,
                 init=tmp_path / "first")
    # record 0 of the second run is the first run's last point, not the initial guess
    assert second.history[0]["misfit"] == first.metrics["misfit"]
    initial = fit(problem, {"name": "gauss_newton", "max_iter": 0}, options=QUIET)
    assert second.history[0]["misfit"] < 0.9 * initial.metrics["misfit"]
    assert second.stop_reason == "discrepancy" and second.metrics["misfit"] < first.metrics["misfit"]
    same = fit(problem, "gauss_newton", options=QUIET, init=first.theta)   # a tensor
    assert torch.equal(same.theta, second.theta)
    # the second run's checkpoint remembers its start: resuming from another one is refused
    for other in (None, torch.zeros(16)):
        with pytest.raises(ResumeError, match="init"):
            fit(problem, "gauss_newton", run_dir=tmp_path / "second", resume=True,
                options=QUIET, init=other)
    again = fit(problem, "gauss_newton", run_dir=tmp_path / "second", resume=True,
                options=QUIET, init=tmp_path / "first" / "params.pt")
    assert torch.equal(again.theta, second.theta)


def test_init_refuses_a_run_of_another_parameterisation(tmp_path):
    problem = build_problem("spring1d", {"n": 8})
    theta = problem.theta0
    for key, saved in (("transform", ("k", "identity")), ("field_name", ("E", "exp"))):
        save_params(tmp_path / key, theta, theta.exp(), *saved)
        with pytest.raises(FitConfigError, match=f"{key} '.*', but spring1d's is") as info:
            initial_theta(problem, tmp_path / key)
        assert str(tmp_path / key / "params.pt") in str(info.value)
    save_params(tmp_path / "same", theta + 1, theta.exp(), "k", "exp")
    assert torch.equal(initial_theta(problem, tmp_path / "same"), theta + 1)


def test_init_refuses_another_problems_params_whose_count_agrees(tmp_path):
    # poisson2d N=5 has (N - 1)^2 = 16 parameters, as spring1d n=16: the count alone would accept it
    poisson = build_problem("poisson2d", {"N": 5})
    springs = build_problem("spring1d", {"n": 16})
    assert poisson.parameterization.n_params == springs.parameterization.n_params
    assert poisson.field_name == springs.field_name == "k"
    first = fit(poisson, {"name": "gauss_newton", "max_iter": 1}, run_dir=tmp_path / "poisson",
                options=QUIET)
    with pytest.raises(FitConfigError, match=r"another problem \(problem 'poisson2d' there, "
                                              r"'spring1d' here\)"):
        initial_theta(springs, tmp_path / "poisson")
    # the same problem with other settings (noise, another seed) starts from it
    again = build_problem("poisson2d", {"N": 5, "noise": 1e-3, "seed": 3})
    assert torch.equal(initial_theta(again, tmp_path / "poisson"), first.theta)
