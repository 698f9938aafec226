"""Krylov solvers in torch: batched CG over right-hand sides and matrix-free CGLS (shifts,
preconditioners, residual targets, a box)."""
import pytest
import torch

from torchfit.linalg import batched_cg, cgls


def test_batched_cg_solves_every_column():
    a = torch.randn(20, 20)
    spd = a @ a.T + 20 * torch.eye(20)
    b = torch.randn(3, 20)
    x, converged, _ = batched_cg(lambda v: v @ spd, b, rtol=1e-13, max_iter=200)
    assert converged
    assert torch.allclose(x, torch.linalg.solve(spd, b.T).T, atol=1e-10)


def test_cgls_matches_least_squares_and_ridge():
    a = torch.randn(30, 8)
    b = torch.randn(30)
    res = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 8, max_iter=50)
    assert torch.allclose(res.x, torch.linalg.lstsq(a, b[:, None]).solution[:, 0], atol=1e-10)
    assert torch.allclose(res.Ax, a @ res.x, atol=1e-10)
    shift = 0.7
    ridge = torch.linalg.solve(a.T @ a + shift * torch.eye(8), a.T @ b)
    res = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 8, shift=shift, max_iter=50)
    assert torch.allclose(res.x, ridge, atol=1e-10)
    assert res.stop_reason == "tolerance"


def test_preconditioned_cgls_solves_the_same_ridge_problem_faster():
    g = torch.Generator().manual_seed(3)
    # Columns scaled over six decades: plain CGLS needs many iterations, CGLS with the
    # exact diagonal of A^T A + shift I as preconditioner far fewer, for the same solution.
    a = torch.randn(60, 20, generator=g) * torch.logspace(0, -6, 20)
    b = torch.randn(60, generator=g)
    shift = 1e-10
    ridge = torch.linalg.solve(a.T @ a + shift * torch.eye(20), a.T @ b)
    diagonal = (a * a).sum(dim=0) + shift
    plain = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 20, shift=shift, max_iter=500,
                 normal_rtol=1e-12)
    pre = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 20, shift=shift, max_iter=500,
               normal_rtol=1e-12, preconditioner=lambda s: s / diagonal)
    assert pre.stop_reason == "tolerance"
    assert torch.allclose(pre.x, ridge, rtol=1e-6, atol=0)
    assert torch.allclose(pre.Ax, a @ pre.x, atol=1e-12)
    assert pre.iterations < plain.iterations / 2
    # the exact inverse as preconditioner: one iteration
    exact = torch.linalg.inv(a.T @ a + shift * torch.eye(20))
    one = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 20, shift=shift, max_iter=5,
               normal_rtol=1e-8, preconditioner=lambda s: exact @ s)
    assert one.iterations == 1 and torch.allclose(one.x, ridge, rtol=1e-6, atol=0)


def test_cgls_stops_at_residual_target_and_counts_products():
    a = torch.randn(40, 10)
    b = torch.randn(40)
    calls = {"mv": 0, "rmv": 0}

    def mv(v):
        calls["mv"] += 1
        return a @ v

    def rmv(w):
        calls["rmv"] += 1
        return a.T @ w

    target = 0.95 * float(b.norm())
    res = cgls(mv, rmv, b, 10, residual_target=target, max_iter=50)
    assert res.residual_norm <= target
    assert res.stop_reason == "tolerance"
    # m iterations cost m products A v and m products A^T w (the first is A^T b).
    assert calls["mv"] == res.iterations and calls["rmv"] == res.iterations


def test_preconditioned_cgls_finds_the_same_least_squares_solution_faster():
    # Columns of very different scale: CGLS needs many iterations, the column-scaling
    # preconditioner M = diag(1 / ||a_j||^2) (an exact inverse of diag(A^T A)) few.
    torch.manual_seed(0)
    scales = torch.logspace(0, 4, 12)
    a = torch.randn(60, 12) * scales
    b = torch.randn(60)
    exact = torch.linalg.lstsq(a, b[:, None]).solution[:, 0]
    column_norm_sq = (a * a).sum(dim=0)
    plain = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 12, max_iter=500, normal_rtol=1e-12)
    pre = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 12, max_iter=500, normal_rtol=1e-12,
               preconditioner=lambda v: v / column_norm_sq)
    assert torch.allclose(pre.x, exact, rtol=1e-8, atol=1e-12)
    assert torch.allclose(pre.Ax, a @ pre.x, atol=1e-9)
    assert pre.iterations < plain.iterations


def test_preconditioner_with_null_space_keeps_iterates_out_of_it():
    # M = I - 11^T/n (singular): iterates stay orthogonal to the constant vector and
    # minimise ||A x - b|| over that subspace.
    torch.manual_seed(1)
    a = torch.randn(30, 6)
    b = torch.randn(30)
    centre = lambda v: v - v.mean()  # noqa: E731
    res = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 6, max_iter=100, preconditioner=centre)
    basis = torch.linalg.qr(torch.eye(6) - 1.0 / 6)[0][:, :5]     # orthonormal, sums to zero
    best = basis @ torch.linalg.lstsq(a @ basis, b[:, None]).solution[:, 0]
    assert abs(float(res.x.sum())) < 1e-12
    assert torch.allclose(res.x, best, atol=1e-9)
    # CG ends at the 5th step (the subspace's dimension): there, on an AVX-512 CPU, s^T M s
    # was 1.2e-15 (round-off), the next beta 4e13, and the iterates left the subspace
    assert res.iterations <= 6 and res.stop_reason == "tolerance"
    # the round-off floor scales with M: a preconditioner 1e-20 times smaller (moduli in
    # pascals) stops at the same step with the same iterate
    tiny = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 6, max_iter=100,
                preconditioner=lambda v: 1e-20 * centre(v))
    assert tiny.iterations == res.iterations and torch.allclose(tiny.x, res.x, atol=1e-12)


def test_a_small_preconditioner_does_not_stop_cgls_early():
    """An SPD preconditioner of any scale keeps CGLS going to the least-squares solution
    (the round-off test is relative to M's own gain)."""
    torch.manual_seed(2)
    a = torch.randn(40, 8) * torch.logspace(0, 3, 8)
    b = torch.randn(40)
    best = torch.linalg.lstsq(a, b[:, None]).solution[:, 0]
    jacobi = 1.0 / (a * a).sum(0)
    for scale in (1.0, 1e-20, 1e20):
        res = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 8, max_iter=100,
                   preconditioner=lambda v: scale * jacobi * v)
        assert torch.allclose(res.x, best, rtol=1e-9, atol=1e-12), scale


def test_cgls_with_a_box_stops_on_its_boundary_along_the_last_update():
    """Steihaug's rule with an infinity-norm box: the unconstrained least-squares solution
    of an ill-conditioned system lies far outside the box; the iteration stops at the
    first update that would leave it, on the boundary of that update, with ``Ax`` and the
    residual of that point, and the residual is no larger than at the previous iterate."""
    g = torch.Generator().manual_seed(5)
    q, _ = torch.linalg.qr(torch.randn(40, 12, generator=g, dtype=torch.float64))
    a = q * torch.logspace(0, -5, 12, dtype=torch.float64)
    b = torch.randn(40, generator=g, dtype=torch.float64)
    free = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 12, max_iter=100, normal_rtol=1e-13)
    assert float(free.x.abs().max()) > 100                  # far outside a box of 1
    boxed = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 12, max_iter=100, normal_rtol=1e-13,
                 max_abs=1.0)
    assert boxed.stop_reason == "boundary"
    assert float(boxed.x.abs().max()) == pytest.approx(1.0, abs=1e-12)
    assert torch.allclose(boxed.Ax, a @ boxed.x, atol=1e-12)
    assert boxed.residual_norm == pytest.approx(float((a @ boxed.x - b).norm()), rel=1e-12)
    # the last inside iterate: one iteration fewer, no box; the boundary point lies on
    # the segment from it along the next update, and its residual is smaller
    inside = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 12, max_iter=boxed.iterations - 1)
    assert float(inside.x.abs().max()) < 1.0
    assert boxed.residual_norm < inside.residual_norm
    after = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 12, max_iter=boxed.iterations)
    direction = after.x - inside.x
    t = float(torch.dot(boxed.x - inside.x, direction) / torch.dot(direction, direction))
    assert 0 < t < 1
    assert torch.allclose(boxed.x, inside.x + t * direction, atol=1e-12)


def test_cgls_with_a_box_that_holds_the_solution_is_plain_cgls():
    g = torch.Generator().manual_seed(6)
    a = torch.randn(30, 8, generator=g, dtype=torch.float64)
    b = 0.01 * torch.randn(30, generator=g, dtype=torch.float64)
    plain = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 8, max_iter=50)
    boxed = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 8, max_iter=50, max_abs=1.0)
    assert float(plain.x.abs().max()) < 1.0
    assert boxed.stop_reason == plain.stop_reason == "tolerance"
    assert torch.equal(boxed.x, plain.x) and boxed.iterations == plain.iterations


def test_cgls_with_an_asymmetric_box_stops_on_its_boundary():
    """``box=(lo, hi)``: a symmetric box gives the ``max_abs`` iterates bit for bit; an
    asymmetric one (room 0 below for some unknowns) stops inside it, on its boundary."""
    g = torch.Generator().manual_seed(5)
    q, _ = torch.linalg.qr(torch.randn(40, 12, generator=g, dtype=torch.float64))
    a = q * torch.logspace(0, -5, 12, dtype=torch.float64)
    b = torch.randn(40, generator=g, dtype=torch.float64)
    ones = torch.ones(12, dtype=torch.float64)
    symmetric = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 12, max_iter=100,
                     normal_rtol=1e-13, box=(-ones, ones))
    scalar = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 12, max_iter=100,
                  normal_rtol=1e-13, max_abs=1.0)
    assert torch.equal(symmetric.x, scalar.x) and symmetric.stop_reason == "boundary"
    lo = torch.where(torch.arange(12) % 2 == 0, -0.05, -0.5).to(torch.float64)
    hi = torch.full((12,), 0.3, dtype=torch.float64)
    boxed = cgls(lambda v: a @ v, lambda w: a.T @ w, b, 12, max_iter=100,
                 normal_rtol=1e-13, box=(lo, hi))
    assert boxed.stop_reason == "boundary"
    assert bool((boxed.x >= lo).all() and (boxed.x <= hi).all())
    on_boundary = torch.isclose(boxed.x, lo, atol=1e-12) | torch.isclose(boxed.x, hi, atol=1e-12)
    assert bool(on_boundary.any())
    assert torch.allclose(boxed.Ax, a @ boxed.x, atol=1e-12)
    assert float((a @ boxed.x - b).norm()) < float(b.norm())
