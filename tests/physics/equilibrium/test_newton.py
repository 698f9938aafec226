"""Newton on the free dofs and the forward solve: iterations and factorisations counted, a
linear model in one factorisation, failures named."""
import numpy as np
import pytest
import torch

from torchfit.linalg import counting
from torchfit.physics import Equilibrium, NewtonConvergenceError, NewtonOptions, ScalarSpringNetwork

from helpers.equilibrium_models import make_hardening


def test_newton_solves_nonlinear_model_and_counts_factorizations():
    model, eq, fixed = make_hardening()
    k = torch.rand(12) + 1.0
    with counting() as count:
        x = eq(k, fixed)
    assert model.residual(x, k)[:, 1:].abs().max() < 1e-12
    iterations = sum(eq.last_newton_iterations)
    # one factorisation per frame and Newton iteration, plus one per frame at the solution
    assert count.factorizations == iterations + 3


def test_linear_chain_one_factorization_for_all_frames(vectors_dir):
    data = np.load(vectors_dir / "spring1d_n64.npz")
    n = 64
    external = torch.full((3, n + 1), float(data["gravity"]) / n)
    external[:, n] += torch.from_numpy(data["loads"])
    nodes = torch.arange(n + 1)
    model = ScalarSpringNetwork(torch.stack([nodes[:-1], nodes[1:]], 1), torch.full((n,), 1.0 / n),
                          external)
    eq = Equilibrium(model, torch.tensor([0]))
    with counting() as count:
        x = eq(torch.from_numpy(data["k"]), torch.zeros(3, 1))
    assert count.factorizations == 1 and count.solves == 1
    np.testing.assert_allclose(x.numpy(), data["positions"], rtol=0, atol=1e-10)


def test_newton_failure_names_frame_and_residual():
    model, _, fixed = make_hardening()
    eq = Equilibrium(model, torch.tensor([0]), newton=NewtonOptions(max_iter=1, rtol=1e-14))
    with pytest.raises(NewtonConvergenceError, match=r"frame \d+: residual norm"):
        eq(torch.rand(12) + 1.0, fixed)


def test_residual_at_its_roundoff_floor_is_converged():
    """A chain held at x = 1e6 m cannot bring its residual below the rounding error of
    evaluating it (about eps |K| |x|, here about 1e-7 of a force of order 1): asked for
    rtol 1e-30 Newton used to fail ("its residual stopped decreasing"); it now accepts the
    equilibrium within (n_row + 1) eps ||(|K| |x|)_free|| and no sooner."""
    model = make_hardening()[0]
    eq = Equilibrium(model, torch.tensor([0]), newton=NewtonOptions(rtol=1e-30, atol=0.0))
    k = torch.linspace(1.0, 2.0, 12, dtype=torch.float64)
    fixed = torch.full((3, 1), 1e6, dtype=torch.float64)
    x = eq(k, fixed)
    free_residual = torch.linalg.vector_norm(model.residual(x, k)[:, 1:], dim=1)
    floor = eq.solver.roundoff_floor(x, k)
    # the floor: 4 entries at most per row (3 + 1) x eps x ||(|K| |x|)_free||, with |K| |x|
    # about 2 k (1 + 3 c s^2) 1e6 per dof: of order 1e-8 here, far above atol = 0
    tangent = model.tangent_pattern.assemble(model.tangent_values(x, k)).abs()
    expected = 4 * torch.finfo(torch.float64).eps * torch.linalg.vector_norm(
        model.tangent_pattern.matvec(tangent, x.abs())[:, 1:], dim=1)
    torch.testing.assert_close(floor, expected, rtol=1e-12, atol=0.0)
    assert bool((floor > 1e-9).all()) and bool((floor < 1e-5).all())
    assert bool((free_residual <= floor).all())
    # the same equilibrium as the chain at the origin, shifted (to the floor's accuracy)
    x_origin = eq(k, torch.zeros(3, 1, dtype=torch.float64))
    torch.testing.assert_close(x - 1e6, x_origin, rtol=0.0, atol=1e-8)


def test_unconverged_residual_above_the_floor_still_fails():
    """The floor accepts round-off, not a Newton cut short: one iteration from the rest
    shape leaves a residual far above it."""
    model = make_hardening()[0]
    eq = Equilibrium(model, torch.tensor([0]), newton=NewtonOptions(max_iter=1, rtol=1e-30,
                                                                    atol=0.0))
    with pytest.raises(NewtonConvergenceError, match="residual norm"):
        eq(torch.linspace(1.0, 2.0, 12, dtype=torch.float64),
           torch.full((3, 1), 1e6, dtype=torch.float64))
