import numpy as np
import pytest
import torch

from torchfit.params import (FieldAndScalars, Parameterization, chain_edges, grid_edges,
                             grid_groups, per_element, per_grid_node, per_region)
from torchfit.params.parameterization import grid_node_positions


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


LOWER, UPPER = np.array([-0.1, 0.2, -0.3]), np.array([0.3, 0.5, 0.4])


def test_grid_node_positions_are_row_major():
    shape = (3, 4, 5)
    nodes = grid_node_positions(shape, LOWER, UPPER)
    assert nodes.shape == (60, 3)
    ix, iy, iz = 2, 1, 3
    spacing = (UPPER - LOWER) / (np.array(shape) - 1)
    np.testing.assert_allclose(nodes[(ix * 4 + iy) * 5 + iz], LOWER + spacing * [ix, iy, iz],
                               rtol=0, atol=1e-15)
    np.testing.assert_allclose(nodes.min(0), LOWER, rtol=0, atol=0)
    np.testing.assert_allclose(nodes.max(0), UPPER, rtol=0, atol=1e-15)


def trilinear(x: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``c0 + c1 x + c2 y + c3 z + c4 xy + c5 xz + c6 yz + c7 xyz``."""
    X, Y, Z = x.T
    return (c[0] + c[1] * X + c[2] * Y + c[3] * Z + c[4] * X * Y + c[5] * X * Z + c[6] * Y * Z
            + c[7] * X * Y * Z)


def test_per_grid_node_reproduces_trilinear_functions():
    shape = (3, 4, 5)
    rng = np.random.default_rng(1)
    points = rng.uniform(LOWER, UPPER, (500, 3))
    outside = np.array([[-1.0, 0.3, 0.0], [0.2, 9.0, 9.0]])      # clamped onto the box
    param = per_grid_node(shape, np.vstack([points, outside]), LOWER, UPPER,
                          transform="identity", name="stiffness")
    assert param.n_params == 60 and param.n_field == 502 and param.name == "stiffness"
    basis = param.basis
    assert basis.is_sparse and basis.is_coalesced() and basis.dtype == torch.float64
    dense = basis.to_dense()
    torch.testing.assert_close(dense.sum(1), torch.ones(502), rtol=0, atol=1e-15)
    assert (dense >= 0).all() and int((dense != 0).sum(1).max()) <= 8
    for _ in range(3):
        c = rng.normal(size=8)
        theta = torch.from_numpy(trilinear(grid_node_positions(shape, LOWER, UPPER), c))
        field = param(theta).numpy()
        np.testing.assert_allclose(field[:500], trilinear(points, c), rtol=0, atol=1e-13)
        np.testing.assert_allclose(field[500:], trilinear(np.clip(outside, LOWER, UPPER), c),
                                   rtol=0, atol=1e-13)
    # at a node the field is that node's value alone
    node = grid_node_positions(shape, LOWER, UPPER)[[17]]
    one = per_grid_node(shape, node, LOWER, UPPER).basis.to_dense()
    assert one.shape == (1, 60) and one[0, 17] == 1.0 and int((one != 0).sum()) == 1


def test_per_grid_node_tv_operator_and_groups():
    nx, ny, nz = shape = (3, 4, 5)
    param = per_grid_node(shape, np.zeros((1, 3)), LOWER, UPPER)
    D = param.difference_operator()
    assert D.shape == ((nx - 1) * ny * nz + nx * (ny - 1) * nz + nx * ny * (nz - 1), 60)
    assert torch.equal(param.difference_groups(), torch.from_numpy(grid_groups(shape)))
    np.testing.assert_array_equal(param.edges.numpy(), grid_edges(shape))
    # neighbours are one grid spacing apart along one axis
    nodes = grid_node_positions(shape, LOWER, UPPER)
    steps = np.abs(nodes[param.edges[:, 1]] - nodes[param.edges[:, 0]])
    spacing = (UPPER - LOWER) / (np.array(shape) - 1)
    assert np.allclose(np.sort(steps / spacing, axis=1), [0, 0, 1])
    # exp: a constant theta is a constant field, and D ignores it
    theta = param.constant(2.5)
    torch.testing.assert_close(param(theta), torch.full((1,), 2.5))
    assert torch.count_nonzero(D @ theta) == 0


def test_per_grid_node_in_2d_is_bilinear():
    rng = np.random.default_rng(2)
    points = rng.uniform([0, 0], [1, 2], (50, 2))
    param = per_grid_node((4, 3), points, [0, 0], [1, 2], transform="identity")
    nodes = grid_node_positions((4, 3), [0, 0], [1, 2])
    f = lambda x: 1 + 2 * x[:, 0] - x[:, 1] + 3 * x[:, 0] * x[:, 1]   # noqa: E731
    np.testing.assert_allclose(param(torch.from_numpy(f(nodes))).numpy(), f(points),
                               rtol=0, atol=1e-13)
    assert param.difference_operator().shape == (3 * 3 + 4 * 2, 12)


def test_per_grid_node_checks_its_grid():
    points = np.zeros((2, 3))
    with pytest.raises(ValueError, match="at least 2 nodes per axis"):
        per_grid_node((1, 3, 3), points, LOWER, UPPER)
    with pytest.raises(ValueError, match="upper > lower"):
        per_grid_node((2, 3, 3), points, LOWER, [0.3, 0.2, 0.4])
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        per_grid_node((2, 3, 3), np.zeros((2, 2)), LOWER, UPPER)
    with pytest.raises(ValueError, match="same length"):
        grid_node_positions((2, 3, 3), LOWER[:2], UPPER)
def _parameterization(kind: str, transform: str, g: torch.Generator) -> Parameterization:
    if kind == "per_element":
        return per_element(6, chain_edges(6), transform=transform)
    if kind == "per_region":
        return per_region(np.array([0, 0, 1, 2, 2, 1, 0]), chain_edges(7), transform=transform)
    # trilinear-like weights of a coarse grid: non-negative rows summing to 1
    weights = torch.rand(9, 4, generator=g, dtype=torch.float64)
    weights = weights / weights.sum(1, keepdim=True)
    return Parameterization(4, chain_edges(4), weights.to_sparse() if kind == "coarse_grid"
                            else weights, transform)


@pytest.mark.parametrize("transform", ["exp", "identity"])
@pytest.mark.parametrize("kind", ["per_element", "per_region", "coarse_grid"])
def test_jacobian_matches_finite_differences(kind, transform):
    g = torch.Generator().manual_seed(0)
    param = _parameterization(kind, transform, g)
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


def _check_explicit_products(param: Parameterization, g: torch.Generator) -> None:
    """``jvp``/``vjp`` against the dense Jacobian at a random point."""
    theta = torch.randn(param.n_params, generator=g, dtype=torch.float64)
    J = param.jacobian(theta)
    v = torch.randn(param.n_params, generator=g, dtype=torch.float64)
    w = torch.randn(param.n_field, generator=g, dtype=torch.float64)
    assert torch.allclose(param.jvp(theta, v), J @ v, rtol=1e-13, atol=1e-14)
    assert torch.allclose(param.vjp(theta, w), J.T @ w, rtol=1e-13, atol=1e-14)


@pytest.mark.parametrize("transform", ["exp", "identity"])
@pytest.mark.parametrize("kind", ["per_element", "per_region", "coarse_grid", "dense_basis"])
def test_explicit_jvp_and_vjp_are_the_jacobian_products(kind, transform):
    g = torch.Generator().manual_seed(1)
    _check_explicit_products(_parameterization(kind, transform, g), g)


def test_field_and_scalars_explicit_products():
    param = FieldAndScalars(per_region(np.array([0, 1, 1, 2]), chain_edges(4)),
                            ("alpha", "beta"), (0.1, 0.2))
    _check_explicit_products(param, torch.Generator().manual_seed(2))


def test_field_and_scalars_parameterisation():
    field = per_element(4, chain_edges(4), "exp")
    param = FieldAndScalars(field, ("alpha", "beta"), (0.5, 2e-3), "exp")
    theta = param.constant(3.0)
    physical = param(theta)
    assert torch.allclose(physical, torch.tensor([3.0, 3.0, 3.0, 3.0, 0.5, 2e-3]))
    assert torch.allclose(param.inverse(physical), theta)
    D = param.difference_operator().to_dense()
    assert D.shape == (3, 6) and bool((D[:, 4:] == 0).all())      # TV leaves alpha, beta alone
    J = param.jacobian(theta)
    assert torch.allclose(J, torch.diag(physical))
    assert torch.allclose(param.scale_direction(theta)[4:], torch.zeros(2))
