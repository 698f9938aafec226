"""The solver of a run: what its registry entry asks of the parameterisation."""
from __future__ import annotations

import pytest

from torchfit.problems import build_problem
from torchfit.run import FitOptions, build_solver, fit

def test_solvers_get_what_their_registry_entry_asks_of_the_parameterisation():
    assert build_solver(build_problem("spring1d", {"n": 6}), "gauss_newton").config.name \
        == "gauss_newton"
    spring = build_problem("spring1d", {"n": 6})
    solver = build_solver(spring, {"name": "levenberg_marquardt", "preconditioner": "difference"})
    assert solver.D.shape == (5, 6)
    with pytest.raises(ValueError, match="no difference operator"):
        build_solver(build_problem("spring1d", {"n": 1}), "split_bregman")


def test_fit_hands_D_to_the_auto_preconditioner():
    """Gauss-Newton's ``preconditioner=auto`` takes the parameterisation's D where it has one."""
    result = fit(build_problem("poisson2d", {"N": 12}), "gauss_newton",
                 options=FitOptions(progress=False))
    assert result.history[0]["preconditioned"] == 1.0


def test_the_problems_bounds_reach_the_solver_and_a_start_outside_is_refused(tmp_path):
    """``InverseProblem.theta_bounds`` goes to ``Solver.set_bounds``; the fit keeps them
    (spring1d's stiffnesses capped at 1.2x the start) and an ``init=`` outside them is one
    line before anything is written."""
    import torch

    from torchfit.run import FitConfigError
    spring = build_problem("spring1d", {"n": 6})
    lower = spring.theta0 - 10.0
    upper = spring.theta0 + 0.18
    spring.theta_bounds = lambda: (lower, upper)
    solver = build_solver(spring, "levenberg_marquardt")
    assert torch.equal(solver.bounds.upper, upper)
    result = fit(spring, "levenberg_marquardt", options=FitOptions(progress=False))
    assert bool((result.theta <= upper).all())
    assert result.history[-1]["at_upper_bound"] >= 1
    with pytest.raises(FitConfigError, match="init=.*lies outside the problem's bounds") as err:
        fit(spring, "levenberg_marquardt", run_dir=tmp_path / "run", init=upper + 1.0,
            options=FitOptions(progress=False))
    assert "\n" not in str(err.value)
    assert not (tmp_path / "run").exists()
