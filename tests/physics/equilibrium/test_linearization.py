"""Derivative products without a graph: the whole Jacobian in one pass (observed or not) and
the explicit products of EquilibriumLinearization (CSR route included)."""
import pytest
import torch

from torchfit.linalg import counting
from torchfit.physics import Equilibrium, ScalarSpringNetwork

from helpers.equilibrium_models import jvp_columns, make_hardening, relative


@pytest.mark.parametrize("material", ["linear", "corotated"])
def test_jacobian_columns_are_the_jvps_and_cost_one_solve_per_frame(material):
    from helpers.tetbox import clamped_box

    model, qs, bottom, top = clamped_box((2, 2, 3), (0.5, 0.5, 1.0), material, atol=1e-15)
    X = model.rest.points
    shift = torch.tensor([[0.1, 0.0, 0.15], [-0.1, 0.05, -0.1]], dtype=torch.float64)
    positions = torch.stack([torch.cat([X[bottom], X[top] + s]) for s in shift])   # 2 frames
    g = torch.Generator().manual_seed(0)
    E = torch.exp(0.3 * torch.randn(model.n_cells, generator=g, dtype=torch.float64))
    V = torch.randn(model.n_cells, 7, generator=g, dtype=torch.float64)
    x = qs(E, positions)                                    # the forward: factorised here
    with counting() as count:
        J = qs.jacobian(E, positions, V)
    assert J.shape == (2, model.n_vertices, 3, 7) and not J.requires_grad
    assert count.factorizations == 0
    if material == "linear":                                # one factor shared by the frames
        assert (count.solves, count.rhs_columns) == (1, 2 * 7)
    else:
        assert (count.solves, count.rhs_columns) == (2, 2 * 7)
    reference = jvp_columns(lambda e: qs(e, positions), E, V)
    assert relative(J, reference) < 1e-10
    assert float(J[:, torch.cat([bottom, top])].abs().max()) == 0.0   # Dirichlet vertices
    # an observation applied frame by frame: the same columns, observed; the same counts
    n_dofs = model.n_vertices * 3
    observe = torch.randn(5, n_dofs, generator=g, dtype=torch.float64)
    observe[:, 1::2] = 0.0                       # sparse, some Dirichlet columns included
    for given in (observe.to_sparse_coo(), observe.to_sparse_csr(), observe):
        with counting() as count:
            observed = qs.jacobian(E, positions, V, observe=given)
        assert observed.shape == (2, 5, 7) and count.factorizations == 0
        assert count.solves == (1 if material == "linear" else 2)
        assert relative(observed, observe @ J.reshape(2, n_dofs, 7)) < 1e-12
    with pytest.raises(ValueError, match="observe"):
        qs.jacobian(E, positions, V, observe=observe[:, :-1])
    # without a cached solution it solves exactly like the forward, then the same answer
    qs.clear_cache()
    J2 = qs.jacobian(E, positions, V)
    assert relative(J2, J) < 1e-10 and torch.allclose(qs(E, positions), x, atol=1e-12)


def test_jacobian_of_a_model_without_param_derivative_takes_the_generic_route():
    model, eq, fixed = make_hardening(8)
    g = torch.Generator().manual_seed(1)
    k = torch.rand(8, generator=g) + 1.0
    V = torch.randn(8, 5, generator=g)
    eq(k, fixed)
    with counting() as count:
        J = eq.jacobian(k, fixed, V)
    assert count.factorizations == 0 and (count.solves, count.rhs_columns) == (3, 15)
    assert J.shape == (3, 9, 5) and float(J[:, 0].abs().max()) == 0.0
    assert relative(J, jvp_columns(lambda p: eq(p, fixed), k, V)) < 1e-10
    with pytest.raises(ValueError, match="directions"):
        eq.jacobian(k, fixed, torch.ones(7, 2))


@pytest.mark.parametrize("material", ["linear", "corotated"])
def test_linearization_products_are_the_autograd_products(material):
    from helpers.tetbox import clamped_box

    model, qs, bottom, top = clamped_box((2, 2, 3), (0.5, 0.5, 1.0), material, atol=1e-15)
    X = model.rest.points
    shift = torch.tensor([[0.1, 0.0, 0.15], [-0.1, 0.05, -0.1]], dtype=torch.float64)
    positions = torch.stack([torch.cat([X[bottom], X[top] + s]) for s in shift])
    g = torch.Generator().manual_seed(4)
    E = torch.exp(0.3 * torch.randn(model.n_cells, generator=g, dtype=torch.float64))
    eq = qs.equilibrium
    values = qs.dirichlet_values(positions).to(E)
    leaf = E.clone().requires_grad_(True)
    x = qs(leaf, positions).reshape(2, -1)
    with counting() as count:
        lin = eq.linearization(E, values)
    assert count.factorizations == 0                       # the forward's solution, cached
    assert torch.equal(lin.x, x.detach())
    v = torch.randn(model.n_cells, generator=g, dtype=torch.float64)
    w = torch.randn(x.shape, generator=g, dtype=torch.float64)
    (reference_vjp,) = torch.autograd.grad(x, leaf, w)
    reference_jvp = jvp_columns(lambda e: qs(e, positions).reshape(2, -1), E, v[:, None])[..., 0]
    assert relative(lin.vjp(w), reference_vjp) < 1e-12
    assert relative(lin.jvp(v), reference_jvp) < 1e-12
    assert float(lin.jvp(v)[:, eq.fixed_dofs].abs().max()) == 0.0
    # the free-dof layout (n_free, F): the same numbers, no Dirichlet rows
    free = eq.free_dofs
    assert relative(lin.free_jvp(v), reference_jvp[:, free].T) < 1e-12
    w_free = w.clone()
    w_free[:, eq.fixed_dofs] = 0.0
    (reference_free,) = torch.autograd.grad(x, leaf, w_free)
    assert relative(lin.free_vjp(w[:, free].T), reference_free) < 1e-12


def test_spring_products_through_the_sparse_derivative_matrix():
    """A model whose param_derivative has matrix_entries: CSR products, one solve each,
    the layout built once per pattern and shared by later solutions."""
    n, frames = 10, 3
    external = torch.full((frames, n + 1), 0.1, dtype=torch.float64)
    external[:, n] += torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64)
    nodes = torch.arange(n + 1)
    model = ScalarSpringNetwork(torch.stack([nodes[:-1], nodes[1:]], 1),
                          torch.full((n,), 1.0 / n, dtype=torch.float64), external)
    eq = Equilibrium(model, torch.tensor([0]))
    g = torch.Generator().manual_seed(5)
    k = torch.rand(n, generator=g, dtype=torch.float64) + 0.5
    fixed = torch.zeros(frames, 1, dtype=torch.float64)
    lin = eq.linearization(k, fixed)
    v = torch.randn(n, generator=g, dtype=torch.float64)
    w = torch.randn(n, frames, generator=g, dtype=torch.float64)
    with counting() as count:
        jv, jtw = lin.free_jvp(v), lin.free_vjp(w)
    assert count.factorizations == 0 and count.solves == 2
    assert lin._matrices is not None                        # the CSR route was taken
    leaf = k.clone().requires_grad_(True)
    x = eq(leaf, fixed)
    reference_jvp = jvp_columns(lambda p: eq(p, fixed), k, v[:, None])[..., 0]
    assert relative(jv, reference_jvp[:, 1:].T) < 1e-12
    grad_full = torch.zeros(frames, n + 1, dtype=torch.float64)
    grad_full[:, 1:] = w.T
    (reference_vjp,) = torch.autograd.grad(x, leaf, grad_full)
    assert relative(jtw, reference_vjp) < 1e-12
    layouts = eq.matrix_layouts.entries
    eq.linearization(1.5 * k, fixed).free_jvp(v)
    assert eq.matrix_layouts.entries is layouts and len(layouts) == 1   # one per pattern
    with pytest.raises(ValueError, match="Dirichlet"):
        eq.free_position(torch.tensor([0, 3]))


def test_linearization_needs_a_param_derivative():
    model, eq, fixed = make_hardening(4)
    with pytest.raises(TypeError, match="param_derivative"):
        eq.linearization(torch.ones(4), fixed)
