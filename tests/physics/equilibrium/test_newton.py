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
