"""The implicit-function adjoint (the autograd Function): gradients and jvps against finite
differences, with respect to the parameters and the Dirichlet values, reusing the forward's
factorisation."""
import pytest
import torch

from torchfit.linalg import counting
from torchfit.physics import Equilibrium

from helpers.equilibrium_models import make_hardening
from helpers.linear_system import MatrixModel, chain_pattern


def test_nonlinear_adjoint_and_jvp_match_finite_differences():
    _, eq, fixed = make_hardening()
    k = (torch.rand(12) + 1.0).requires_grad_()
    assert torch.autograd.gradcheck(lambda k: eq(k, fixed), (k,), atol=1e-7)
    assert torch.autograd.gradcheck(lambda k: eq(k, fixed), (k,), check_forward_ad=True,
                                    check_backward_ad=False, check_undefined_grad=False,
                                    check_batched_grad=False, atol=1e-7)


def test_dirichlet_values_are_differentiable():
    _, eq, _ = make_hardening(6)
    k = torch.rand(6) + 1.0
    fixed = torch.tensor([[0.0], [0.1], [-0.2]], requires_grad=True)
    assert torch.autograd.gradcheck(lambda f: eq(k, f), (fixed,), atol=1e-7)


def test_backward_and_jvp_reuse_the_forward_factorization():
    _, eq, fixed = make_hardening()
    k = (torch.rand(12) + 1.0).requires_grad_()
    x = eq(k, fixed)
    with counting() as count:
        for _ in range(3):
            torch.autograd.grad(x, k, torch.randn_like(x), retain_graph=True)
        import torch.autograd.forward_ad as fwAD
        with fwAD.dual_level():
            fwAD.unpack_dual(eq(fwAD.make_dual(k.detach(), torch.randn(12)), fixed)).tangent
    assert count.factorizations == 0
    assert count.solves == 3 * 3 + 3   # per-frame factors: one solve per frame per product


@pytest.mark.parametrize("backend", ["scipy", "cg"])
def test_linear_adjoint_and_jvp_match_finite_differences(backend):
    """A linear model (one factor for all frames): reverse and forward mode, in the
    parameters and the Dirichlet values, with a direct and an iterative backend."""
    pattern, values_of = chain_pattern(7)
    model = MatrixModel(pattern, values_of(torch.rand(6) + 0.5), torch.randn(2, 7))
    eq = Equilibrium(model, torch.tensor([0]), backend=backend)
    shift = (torch.rand(7) + 0.5).requires_grad_()
    fixed = torch.randn(2, 1, requires_grad=True)
    fn = lambda s, f: eq(s, f)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (shift, fixed))
    assert torch.autograd.gradcheck(fn, (shift, fixed), check_forward_ad=True,
                                    check_backward_ad=False, check_undefined_grad=False,
                                    check_batched_grad=False)


def test_linear_factorization_is_reused_by_backward_and_jvp():
    pattern, values_of = chain_pattern(50)
    model = MatrixModel(pattern, values_of(torch.rand(49) + 1), torch.randn(3, 50))
    eq = Equilibrium(model, torch.tensor([0]))
    shift = (torch.rand(50) + 1).requires_grad_()
    fixed = torch.zeros(3, 1)
    with counting() as count:
        x = eq(shift, fixed)
        for _ in range(3):
            torch.autograd.grad(x, shift, torch.randn(3, 50), retain_graph=True)
        import torch.autograd.forward_ad as fwAD
        with fwAD.dual_level():
            fwAD.unpack_dual(eq(fwAD.make_dual(shift.detach(), torch.randn(50)), fixed)).tangent
    assert count.factorizations == 1
    assert count.solves == 1 + 3 + 1        # one shared factor: one solve per product
