"""Helpers of the solver tests: residuals that record where they are linearised or fail
there, a count of distinct parameter vectors, and a timed fit with the parameterisation's
operators."""
from __future__ import annotations

import math
import time

import torch

from torchfit.solvers import ResidualFunction, gauss_newton, split_bregman


def distinct(points: list[torch.Tensor]) -> int:
    """How many different parameter vectors ``points`` holds (``torch.equal``)."""
    unique: list[torch.Tensor] = []
    for p in points:
        if not any(torch.equal(p, q) for q in unique):
            unique.append(p)
    return len(unique)


def timed_fit(problem, solver, config=None):
    """``(result, metrics, seconds)`` of Gauss-Newton or split Bregman on ``problem``, with
    the parameterisation's ``D`` (and TV groups)."""
    D = problem.parameterization.difference_operator()
    start = time.perf_counter()
    if solver is gauss_newton:
        result = gauss_newton(problem.residual(), problem.theta0, config, D=D)
    else:
        result = split_bregman(problem.residual(), problem.theta0, config, D=D,
                               groups=problem.parameterization.difference_groups())
    return result, problem.metrics(result.theta), time.perf_counter() - start


class CountingResidual(ResidualFunction):
    """Records every parameter vector at which the residual is linearised."""

    def __init__(self, inner: ResidualFunction) -> None:
        super().__init__(inner.forward, inner.data, inner.noise_level, inner.gauge)
        self.points: list[torch.Tensor] = []

    def linearize(self, theta):
        self.points.append(theta.detach().clone())
        return super().linearize(theta)


class FlakyResidual(ResidualFunction):
    """The simulation 'fails' (NaN residual) at the linearisations ``start <= count < stop``."""

    def __init__(self, inner: ResidualFunction, start: int, stop: int) -> None:
        super().__init__(inner.forward, inner.data, inner.noise_level, inner.gauge)
        self.count, self.start, self.stop = 0, start, stop

    def linearize(self, theta):
        lin = super().linearize(theta)
        self.count += 1
        if self.start <= self.count < self.stop:
            lin.r = torch.full_like(lin.r, math.nan)
            lin.norm = math.nan
        return lin


def underestimated_noise(problem, factor: float = 0.8):
    """The problem's residual with a noise level ``factor`` times too small: no stage can
    reach ``tau delta``, so the misfits of later stages only creep down."""
    def residual():
        problem.equilibrium.clear_cache()
        r = problem.residual()
        r.noise_level = factor * r.noise_level
        return r
    return residual
