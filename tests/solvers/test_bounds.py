"""Bounds on theta (torchfit.solvers.bounds): the box is never left, an active bound is
respected while the free parameters converge to the constrained minimiser, bad bounds and
solvers without bounds are refused."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import lsq_linear

from torchfit.params.parameterization import chain_edges, per_element
from torchfit.solvers import (GaussNewton, GaussNewtonConfig, LevenbergMarquardt,
                              LevenbergMarquardtConfig, ResidualFunction, Solver, SolverConfig,
                              SolverConfigError, SplitBregmanConfig)
from torchfit.solvers.bounds import ThetaBounds, box_scale
from torchfit.solvers.split_bregman.solver import SplitBregman

torch.set_default_dtype(torch.float64)

SOLVERS = [
    (LevenbergMarquardt, LevenbergMarquardtConfig(max_iter=200, dense_jacobian_max_params=0,
                                                  gtol=1e-8, rtol=0.0)),
    (LevenbergMarquardt, LevenbergMarquardtConfig(max_iter=200, gtol=1e-8, rtol=0.0)),
    (LevenbergMarquardt, LevenbergMarquardtConfig(max_iter=200, gtol=1e-8, rtol=0.0,
                                                  max_step=0.3)),
    (GaussNewton, GaussNewtonConfig(max_iter=200, gtol=1e-8, rtol=0.0, eta_max=0.01,
                                    preconditioner="none")),
]
IDS = ["lm-cgls", "lm-dense", "lm-max-step", "gn"]


def linear_problem(seed: int = 0, m: int = 30, n: int = 8):
    """``r = A theta - b`` whose unconstrained minimiser leaves ``[-1, 1]^n`` on several
    parameters; the box-constrained minimiser from scipy's ``lsq_linear``."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((m, n))
    x_free = np.linspace(-3.0, 3.0, n)
    b = A @ x_free + 0.1 * rng.standard_normal(m)
    lower, upper = -np.ones(n), np.ones(n)
    reference = lsq_linear(A, b, bounds=(lower, upper), tol=1e-14, method="bvls").x
    A_t = torch.from_numpy(A)
    residual = ResidualFunction(lambda theta: A_t @ theta, torch.from_numpy(b),
                                jacobian=lambda theta: A_t.clone())
    return residual, torch.from_numpy(lower), torch.from_numpy(upper), reference


@pytest.mark.parametrize("solver_class,config", SOLVERS, ids=IDS)
def test_bounded_solver_reaches_the_constrained_minimiser_and_never_leaves_the_box(
        solver_class, config):
    residual, lower, upper, reference = linear_problem()
    solver = solver_class(config)
    solver.set_bounds(lower, upper)
    records = []
    result = solver.solve(residual, torch.zeros(8), [records.append])
    for record in records:
        assert bool((record.theta >= lower).all() and (record.theta <= upper).all())
    # several bounds bind at the answer (the free minimiser spans [-3, 3]) ...
    on_bound = np.isclose(np.abs(reference), 1.0)
    assert on_bound.sum() >= 4 and (~on_bound).sum() >= 2
    # ... they are met exactly, and the free parameters converge to scipy's minimiser
    assert np.abs(result.theta.numpy() - reference).max() < 1e-7
    assert result.converged
    assert records[-1].extra["at_lower_bound"] + records[-1].extra["at_upper_bound"] \
        == on_bound.sum()


def test_unbounded_run_is_unchanged_by_infinite_bounds():
    """Bounds that never bind give the unbounded iterates bit for bit (the same products)."""
    residual, _, _, _ = linear_problem(seed=1)
    config = LevenbergMarquardtConfig(max_iter=6, max_step=0.5)
    plain = LevenbergMarquardt(config).solve(residual, torch.zeros(8))
    bounded = LevenbergMarquardt(config)
    bounded.set_bounds(torch.full((8,), -torch.inf), torch.full((8,), torch.inf))
    boxed = bounded.solve(residual, torch.zeros(8))
    assert torch.equal(plain.theta, boxed.theta)


def test_gauge_and_bounds_steps_stay_orthogonal_to_the_gauge():
    """With a gauge (scale-free residual) the projector keeps the active parameters fixed
    and the step orthogonal to the gauge: the free parameters' sum is unchanged."""
    n = 6
    ones = torch.ones(n) / n ** 0.5
    target = torch.tensor([2.0, -2.0, 0.5, -0.5, 0.2, -0.2])

    def forward(theta):       # depends on theta only through theta - mean(theta)
        return theta - theta.mean()
    residual = ResidualFunction(forward, target - target.mean(), gauge=lambda theta: ones)
    solver = LevenbergMarquardt(LevenbergMarquardtConfig(max_iter=50, rtol=0.0, gtol=1e-12))
    solver.set_bounds(torch.full((n,), -1.0), torch.full((n,), 1.0))
    result = solver.solve(residual, torch.zeros(n))
    theta = result.theta
    assert float(theta.abs().max()) <= 1.0
    assert abs(float(theta.sum())) < 1e-12             # every step orthogonal to the gauge
    assert theta[0] == 1.0 and theta[1] == -1.0          # the bounds that bind
    assert torch.allclose(theta[2:], target[2:], atol=1e-8)


@pytest.mark.parametrize("lower,upper,words", [
    ([0.0, 1.0], [1.0, 1.0], "lower >= upper at parameter 1"),
    ([0.0], [1.0, 2.0], "lower has 1 entries, upper 2"),
])
def test_bad_bounds_are_refused(lower, upper, words):
    with pytest.raises(SolverConfigError, match=words):
        ThetaBounds(torch.tensor(lower), torch.tensor(upper))


def test_start_outside_the_box_is_refused():
    residual, lower, upper, _ = linear_problem()
    solver = LevenbergMarquardt()
    solver.set_bounds(lower, upper)
    with pytest.raises(SolverConfigError, match="parameter 3 is 2.0, outside"):
        solver.solve(residual, torch.tensor([0, 0, 0, 2.0, 0, 0, 0, 0]))


class NoBounds(Solver):
    """A solver that cannot keep bounds (the base class's refusal)."""

    config_class = SolverConfig

    def start(self, theta0):
        raise NotImplementedError

    def step(self):
        raise NotImplementedError

    def _get_state(self):
        return {}

    def _set_state(self, state):
        pass

    def resume(self):
        pass

    @property
    def theta(self):
        return torch.zeros(1)


def test_solvers_without_bounds_refuse_in_one_line():
    with pytest.raises(SolverConfigError, match="solver=solver cannot keep") as err:
        NoBounds().set_bounds(torch.zeros(2), torch.ones(2))
    assert "\n" not in str(err.value)
    geodesic = LevenbergMarquardt(LevenbergMarquardtConfig(geodesic_acceleration=True))
    with pytest.raises(SolverConfigError, match="geodesic_acceleration"):
        geodesic.set_bounds(torch.zeros(2), torch.ones(2))


def test_split_bregman_keeps_the_bounds_through_its_inner_solve():
    """Denoising ``theta ~ y`` with a little TV and ``0 <= theta <= 1``: every iterate in the
    box, and the answer near ``clip(y, 0, 1)`` (the TV weight is small)."""
    n = 12
    y = torch.linspace(-0.6, 1.6, n)
    residual = ResidualFunction(lambda theta: theta.clone(), y,
                                jacobian=lambda theta: torch.eye(n))
    D = per_element(n, chain_edges(n)).difference_operator()
    solver = SplitBregman(SplitBregmanConfig(mu=1e4, max_iter=30), D=D)
    solver.set_bounds(torch.zeros(n), torch.ones(n))
    records = []
    result = solver.solve(residual, torch.full((n,), 0.5), [records.append])
    assert all(float(r.theta.min()) >= 0.0 and float(r.theta.max()) <= 1.0 for r in records)
    assert float((result.theta - y.clamp(0.0, 1.0)).abs().max()) < 0.02
    assert int((result.theta <= 1e-6).sum()) >= 3 and int((result.theta >= 1.0 - 1e-6).sum()) >= 3


def test_active_set_and_box_scale():
    bounds = ThetaBounds(torch.tensor([0.0, 0.0, 0.0]), torch.tensor([1.0, 1.0, 1.0]))
    theta = torch.tensor([0.0, 1.0, 0.0])
    gradient = torch.tensor([1.0, -1.0, -1.0])   # -g: outward, outward, inward
    assert bounds.active(theta, gradient).tolist() == [True, True, False]
    lo, hi = bounds.step_box(theta, gradient, max_step=0.5)
    assert lo.tolist() == [0.0, 0.0, 0.0] and hi.tolist() == [0.0, 0.0, 0.5]
    assert box_scale(torch.tensor([0.0, 0.0, 2.0]), (lo, hi)) == 0.25
