"""The generic equilibrium: Newton forward, implicit-function adjoint and jvp."""
import numpy as np
import pytest
import torch

from torchfit.linalg import SparsePattern, counting
from torchfit.physics import Equilibrium, NewtonConvergenceError, NewtonOptions, SpringChain1D


class HardeningChain:
    """Springs with tension ``k (s + c s^3)`` (s = stretch): non-linear, frame-dependent tangent."""

    linear = False
    symmetric = True

    def __init__(self, n: int, loads: torch.Tensor, c: float = 50.0) -> None:
        self.n_dofs = n + 1
        self.c = c
        self.a = torch.arange(n)
        self.b = self.a + 1
        self.rest = torch.full((n,), 1.0 / n)
        self.external = torch.zeros(loads.numel(), n + 1)
        self.external[:, 1:] = 0.5 / n
        self.external[:, n] += loads
        rows = torch.stack([self.a, self.a, self.b, self.b], 1).reshape(-1)
        cols = torch.stack([self.a, self.b, self.a, self.b], 1).reshape(-1)
        self.tangent_pattern = SparsePattern(rows, cols, (n + 1, n + 1))

    def _stretch(self, x):
        return x[:, self.b] - x[:, self.a] - self.rest

    def residual(self, x, k):
        s = self._stretch(x)
        t = k * (s + self.c * s ** 3)
        return x.new_zeros(x.shape).index_add(1, self.b, t).index_add(1, self.a, -t) - self.external

    def tangent_values(self, x, k):
        s = self._stretch(x)
        d = k * (1 + 3 * self.c * s ** 2)
        return torch.stack([d, -d, -d, d], dim=-1).reshape(x.shape[0], -1)


def make_hardening(n=12):
    model = HardeningChain(n, torch.tensor([0.0, 0.3, 1.0]))
    eq = Equilibrium(model, torch.tensor([0]), newton=NewtonOptions(rtol=1e-13, atol=1e-14))
    return model, eq, torch.zeros(3, 1)


def test_newton_solves_nonlinear_model_and_counts_factorizations():
    model, eq, fixed = make_hardening()
    k = torch.rand(12) + 1.0
    with counting() as count:
        x = eq(k, fixed)
    assert model.residual(x, k)[:, 1:].abs().max() < 1e-12
    iterations = sum(eq.last_newton_iterations)
    # one factorisation per frame and Newton iteration, plus one per frame at the solution
    assert count.factorizations == iterations + 3


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


def test_linear_chain_one_factorization_for_all_frames(vectors_dir):
    data = np.load(vectors_dir / "spring1d_n64.npz")
    n = 64
    external = torch.full((3, n + 1), float(data["gravity"]) / n)
    external[:, n] += torch.from_numpy(data["loads"])
    nodes = torch.arange(n + 1)
    model = SpringChain1D(torch.stack([nodes[:-1], nodes[1:]], 1), torch.full((n,), 1.0 / n),
                          external)
    eq = Equilibrium(model, torch.tensor([0]))
    with counting() as count:
        x = eq(torch.from_numpy(data["k"]), torch.zeros(3, 1))
    assert count.factorizations == 1 and count.solves == 1
    np.testing.assert_allclose(x.numpy(), data["positions"], rtol=0, atol=1e-10)


def test_spring_residual_is_gradient_of_energy():
    n = 5
    nodes = torch.arange(n + 1)
    model = SpringChain1D(torch.stack([nodes[:-1], nodes[1:]], 1), torch.full((n,), 0.2),
                          torch.rand(2, n + 1))
    x = torch.rand(2, n + 1, requires_grad=True)
    k = torch.rand(n) + 1
    (grad,) = torch.autograd.grad(model.energy(x, k).sum(), x)
    assert torch.allclose(grad, model.residual(x, k))
    dense = model.tangent_pattern.to_scipy(
        model.tangent_pattern.assemble(model.tangent_values(x, k))[0]).toarray()
    hessian = torch.autograd.functional.hessian(lambda y: model.energy(y[None], k)[0], x[0].detach())
    assert np.allclose(dense, hessian.numpy())


def test_no_dirichlet_node_is_a_clear_error():
    model, _, _ = make_hardening()
    with pytest.raises(ValueError, match="no Dirichlet"):
        Equilibrium(model, torch.tensor([], dtype=torch.long))


def test_newton_failure_names_frame_and_residual():
    model, _, fixed = make_hardening()
    eq = Equilibrium(model, torch.tensor([0]), newton=NewtonOptions(max_iter=1, rtol=1e-14))
    with pytest.raises(NewtonConvergenceError, match=r"frame \d+: residual norm"):
        eq(torch.rand(12) + 1.0, fixed)


def test_bad_dirichlet_values_are_named():
    _, eq, _ = make_hardening()
    with pytest.raises(ValueError, match="shape"):
        eq(torch.ones(12), torch.zeros(3, 2))
    with pytest.raises(ValueError, match="frame 1"):
        eq(torch.ones(12), torch.tensor([[0.0], [float("nan")], [0.0]]))


def test_live_graph_keeps_its_factorization_after_other_points():
    """A linearisation's J v stays factorisation-free however many points come between."""
    from torchfit.problems import Spring1D

    problem = Spring1D(n=16)
    residual = problem.residual()
    lin = residual.linearize(problem.theta0)
    for shift in (0.1, 0.2, 0.3):               # more points than the cache holds
        residual.value(problem.theta0 + shift)
    with counting() as count:
        lin.jvp(torch.randn(16))
        lin.vjp(torch.randn(problem.data.numel()))
    assert count.factorizations == 0 and count.solves == 2
    del lin
    import gc
    gc.collect()
    for shift in (0.4, 0.5):                    # push it out of the LRU cache too
        residual.value(problem.theta0 + shift)
    with counting() as count:                   # graph gone: the point is solved afresh
        residual.value(problem.theta0)
    assert count.factorizations == 1


# -- the whole Jacobian in one pass ---------------------------------------------------------
def _jvp_columns(fn, params, directions):
    import torch.autograd.forward_ad as fwAD
    columns = []
    for j in range(directions.shape[1]):
        with fwAD.dual_level():
            columns.append(fwAD.unpack_dual(fn(fwAD.make_dual(params, directions[:, j]))).tangent)
    return torch.stack(columns, dim=-1)


def _relative(a, b):
    return float((a - b).norm() / b.norm())


@pytest.mark.parametrize("material", ["linear", "corotated"])
def test_jacobian_columns_are_the_jvps_and_cost_one_solve_per_frame(material):
    from tetbox import clamped_box

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
    reference = _jvp_columns(lambda e: qs(e, positions), E, V)
    assert _relative(J, reference) < 1e-10
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
        assert _relative(observed, observe @ J.reshape(2, n_dofs, 7)) < 1e-12
    with pytest.raises(ValueError, match="observe"):
        qs.jacobian(E, positions, V, observe=observe[:, :-1])
    # without a cached solution it solves exactly like the forward, then the same answer
    qs.clear_cache()
    J2 = qs.jacobian(E, positions, V)
    assert _relative(J2, J) < 1e-10 and torch.allclose(qs(E, positions), x, atol=1e-12)


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
    assert _relative(J, _jvp_columns(lambda p: eq(p, fixed), k, V)) < 1e-10
    with pytest.raises(ValueError, match="directions"):
        eq.jacobian(k, fixed, torch.ones(7, 2))


# -- explicit products (no autograd graph) --------------------------------------------------
@pytest.mark.parametrize("material", ["linear", "corotated"])
def test_linearization_products_are_the_autograd_products(material):
    from tetbox import clamped_box

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
    reference_jvp = _jvp_columns(lambda e: qs(e, positions).reshape(2, -1), E, v[:, None])[..., 0]
    assert _relative(lin.vjp(w), reference_vjp) < 1e-12
    assert _relative(lin.jvp(v), reference_jvp) < 1e-12
    assert float(lin.jvp(v)[:, eq.fixed_dofs].abs().max()) == 0.0
    # the free-dof layout (n_free, F): the same numbers, no Dirichlet rows
    free = eq.free_dofs
    assert _relative(lin.free_jvp(v), reference_jvp[:, free].T) < 1e-12
    w_free = w.clone()
    w_free[:, eq.fixed_dofs] = 0.0
    (reference_free,) = torch.autograd.grad(x, leaf, w_free)
    assert _relative(lin.free_vjp(w[:, free].T), reference_free) < 1e-12


def test_spring_products_through_the_sparse_derivative_matrix():
    """A model whose param_derivative has matrix_entries: CSR products, one solve each,
    the layout built once per pattern and shared by later solutions."""
    n, frames = 10, 3
    external = torch.full((frames, n + 1), 0.1, dtype=torch.float64)
    external[:, n] += torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64)
    nodes = torch.arange(n + 1)
    model = SpringChain1D(torch.stack([nodes[:-1], nodes[1:]], 1),
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
    reference_jvp = _jvp_columns(lambda p: eq(p, fixed), k, v[:, None])[..., 0]
    assert _relative(jv, reference_jvp[:, 1:].T) < 1e-12
    grad_full = torch.zeros(frames, n + 1, dtype=torch.float64)
    grad_full[:, 1:] = w.T
    (reference_vjp,) = torch.autograd.grad(x, leaf, grad_full)
    assert _relative(jtw, reference_vjp) < 1e-12
    layouts = eq.matrix_layouts.entries
    eq.linearization(1.5 * k, fixed).free_jvp(v)
    assert eq.matrix_layouts.entries is layouts and len(layouts) == 1   # one per pattern
    with pytest.raises(ValueError, match="Dirichlet"):
        eq.free_position(torch.tensor([0, 3]))


def test_linearization_needs_a_param_derivative():
    model, eq, fixed = make_hardening(4)
    with pytest.raises(TypeError, match="param_derivative"):
        eq.linearization(torch.ones(4), fixed)


class DoubleWell:
    """One free dof in the energy ``x^4 / 4 - x^2 / 2 - a x``: two stable equilibria (near
    -1 and +1) while ``|a| < 0.385``, one beyond. Dof 0 is a fixed dummy."""

    linear = False
    symmetric = True
    n_dofs = 2
    tangent_pattern = SparsePattern(torch.tensor([0, 1]), torch.tensor([0, 1]), (2, 2))

    def residual(self, x, a):
        free = x[:, 1:] ** 3 - x[:, 1:] - a
        return torch.cat([torch.zeros_like(free), free], dim=1)

    def tangent_values(self, x, a):
        return torch.stack([torch.ones_like(x[:, 1]), 3 * x[:, 1] ** 2 - 1], dim=-1)


@pytest.mark.parametrize("derivative_taken", [True, False])
def test_warm_start_comes_from_the_point_derivatives_were_taken_at(derivative_taken):
    """A solver linearises at a point, tries a far one (rejected) and then a near one: the
    near one starts from the linearisation point and stays in its well. Without a
    linearisation the most recent solution is the start (the other well)."""
    eq = Equilibrium(DoubleWell(), torch.tensor([0]), newton=NewtonOptions(rtol=1e-12))
    fixed = torch.zeros(1, 1, dtype=torch.float64)
    start = torch.tensor([[0.0, 1.2]], dtype=torch.float64)
    a = torch.tensor([0.0], dtype=torch.float64, requires_grad=True)
    x = eq(a, fixed, start)
    assert abs(float(x[0, 1].detach()) - 1.0) < 1e-10
    if derivative_taken:
        (slope,) = torch.autograd.grad(x[0, 1], a)     # dx/da = 1 / (3 x^2 - 1) = 0.5
        assert abs(float(slope) - 0.5) < 1e-10
    far = eq(torch.tensor([-1.0], dtype=torch.float64), fixed, start)
    assert float(far[0, 1]) < -1.3                     # the only equilibrium there
    near = eq(torch.tensor([0.05], dtype=torch.float64), fixed, start)
    assert eq.last_warm_started
    if derivative_taken:
        assert abs(float(near[0, 1]) - 1.0) < 0.05     # the linearisation point's well
    else:
        assert abs(float(near[0, 1]) + 1.0) < 0.05     # the rejected trial's well


def test_an_independent_solve_starts_cold_and_seeds_no_warm_start():
    """A solve inside ``independent()`` (a synthetic target, a baseline) neither starts from
    an earlier solution nor becomes the start of a later one; found again at the same
    parameters outside it, it is the solver's point and seeds as before."""
    eq = Equilibrium(DoubleWell(), torch.tensor([0]), newton=NewtonOptions(rtol=1e-12))
    fixed = torch.zeros(1, 1, dtype=torch.float64)
    start = torch.tensor([[0.0, 1.2]], dtype=torch.float64)
    left = -start
    eq(torch.tensor([-1.0], dtype=torch.float64), fixed, left)         # the only well: -1.32
    with eq.independent():
        cold = eq(torch.tensor([0.05], dtype=torch.float64), fixed, start)
        assert not eq.last_warm_started and float(cold[0, 1]) > 0.9   # the start's well
        far = eq(torch.tensor([-0.9], dtype=torch.float64), fixed, left)
        assert float(far[0, 1]) < -1.2
    near = eq(torch.tensor([0.1], dtype=torch.float64), fixed, start)
    # the most recent solution (a = -0.9) came from independent(): not a start, so this one
    # starts cold, in the +1 well (a warm start from it would end near -0.95)
    assert not eq.last_warm_started and float(near[0, 1]) > 0.9
    iterations = eq.last_newton_iterations
    again = eq(torch.tensor([-0.9], dtype=torch.float64), fixed, left)    # cached: promoted
    assert eq.last_newton_iterations is iterations and float(again[0, 1]) < -1.2
    eq(torch.tensor([0.0], dtype=torch.float64), fixed, start)
    assert eq.last_warm_started                                  # from a = -0.9 now
