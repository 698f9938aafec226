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


@pytest.mark.parametrize("transform", ["exp", "identity"])
@pytest.mark.parametrize("kind", ["per_element", "per_region", "coarse_grid"])
def test_jacobian_matches_finite_differences(kind, transform):
    g = torch.Generator().manual_seed(0)
    if kind == "per_element":
        param = per_element(6, chain_edges(6), transform=transform)
    elif kind == "per_region":
        param = per_region(np.array([0, 0, 1, 2, 2, 1, 0]), chain_edges(7), transform=transform)
    else:   # trilinear-like weights of a coarse grid: dense, non-negative rows summing to 1
        weights = torch.rand(9, 4, generator=g, dtype=torch.float64)
        param = Parameterization(4, chain_edges(4), (weights / weights.sum(1, keepdim=True))
                                 .to_sparse(), transform)
    theta = torch.randn(param.n_params, generator=g, dtype=torch.float64) * 0.5 + 1.0
    J = param.jacobian(theta)
    assert J.shape == (param.n_field, param.n_params) and J.layout == torch.strided
    h = 1e-6
    for j in range(param.n_params):
        e = torch.zeros_like(theta)
        e[j] = h
        fd = (param(theta + e) - param(theta - e)) / (2 * h)
        assert torch.allclose(J[:, j], fd, rtol=1e-8, atol=1e-10), j
    assert torch.allclose(J, torch.autograd.functional.jacobian(param, theta), atol=1e-14)
