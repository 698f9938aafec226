"""Split Bregman's settings (torchfit.solvers.split_bregman.settings): bad values are
named."""
from __future__ import annotations

import pytest

from torchfit.problems import Spring1D
from torchfit.solvers import SolverConfigError, SplitBregmanConfig, split_bregman


@pytest.mark.parametrize("config, match", [
    (SplitBregmanConfig(mu=0.0), "solver.mu"),
    (SplitBregmanConfig(mu=-1.0), "solver.mu"),
    (SplitBregmanConfig(beta=0.0), "solver.beta"),
    (SplitBregmanConfig(beta=-2.0), "solver.beta"),
    (SplitBregmanConfig(mu_rel=0.0), "solver.mu_rel"),
    (SplitBregmanConfig(growth=1.0), "solver.growth"),
    (SplitBregmanConfig(inner_solver="newton"), "solver.inner_solver"),
    (SplitBregmanConfig(power_iterations=0), "solver.power_iterations"),
    (SplitBregmanConfig(power_iterations=10 ** 12), r"solver.power_iterations must be in \[1, 1000\]"),
])
def test_bad_settings_are_named(config, match):
    problem = Spring1D(n=4)
    with pytest.raises(SolverConfigError, match=match):
        split_bregman(problem.residual(), problem.theta0, config,
                      D=problem.parameterization.difference_operator())
