"""The dense-Jacobian path: a residual with a one-pass ``jacobian``, the linearisation's
``jacobian()``/``use_dense()``, the solvers choosing it by size, exact resume."""
from __future__ import annotations

import math

import pytest
import torch

from torchfit.linalg import counting
from torchfit.problems import Spring1D, Spring1DConfig, has_forward_jacobian
from torchfit.solvers import (GaussNewton, GaussNewtonConfig, LevenbergMarquardt,
                              LevenbergMarquardtConfig, ResidualFunction, SolverConfigError,
                              SplitBregman, SplitBregmanConfig, gauss_newton, levenberg_marquardt,
                              split_bregman)
from torchfit.solvers.least_squares import DenseNormalEquations
from torchfit.solvers.stacked import CachedResidual, LinearResidual, StackedResidual

from helpers.solver_resume import check_resume, roundtrip, run_with_snapshots


class DenseSpring1D(Spring1D):
    """spring1d with the one-pass Jacobian (the equilibrium's ``jacobian``)."""

    def simulate_jacobian(self, stiffness, directions):
        return self.equilibrium.jacobian(stiffness, self.fixed_values, directions)[:, :, None, :]


def problem(n: int = 16, noise: float = 0.0) -> DenseSpring1D:
    p = DenseSpring1D(Spring1DConfig(n=n, noise=noise))
    p.equilibrium.clear_cache()
    return p


def start_of(p: Spring1D) -> torch.Tensor:
    g = torch.Generator().manual_seed(3)
    return p.theta0 + 0.3 * torch.randn(p.theta0.shape, generator=g, dtype=p.theta0.dtype)


def test_one_pass_jacobian_is_the_stack_of_jvps_and_costs_one_solve():
    p = problem()
    residual = p.residual()
    assert residual.jacobian is not None and has_forward_jacobian(p)
    assert Spring1D(n=4).residual().jacobian is None          # nothing opts in by default
    theta = start_of(p)
    lin = residual.linearize(theta)
    with counting() as count:
        J = lin.jacobian()
        assert lin.jacobian() is J                           # computed once, cached
    # a linear model: one shared factor, one solve with F n columns, no factorisation
    assert count.as_dict() == {"factorizations": 0, "solves": 1,
                               "rhs_columns": p.n_frames * 16, "analyses": 0}
    generic = ResidualFunction(p.forward, p.data).linearize(theta)
    assert generic.jacobian().shape == J.shape == (p.data.numel(), 16)
    assert float((J - generic.jacobian()).norm() / J.norm()) < 1e-12
    # Taylor: J predicts the change of the residual to second order
    v = torch.randn(16, dtype=theta.dtype, generator=torch.Generator().manual_seed(4))
    errors = [float(torch.linalg.vector_norm(residual.value(theta + h * v) - lin.r - h * (J @ v)))
              for h in (1e-2, 5e-3)]
    assert 3.5 < errors[0] / errors[1] < 4.5


def test_use_dense_makes_products_matrix_products_without_simulating():
    p = problem()
    calls = []

    def forward(theta):
        calls.append(1)
        return p.forward(theta)

    residual = ResidualFunction(forward, p.data, jacobian=p.forward_jacobian)
    lin = residual.linearize(start_of(p))
    v = torch.randn(16, dtype=lin.r.dtype)
    w = torch.randn(lin.r.numel(), dtype=lin.r.dtype)
    expected = (lin.jvp(v), lin.vjp(w))
    assert not lin.dense
    lin.use_dense()
    before = len(calls)
    with counting() as count:
        dense = (lin.jvp(v), lin.vjp(w))
    assert len(calls) == before and count.solves == 0 and lin.dense
    assert torch.allclose(dense[0], expected[0], rtol=1e-12, atol=1e-14)
    assert torch.allclose(dense[1], expected[1], rtol=1e-12, atol=1e-14)
    with pytest.raises(ValueError, match="shape"):
        ResidualFunction(p.forward, p.data, jacobian=lambda t: torch.zeros(3, 3)) \
            .linearize(p.theta0).jacobian()


def test_dense_normal_equations_match_cgls_with_the_gauge_projector():
    from torchfit.linalg import cgls
    g = torch.Generator().manual_seed(0)
    J = torch.randn(30, 8, generator=g)
    J[:, 0] = J[:, 1:].sum(dim=1)             # a null direction, as a gauge makes one
    r = torch.randn(30, generator=g)
    gauge = torch.ones(8) / math.sqrt(8)

    class Lin:
        theta = torch.zeros(8)

        def jacobian(self):
            return J

    def project(v):
        return v - torch.dot(gauge, v) * gauge

    normal = DenseNormalEquations(Lin(), project)
    for shift in (1e-3, 0.0):
        exact = normal.solve(-r, shift)
        ref = cgls(lambda v: J @ v, lambda w: J.T @ w, -r, 8, shift=shift, max_iter=200,
                   project=project, normal_rtol=1e-15)
        assert abs(float(torch.dot(gauge, exact.x))) < 1e-12
        assert torch.allclose(exact.x, ref.x, rtol=1e-8, atol=1e-10), shift
        assert torch.allclose(exact.Ax, J @ exact.x) and exact.stop_reason == "exact"


def test_dense_levenberg_marquardt_reaches_the_cg_answer_with_fewer_solves():
    results = {}
    for limit in (0, 1000):
        p = problem()
        config = LevenbergMarquardtConfig(dense_jacobian_max_params=limit, rtol=1e-10,
                                          gtol=1e-14, max_iter=60)
        results[limit] = levenberg_marquardt(p.residual(), start_of(p), config)
    cg, dense = results[0], results[1000]
    assert dense.converged            # (the CG run may end "stalled" at round-off)
    assert float((dense.theta - cg.theta).abs().max()) < 1e-6
    assert dense.solves < cg.solves / 3
    assert all(r.extra.get("dense_jacobian") == 1.0 for r in dense.history)
    assert all("dense_jacobian" not in r.extra for r in cg.history)
    assert all(r.cg_iterations == 0 for r in dense.history)
    # a trial point costs at most its forward solve (a linear model; none when the
    # simulator's cache has it), an accepted one also its Jacobian (one solve of F n
    # columns); no product costs a solve
    for before, after in zip(dense.history[:-1], dense.history[1:]):
        assert after.solves - before.solves <= (2 if after.accepted else 1)
        assert after.factorizations - before.factorizations <= 1


@pytest.mark.parametrize("limit, n", [(15, 16), (0, 16)])
def test_threshold_and_zero_keep_the_matrix_free_path(limit, n):
    p = problem(n)
    result = levenberg_marquardt(p.residual(), start_of(p),
                                 LevenbergMarquardtConfig(dense_jacobian_max_params=limit,
                                                          max_iter=2))
    assert all("dense_jacobian" not in r.extra for r in result.history)


def test_dense_gauss_newton_keeps_cgls_and_reaches_the_same_answer():
    results = {}
    for limit in (0, 1000):
        p = problem()
        results[limit] = gauss_newton(p.residual(), start_of(p), GaussNewtonConfig(
            dense_jacobian_max_params=limit, rtol=1e-12, gtol=1e-14, max_iter=40))
    cg, dense = results[0], results[1000]
    assert float((dense.theta - cg.theta).abs().max()) < 1e-6
    assert dense.history[-1].extra["dense_jacobian"] == 1.0 and dense.solves < cg.solves
    assert any(r.cg_iterations > 0 for r in dense.history[1:])   # still CGLS (REGINN)


def test_bad_threshold_is_named():
    for config in (GaussNewtonConfig(dense_jacobian_max_params=-1),
                   LevenbergMarquardtConfig(dense_jacobian_max_params=-1),
                   SplitBregmanConfig(dense_jacobian_max_params=-1)):
        with pytest.raises(SolverConfigError, match="solver.dense_jacobian_max_params"):
            config.validate()


def test_stacked_and_cached_residuals_provide_the_dense_jacobian():
    p = problem(8)
    model = CachedResidual(p.residual())
    D = p.parameterization.difference_operator()
    diff = LinearResidual(D, torch.ones(D.shape[0], dtype=torch.float64))
    stacked = StackedResidual([model, diff], [2.0, 3.0])
    assert stacked.jacobian is not None
    assert StackedResidual([CachedResidual(Spring1D(n=8).residual()), diff], [1, 1]).jacobian \
        is None
    theta = start_of(p)
    lin = stacked.linearize(theta)
    J = lin.jacobian()
    assert torch.allclose(J, stacked.jacobian(theta), atol=1e-14)
    v = torch.randn(8, dtype=theta.dtype)
    w = torch.randn(J.shape[0], dtype=theta.dtype)
    expected = (lin.jvp(v), lin.vjp(w))
    lin.use_dense()
    assert torch.allclose(lin.jvp(v), expected[0], atol=1e-12)
    assert torch.allclose(lin.vjp(w), expected[1], atol=1e-12)


@pytest.mark.parametrize("solver_class, config", [
    (LevenbergMarquardt, LevenbergMarquardtConfig(damping_init=1e-12, rtol=1e-10)),
    (LevenbergMarquardt, LevenbergMarquardtConfig(geodesic_acceleration=True,
                                                  damping_update="nielsen")),
    (GaussNewton, GaussNewtonConfig()),
], ids=["lm-rejections", "lm-geodesic", "gn"])
def test_dense_path_resumes_bit_for_bit(solver_class, config):
    p = problem(noise=1e-4)
    full, snapshots = run_with_snapshots(solver_class(config), p.residual(), start_of(p),
                                         {0, 1, 2, 4, 6})
    assert full.history[-1].extra["dense_jacobian"] == 1.0
    for k, (state, _) in snapshots.items():
        p.equilibrium.clear_cache()
        resumed = solver_class(config).solve(p.residual(), start_of(p), state=roundtrip(state))
        check_resume(full, resumed, k, counters=False)


def test_split_bregman_inner_solve_on_the_dense_jacobian():
    results = {}
    for limit in (0, 1000):
        p = problem(8, noise=1e-3)
        D = p.parameterization.difference_operator()
        config = SplitBregmanConfig(dense_jacobian_max_params=limit, max_iter=8)
        results[limit] = split_bregman(p.residual(), p.theta0, config, D=D)
    cg, dense = results[0], results[1000]
    assert dense.history[-1].extra["dense_jacobian"] == 1.0
    assert "dense_jacobian" not in cg.history[-1].extra
    assert dense.solves < cg.solves / 3
    # the same iterations (CGLS on matrix products instead of simulator products)
    assert dense.iterations == cg.iterations
    assert float((dense.theta - cg.theta).norm() / cg.theta.norm()) < 1e-6
    # resume on the dense path
    p = problem(8, noise=1e-3)
    D = p.parameterization.difference_operator()
    config = SplitBregmanConfig(max_iter=8)
    full, snapshots = run_with_snapshots(SplitBregman(config, D=D), p.residual(), p.theta0,
                                         {2, 5})
    for k, (state, _) in snapshots.items():
        p.equilibrium.clear_cache()
        resumed = SplitBregman(config, D=D).solve(p.residual(), p.theta0, state=roundtrip(state))
        check_resume(full, resumed, k, counters=False)
