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
