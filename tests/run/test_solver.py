"""The solver of a run: what its registry entry asks of the parameterisation."""
from __future__ import annotations

import pytest

from torchfit.problems import build_problem
from torchfit.run import build_solver



def test_solvers_get_what_their_registry_entry_asks_of_the_parameterisation():
    class NoDifferences:
        n_params = 3

    class Custom:                      # only what build_solver looks at
        name = "custom"
        parameterization = NoDifferences()

    with pytest.raises(ValueError, match="split_bregman needs the difference operator D.*custom"):
        build_solver(Custom(), "split_bregman")
    assert build_solver(Custom(), "gauss_newton").config.name == "gauss_newton"
    with pytest.raises(ValueError, match="levenberg_marquardt needs the difference operator D"):
        build_solver(Custom(), {"name": "levenberg_marquardt", "preconditioner": "difference"})
    spring = build_problem("spring1d", {"n": 6})
    solver = build_solver(spring, {"name": "levenberg_marquardt", "preconditioner": "difference"})
    assert solver.D.shape == (5, 6)
    with pytest.raises(ValueError, match="no difference operator"):
        build_solver(build_problem("spring1d", {"n": 1}), "split_bregman")
