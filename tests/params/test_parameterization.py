import numpy as np
import pytest
import torch

from torchfit.params import Parameterization, chain_edges, grid_edges, per_element, per_region


def test_exp_map_inverse_and_scale_direction():
    param = per_element(5, chain_edges(5))
    field = torch.tensor([1.0, 2.0, 4.0, 0.5, 3.0])
    theta = param.inverse(field)
    assert torch.allclose(param(theta), field)
    # moving along the scale direction multiplies the field by a constant
    moved = param(theta + 0.7 * param.scale_direction(theta) * np.sqrt(5))
    ratio = moved / field
    assert torch.allclose(ratio, ratio[0].expand(5))


def test_identity_scale_direction_is_theta():
    param = per_element(3, transform="identity")
    theta = torch.tensor([1.0, 2.0, 3.0])
    moved = param(theta + 0.5 * param.scale_direction(theta) * theta.norm())
    assert torch.allclose(moved / theta, torch.full((3,), 1.5))


def test_chain_difference_operator():
    d = per_element(4, chain_edges(4)).difference_operator().to_dense()
    expected = torch.tensor([[-1.0, 1, 0, 0], [0, -1, 1, 0], [0, 0, -1, 1]])
    assert torch.equal(d, expected)
    # constants are in its null space (TV does not see the global scale)
    assert torch.allclose(d @ torch.ones(4), torch.zeros(3))


def test_grid_edges_count():
    edges = grid_edges((3, 4))
    assert edges.shape == (3 * 3 + 2 * 4, 2)
    assert len({tuple(e) for e in edges.tolist()}) == edges.shape[0]


def test_per_region_maps_labels_and_builds_region_adjacency():
    labels = np.array([0, 0, 1, 1, 2, 2])
    param = per_region(labels, chain_edges(6))
    theta = torch.log(torch.tensor([1.0, 10.0, 100.0]))
    assert torch.allclose(param(theta), torch.tensor([1.0, 1, 10, 10, 100, 100]))
    assert param.edges.tolist() == [[0, 1], [1, 2]]
    assert torch.allclose(param.inverse(param(theta)), theta)


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="at least one parameter"):
        per_element(0)
    with pytest.raises(ValueError, match="transform"):
        per_element(3, transform="softplus")
    param = per_element(3, name="stiffness")
    with pytest.raises(ValueError, match=r"stiffness must have shape \(3,\)"):
        param(torch.zeros(4))
    with pytest.raises(ValueError, match="no difference operator"):
        param.difference_operator()
    with pytest.raises(ValueError, match="positive"):
        param.inverse(torch.tensor([1.0, -1.0, 2.0]))
    with pytest.raises(ValueError, match="labels"):
        per_region(np.array([0, 2]))
