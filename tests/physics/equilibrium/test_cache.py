"""The solution cache: factorisations kept while a graph lives, warm starts from the point
derivatives were taken at, independent solves that never seed."""
import pytest
import torch

from torchfit.linalg import counting
from torchfit.physics import Equilibrium, NewtonOptions

from helpers.equilibrium_models import DoubleWell


def test_live_graph_keeps_its_factorization_after_other_points():
    """A linearisation's J v stays factorisation-free however many points come between."""
    from torchfit.problems import Spring1D

    problem = Spring1D(n=16)
    residual = problem.residual()
    lin = residual.linearize(problem.theta0)
    for shift in (0.1, 0.2, 0.3):               # more points than the cache holds
        residual.value(problem.theta0 + shift)
    with counting() as count:
        lin.jvp(torch.randn(16))
        lin.vjp(torch.randn(problem.data.numel()))
    assert count.factorizations == 0 and count.solves == 2
    del lin
    import gc
    gc.collect()
    for shift in (0.4, 0.5):                    # push it out of the LRU cache too
        residual.value(problem.theta0 + shift)
    with counting() as count:                   # graph gone: the point is solved afresh
        residual.value(problem.theta0)
    assert count.factorizations == 1


@pytest.mark.parametrize("derivative_taken", [True, False])
def test_warm_start_comes_from_the_point_derivatives_were_taken_at(derivative_taken):
    """A solver linearises at a point, tries a far one (rejected) and then a near one: the
    near one starts from the linearisation point and stays in its well. Without a
    linearisation the most recent solution is the start (the other well)."""
    eq = Equilibrium(DoubleWell(), torch.tensor([0]), newton=NewtonOptions(rtol=1e-12))
    fixed = torch.zeros(1, 1, dtype=torch.float64)
    start = torch.tensor([[0.0, 1.2]], dtype=torch.float64)
    a = torch.tensor([0.0], dtype=torch.float64, requires_grad=True)
    x = eq(a, fixed, start)
    assert abs(float(x[0, 1].detach()) - 1.0) < 1e-10
    if derivative_taken:
        (slope,) = torch.autograd.grad(x[0, 1], a)     # dx/da = 1 / (3 x^2 - 1) = 0.5
        assert abs(float(slope) - 0.5) < 1e-10
    far = eq(torch.tensor([-1.0], dtype=torch.float64), fixed, start)
    assert float(far[0, 1]) < -1.3                     # the only equilibrium there
    near = eq(torch.tensor([0.05], dtype=torch.float64), fixed, start)
    assert eq.last_warm_started
    if derivative_taken:
        assert abs(float(near[0, 1]) - 1.0) < 0.05     # the linearisation point's well
    else:
        assert abs(float(near[0, 1]) + 1.0) < 0.05     # the rejected trial's well


def test_an_independent_solve_starts_cold_and_seeds_no_warm_start():
    """A solve inside ``independent()`` (a synthetic target, a baseline) neither starts from
    an earlier solution nor becomes or displaces the start of a later one: the solver's
    next solve is bit for bit what it is without the independent block (so a resumed run,
    whose baseline is simulated at another moment, starts where the uninterrupted one
    did). Found again at the same parameters outside it, it is the solver's point and seeds
    as before."""
    def solver_sequence(with_independent_block):
        eq = Equilibrium(DoubleWell(), torch.tensor([0]), newton=NewtonOptions(rtol=1e-12))
        eq(torch.tensor([-1.0], dtype=torch.float64), fixed, left)     # the only well: -1.32
        if with_independent_block:
            with eq.independent():
                cold = eq(torch.tensor([0.05], dtype=torch.float64), fixed, start)
                assert not eq.last_warm_started and float(cold[0, 1]) > 0.9  # start's well
                far = eq(torch.tensor([-0.9], dtype=torch.float64), fixed, left)
                assert float(far[0, 1]) < -1.2
                eq(torch.tensor([-1.0], dtype=torch.float64), fixed, left)   # a cached one
        near = eq(torch.tensor([0.1], dtype=torch.float64), fixed, start)
        return eq, near, list(eq.last_newton_iterations), eq.last_warm_started

    fixed = torch.zeros(1, 1, dtype=torch.float64)
    start = torch.tensor([[0.0, 1.2]], dtype=torch.float64)
    left = -start
    eq, near, iterations, warm = solver_sequence(True)
    _, alone, alone_iterations, alone_warm = solver_sequence(False)
    # from the seed a = -1 (not from a = -0.9, the most recent, nor cold from the start)
    assert warm and alone_warm and float(near[0, 1]) < -0.9
    assert torch.equal(near, alone) and iterations == alone_iterations
    again = eq(torch.tensor([-0.9], dtype=torch.float64), fixed, left)    # cached: promoted
    assert float(again[0, 1]) < -1.2
    eq(torch.tensor([0.0], dtype=torch.float64), fixed, start)
    assert eq.last_warm_started                      # from a = -0.9 now: the solver's seed
    assert float(eq(torch.tensor([0.0], dtype=torch.float64), fixed, start)[0, 1]) < -1.0
