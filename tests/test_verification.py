"""Derivative verification (torchfit.verification): Taylor, dot-product and FD checks."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from torchfit.problems import Spring1D
from torchfit.residual import ResidualFunction
from torchfit.verification import (dot_product_test, finite_difference_test, format_report,
                                   random_direction, taylor_test, verify)

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def spring():
    problem = Spring1D()
    generator = torch.Generator().manual_seed(1234)
    theta = problem.theta0 + 0.1 * torch.randn(problem.theta0.shape, generator=generator,
                                               dtype=torch.float64)
    return problem, problem.residual(), theta


class _WrongLinearization:
    def __init__(self, lin, jvp_scale: float, vjp_scale: float) -> None:
        self._lin, self._jvp_scale, self._vjp_scale = lin, jvp_scale, vjp_scale
        self.r, self.theta = lin.r, lin.theta

    def jvp(self, v):
        return self._jvp_scale * self._lin.jvp(v)

    def vjp(self, w):
        return self._vjp_scale * self._lin.vjp(w)


class WrongResidual:
    """A residual whose ``J v`` and/or ``J^T w`` are scaled (deliberately wrong)."""

    def __init__(self, residual: ResidualFunction, jvp_scale: float = 1.0,
                 vjp_scale: float = 1.0) -> None:
        self._residual, self.data = residual, residual.data
        self._jvp_scale, self._vjp_scale = jvp_scale, vjp_scale

    def value(self, theta):
        return self._residual.value(theta)

    def linearize(self, theta):
        return _WrongLinearization(self._residual.linearize(theta), self._jvp_scale,
                                   self._vjp_scale)


# -- spring1d: the checks pass ------------------------------------------------------------
def test_spring1d_passes(spring):
    _, residual, theta = spring
    report = verify(residual, theta, seed=0)
    assert not report.taylor.linear
    assert abs(report.taylor.rate - 2.0) <= 0.05
    assert report.dot.rel_error <= 1e-10
    assert report.fd.rel_error <= 1e-6
    assert report.passed and report.taylor_passed and report.dot_passed and report.fd_passed
    # The automatic window: a long stable run, large-end and round-off steps excluded.
    lo, hi = report.taylor.window
    assert hi - lo >= 8
    assert all(abs(r - 2.0) <= 0.05 for r in report.taylor.window_rates)
    assert any(report.taylor.roundoff), "the step range should reach round-off"
    assert not any(report.taylor.roundoff[lo:hi + 1])

    d = report.to_dict()
    for key in ("taylor_rate", "dot_product_rel_error", "fd_rel_error", "passed",
                "taylor_passed", "dot_product_passed", "fd_passed", "taylor"):
        assert key in d
    assert d["taylor_rate"] == pytest.approx(report.taylor.rate)
    assert len(d["taylor"]["steps"]) == len(d["taylor"]["remainders"])
    json.dumps(d, allow_nan=False)

    text = format_report(report)
    assert "Taylor rate" in text and "PASSED" in text
    assert len(text.splitlines()) >= len(report.taylor.steps)


def test_steps_are_automatic_and_scale_free(spring):
    """The step range follows ||theta|| and ||v||: the same rate for a scaled direction."""
    _, residual, theta = spring
    lin = residual.linearize(theta)
    v = random_direction(theta.numel(), torch.Generator().manual_seed(5), theta)
    a = taylor_test(residual, theta, v, lin=lin)
    b = taylor_test(residual, theta, 1e3 * v, lin=lin)
    assert a.steps[0] * 1.0 == pytest.approx(b.steps[0] * 1e3)
    assert a.steps[0] * float(v.norm()) == pytest.approx(0.1 * float(theta.norm()))
    assert abs(a.rate - 2) <= 0.05 and abs(b.rate - 2) <= 0.05


def test_first_order_remainder_has_rate_one(spring):
    """Without the J v term the remainder is O(h): the test can tell the orders apart."""
    _, residual, theta = spring
    v = random_direction(theta.numel(), torch.Generator().manual_seed(1), theta)
    first = taylor_test(residual, theta, v, order=1)
    assert abs(first.rate - 1.0) <= 0.05
    assert abs(first.rate - 2.0) > 0.05          # would fail a second-order check
    assert first.expected == 1.0


# -- the checks can fail --------------------------------------------------------------------
def test_wrong_jvp_fails(spring):
    _, residual, theta = spring
    report = verify(WrongResidual(residual, jvp_scale=1.01), theta, seed=0)
    assert abs(report.taylor.rate - 1.0) <= 0.1
    assert not report.taylor_passed
    assert not report.fd_passed
    assert report.fd.rel_error == pytest.approx(0.01 / 1.01, rel=1e-3)
    assert not report.passed
    assert report.to_dict()["passed"] is False
    assert "FAILED" in format_report(report)


def test_vjp_not_transpose_fails(spring):
    _, residual, theta = spring
    report = verify(WrongResidual(residual, vjp_scale=1.0 + 1e-6), theta, seed=0)
    assert report.dot.rel_error == pytest.approx(1e-6, rel=1e-3)
    assert not report.dot_passed
    assert report.taylor_passed and report.fd_passed      # J v itself is right
    assert not report.passed


def test_dot_product_test_direct(spring):
    _, residual, theta = spring
    lin = residual.linearize(theta)
    g = torch.Generator().manual_seed(2)
    v = random_direction(theta.numel(), g, theta)
    w = random_direction(lin.r.numel(), g, lin.r)
    assert dot_product_test(lin, v, w).rel_error <= 1e-12
    fd = finite_difference_test(residual, lin, v)
    assert fd.rel_error <= 1e-6 and fd.jv_norm > 0


# -- linear residuals ---------------------------------------------------------------------
def _linear_residual(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(30, 10, generator=g, dtype=torch.float64)
    data = torch.randn(30, generator=g, dtype=torch.float64)
    return ResidualFunction(lambda th: a @ th, data), g


@pytest.mark.parametrize("at_zero", [False, True])
def test_linear_residual_is_reported_as_linear(at_zero):
    residual, g = _linear_residual()
    theta = torch.zeros(10, dtype=torch.float64) if at_zero else torch.randn(
        10, generator=g, dtype=torch.float64)
    report = verify(residual, theta, seed=3)
    assert report.taylor.linear
    assert math.isnan(report.taylor.rate)
    assert report.taylor_passed and report.passed
    assert report.to_dict()["taylor_rate"] is None
    assert report.to_dict()["taylor_linear"] is True
    assert "linear" in format_report(report)


def test_linear_residual_with_wrong_jvp_is_not_linear():
    residual, g = _linear_residual(1)
    theta = torch.randn(10, generator=g, dtype=torch.float64)
    report = verify(WrongResidual(residual, jvp_scale=1.01), theta)
    assert not report.taylor.linear
    assert abs(report.taylor.rate - 1.0) <= 0.05
    assert not report.passed


def test_bad_arguments():
    residual, _ = _linear_residual()
    theta = torch.ones(10, dtype=torch.float64)
    with pytest.raises(ValueError, match="direction"):
        taylor_test(residual, theta, torch.zeros(10, dtype=torch.float64))
    with pytest.raises(ValueError, match="taylor_tol"):
        verify(residual, theta, taylor_tol=-1)


def test_default_fd_tolerance_follows_the_simulation_accuracy():
    """Exact simulations keep 1e-6; one solved to a tolerance ``a`` gets what a central
    difference can resolve, ``100 a^(2/3)``; an explicit tolerance wins."""
    from torchfit.verification import default_fd_tol, verify

    data = torch.zeros(3, dtype=torch.float64)
    exact = ResidualFunction(lambda t: t, data)
    newton = ResidualFunction(lambda t: t, data, accuracy=1e-10)
    assert default_fd_tol(exact) == 1e-6
    assert default_fd_tol(newton) == pytest.approx(100 * 1e-10 ** (2 / 3))
    assert default_fd_tol(ResidualFunction(lambda t: t, data, accuracy=1e-20)) == 1e-6
    theta = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    assert verify(newton, theta).fd_tol == pytest.approx(2.154e-5, rel=1e-3)
    assert verify(newton, theta, fd_tol=1e-7).fd_tol == 1e-7


class _SolverFloorResidual:
    """A quadratic residual observed through an iterative solve: away from ``theta0`` every
    value carries a solver error of about ``floor`` that shrinks only slowly with the step
    (the 2-frame stable neo-Hookean arm: remainders 5.8e-7 at rate 2 down to 6.8e-10, then
    2.9e-10 for 14 halvings, each a little lower than the last)."""

    def __init__(self, floor: float, theta0: torch.Tensor) -> None:
        g = torch.Generator().manual_seed(5)
        self.a = torch.randn(40, theta0.numel(), generator=g, dtype=torch.float64)
        self.u = torch.randn(40, generator=g, dtype=torch.float64)
        self.u /= torch.linalg.vector_norm(self.u)
        self.data = torch.randn(40, generator=g, dtype=torch.float64)
        self.floor, self.theta0 = floor, theta0

    def _exact(self, theta):
        z = self.a @ theta
        return z + 0.5 * z.square() - self.data

    def value(self, theta):
        distance = float(torch.linalg.vector_norm(theta - self.theta0))
        if distance == 0:
            return self._exact(theta)
        # 0.05 % lower per decade of the step: sinking, but far slower than Taylor's h^2
        error = self.floor * (1.0 + 5e-4 * math.log10(distance))
        return self._exact(theta) + error * self.u

    def linearize(self, theta):
        residual = ResidualFunction(lambda th: self.a @ th + 0.5 * (self.a @ th).square(),
                                    self.data)
        return residual.linearize(theta)


def test_a_slowly_sinking_solver_floor_is_not_taken_for_the_asymptotic_window():
    theta = torch.full((6,), 0.1, dtype=torch.float64)
    residual = _SolverFloorResidual(3e-10, theta)
    direction = torch.linspace(-1.0, 1.0, 6, dtype=torch.float64)
    result = taylor_test(residual, theta, direction, relative_step=0.003)
    assert abs(result.rate - 2.0) <= 0.05, result.rates
    assert result.window[1] <= 12          # the window ends before the floor
