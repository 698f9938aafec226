"""The linear spring chain: its residual is the gradient of its energy, its tangent the
Hessian, its parameter derivative that of autograd."""
import numpy as np
import torch
import torch.autograd.forward_ad as fwAD

from torchfit.linalg import counting
from torchfit.physics import Equilibrium, ScalarSpringNetwork


def random_springs(seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    edges = torch.tensor([[0, 1], [1, 2], [2, 3], [0, 2], [1, 3], [3, 4]])
    rest = torch.rand(6, generator=gen, dtype=torch.float64)
    forces = torch.randn(2, 5, generator=gen, dtype=torch.float64)
    return ScalarSpringNetwork(edges, rest, forces), gen


def test_param_derivative_matches_autograd_of_the_residual():
    model, gen = random_springs()
    x = torch.randn(2, 5, generator=gen, dtype=torch.float64)
    k = torch.rand(6, generator=gen, dtype=torch.float64) + 0.5
    jac = torch.autograd.functional.jacobian(lambda kk: model.residual(x, kk), k)  # (2, 5, 6)
    derivative = model.param_derivative(x, k)
    v = torch.randn(6, generator=gen, dtype=torch.float64)
    w = torch.randn(2, 5, generator=gen, dtype=torch.float64)
    assert torch.allclose(derivative.jvp(v), torch.einsum("fne,e->fn", jac, v), atol=1e-13)
    assert torch.allclose(derivative.vjp(w), torch.einsum("fne,fn->e", jac, w), atol=1e-13)


def test_equilibrium_gradients_with_param_derivative_match_finite_differences():
    model, gen = random_springs(1)
    eq = Equilibrium(model, torch.tensor([0]))
    k = (torch.rand(6, generator=gen, dtype=torch.float64) + 0.5).requires_grad_(True)
    fixed = torch.zeros(2, 1, dtype=torch.float64)
    g = torch.randn(2, 5, generator=gen, dtype=torch.float64)
    v = torch.randn(6, generator=gen, dtype=torch.float64)
    with counting() as count:
        x = eq(k, fixed)
        (grad,) = torch.autograd.grad(x, k, g)
    assert count.factorizations == 1 and count.solves == 2     # forward + adjoint
    eps = 1e-6
    with torch.no_grad():
        fd = (eq(k + eps * v, fixed) - eq(k - eps * v, fixed)) / (2 * eps)
    assert abs(float(torch.dot(grad, v)) - float((g * fd).sum())) < 1e-7
    with fwAD.dual_level():   # forward mode, as the solvers' J v
        tangent = fwAD.unpack_dual(eq(fwAD.make_dual(k.detach(), v), fixed)).tangent
    assert torch.allclose(tangent, fd, atol=1e-7)


def test_spring_residual_is_gradient_of_energy():
    n = 5
    nodes = torch.arange(n + 1)
    model = ScalarSpringNetwork(torch.stack([nodes[:-1], nodes[1:]], 1), torch.full((n,), 0.2),
                          torch.rand(2, n + 1))
    x = torch.rand(2, n + 1, requires_grad=True)
    k = torch.rand(n) + 1
    (grad,) = torch.autograd.grad(model.energy(x, k).sum(), x)
    assert torch.allclose(grad, model.residual(x, k))
    dense = model.tangent_pattern.to_scipy(
        model.tangent_pattern.assemble(model.tangent_values(x, k))[0]).toarray()
    hessian = torch.autograd.functional.hessian(lambda y: model.energy(y[None], k)[0], x[0].detach())
    assert np.allclose(dense, hessian.numpy())
