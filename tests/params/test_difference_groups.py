"""TV groups of grid parameterisations (isotropic TV needs the rows of D grouped per cell)."""
import numpy as np
import pytest
import torch

from torchfit.params import (Parameterization, chain_edges, grid_edges, grid_groups,
                             per_element, per_grid_cell, per_region)


@pytest.mark.parametrize("shape", [(5,), (3, 4), (2, 3, 4)])
def test_grid_groups_put_the_axis_differences_of_one_cell_together(shape):
    edges = grid_edges(shape)
    groups = grid_groups(shape)
    assert groups.shape == (len(edges),)
    n = int(np.prod(shape))
    cells = np.arange(n).reshape(shape)
    for cell in range(n):
        members = edges[groups == cell]
        # one forward difference per axis along which the cell has a next neighbour
        index = np.unravel_index(cell, shape)
        expected = sorted(
            int(np.ravel_multi_index(tuple(i + (a == ax) for a, i in enumerate(index)), shape))
            for ax in range(len(shape)) if index[ax] + 1 < shape[ax])
        assert sorted(members[:, 1].tolist()) == expected
        assert (members[:, 0] == cell).all()
    assert cells.size == n


def test_isotropic_tv_of_a_ramp():
    """theta = a x + b y on a grid: interior cells have gradient norm sqrt(a^2 + b^2)."""
    shape = (4, 6)
    param = per_grid_cell(shape, transform="identity")
    y, x = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    theta = torch.as_tensor((3.0 * x + 4.0 * y).reshape(-1), dtype=torch.float64)
    t = torch.mv(param.difference_operator(), theta)
    groups = param.difference_groups()
    norms = torch.zeros(param.n_params).index_add_(0, groups, t * t).sqrt()
    interior = torch.as_tensor(((y < shape[0] - 1) & (x < shape[1] - 1)).reshape(-1))
    assert torch.allclose(norms[interior], torch.full((int(interior.sum()),), 5.0))


def test_groups_are_optional_and_validated():
    assert per_element(4, chain_edges(4)).difference_groups() is None
    assert per_region(np.array([0, 0, 1, 1]), chain_edges(4)).difference_groups() is None
    param = per_element(6, grid_edges((2, 3)), groups=grid_groups((2, 3)))
    assert torch.equal(param.difference_groups(), torch.as_tensor(grid_groups((2, 3))))
    with pytest.raises(ValueError, match="one group index per edge"):
        Parameterization(6, grid_edges((2, 3)), groups=np.zeros(3, dtype=int))
    with pytest.raises(ValueError, match=">= 0"):
        Parameterization(3, chain_edges(3), groups=np.array([0, -1]))
