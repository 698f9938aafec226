"""The Dirichlet reduction: its checks of the fixed dofs and of the values handed in."""
import pytest
import torch

from torchfit.physics import Equilibrium

from helpers.equilibrium_models import make_hardening


def test_no_dirichlet_node_is_a_clear_error():
    model, _, _ = make_hardening()
    with pytest.raises(ValueError, match="no Dirichlet"):
        Equilibrium(model, torch.tensor([], dtype=torch.long))


def test_bad_dirichlet_values_are_named():
    _, eq, _ = make_hardening()
    with pytest.raises(ValueError, match="shape"):
        eq(torch.ones(12), torch.zeros(3, 2))
    with pytest.raises(ValueError, match="frame 1"):
        eq(torch.ones(12), torch.tensor([[0.0], [float("nan")], [0.0]]))
