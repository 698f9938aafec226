import numpy as np
import pytest
import torch

from torchfit.linalg import counting
from torchfit.problems import Poisson2D, ProblemConfigError


def nearest(points: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Index into ``reference`` of each point (exact coordinate match asserted)."""
    distance = ((points[:, None, :] - reference[None, :, :]) ** 2).sum(-1)
    index = distance.argmin(axis=1)
    assert np.allclose(reference[index], points, atol=1e-12)
    return index


@pytest.mark.parametrize("pattern", ["blocks", "ipam"])
def test_reproduces_independent_vectors(vectors_dir, pattern):
    data = np.load(vectors_dir / f"poisson2d_N16_{pattern}.npz")
    problem = Poisson2D(N=int(data["N"]), s=float(data["s"]), pattern=pattern)
    cells = nearest(problem.cell_centres.numpy(), data["cell_centres"])
    nodes = nearest(problem.rest_positions.numpy(), data["rest_positions"])
    np.testing.assert_array_equal(problem.field_true.numpy(), data["k"][cells])
    x = problem.simulate(torch.from_numpy(data["k"][cells]))
    np.testing.assert_allclose(x[0].numpy(), data["positions"][nodes], rtol=0, atol=1e-10)


def test_constant_field_stretches_uniformly_in_x():
    problem = Poisson2D(N=9)
    x = problem.simulate(torch.full((64,), 3.0))[0]
    assert torch.allclose(x[:, 0], problem.rest_positions[:, 0] / 0.5, atol=1e-13)


def test_scale_free_and_both_components_share_one_factorization():
    problem = Poisson2D(N=12)
    k = torch.rand(121) + 0.5
    problem.equilibrium.clear_cache()
    with counting() as count:
        x = problem.simulate(k)
    assert count.factorizations == 1 and count.solves == 1 and count.rhs_columns == 2
    assert torch.allclose(problem.simulate(7.5 * k), x, atol=1e-12)
    metrics = problem.metrics(problem.parameterization.inverse(3.0 * problem.field_true))
    assert metrics["k_err_rel_aligned"] < 1e-12 and metrics["k_err_rel"] == pytest.approx(2.0)


def test_sparse_data_every_fourth_node():
    problem = Poisson2D(N=17, data="sparse")
    i, j = np.divmod(problem.observed_nodes.numpy(), 17)
    assert (i % 4 == 0).all() and (j % 4 == 0).all()
    assert (i != 0).all() and (i != 16).all()             # Dirichlet columns never observed
    assert problem.data.numel() == 2 * 3 * 5


def test_gauge_keeps_mean_log_k():
    problem = Poisson2D(N=8)
    residual = problem.residual()
    project = residual.projector(problem.theta0)
    assert abs(float(project(torch.randn(49)).sum())) < 1e-12


@pytest.mark.parametrize("overrides, match", [
    ({"N": 2}, "problem.N"),
    ({"pattern": "smiley"}, "blocks"),
    ({"data": "some"}, "dense"),
    ({"noise": -1e-3}, "problem.noise"),
    ({"N": 8, "data": "sparse", "sparse_stride": 9}, "larger than the grid"),
])
def test_bad_settings_are_clear_errors(overrides, match):
    with pytest.raises(ProblemConfigError, match=match):
        Poisson2D(**overrides)


@pytest.mark.parametrize("data", ["dense", "sparse"])
def test_explicit_products_equal_the_autograd_products_and_cost_one_solve(data):
    """The solvers' explicit J v / J^T w (no autograd engine) against the autograd route
    (the definition), a dot-product identity, and one solve per product."""
    from torchfit.verification import dot_product_test, taylor_test

    from helpers.products import explicit_and_autograd

    problem = Poisson2D(N=13, data=data, noise=1e-3)
    theta, lin, reference, v, w = explicit_and_autograd(problem, 3)
    assert torch.equal(lin.r, reference.r)
    with counting() as count:
        jv, jtw = lin.jvp(v), lin.vjp(w)
    assert count.factorizations == 0 and count.solves == 2
    assert torch.allclose(jv, reference.jvp(v), rtol=1e-12, atol=1e-15)
    assert torch.allclose(jtw, reference.vjp(w), rtol=1e-12, atol=1e-15)
    assert dot_product_test(lin, v, w).passed(1e-12)
    assert taylor_test(problem.residual(), theta, v).passed()
