"""The banded (RCM + LAPACK banded Cholesky) backend: agreement with SuperLU, fallbacks."""
from __future__ import annotations

import pytest
import torch

from torchfit.linalg import BandedBackend, ScipyBackend, counting, get_backend, sparse_solve

from grid_matrices import grid_laplacian


def test_banded_solve_matches_superlu_and_counts():
    pattern, values = grid_laplacian(60, 8)
    rhs = torch.randn(pattern.shape[0], 3, generator=torch.Generator().manual_seed(1))
    backend = BandedBackend()
    assert backend.plan(pattern).bandwidth <= 2 * 8 + 2       # RCM finds the thin direction
    with counting() as count:
        factor = backend.factorize(pattern, values, symmetric=True)
        x = factor.solve(rhs)
        x1 = factor.solve(rhs[:, 0], transpose=True)
    assert count.factorizations == 1 and count.solves == 2
    ref = ScipyBackend().factorize(pattern, values, True).solve(rhs)
    assert torch.allclose(x, ref, atol=1e-10) and torch.allclose(x1, ref[:, 0], atol=1e-10)
    assert type(factor).__name__ == "BandedFactor"


def test_banded_falls_back_for_indefinite_and_wide_band_matrices():
    pattern, values = grid_laplacian(30, 6, shift=-2.0)     # indefinite
    factor = BandedBackend().factorize(pattern, values, symmetric=True)
    assert type(factor).__name__ == "ScipyFactor"
    rhs = torch.randn(pattern.shape[0], dtype=torch.float64)
    x = factor.solve(rhs)
    assert torch.allclose(pattern.matvec(values, x), rhs, atol=1e-9)
    square, square_values = grid_laplacian(40, 40)              # band too wide for its size
    assert type(BandedBackend(max_bandwidth_fraction=0.01).factorize(
        square, square_values, True)).__name__ == "ScipyFactor"


def test_banded_sparse_solve_gradients():
    pattern, values = grid_laplacian(12, 3)
    rhs = torch.randn(pattern.shape[0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda b: sparse_solve(pattern, values, b, backend="banded"), (rhs,))
    # the values gradient (on the symmetric pattern) is the one of the direct solver
    grads = []
    for backend in ("banded", "scipy"):
        v = values.clone().requires_grad_(True)
        x = sparse_solve(pattern, v, rhs.detach(), backend=backend)
        grads.append(torch.autograd.grad(x.square().sum(), v)[0])
    assert torch.allclose(grads[0], grads[1], atol=1e-10)


def test_get_backend_names():
    assert get_backend("banded").name == "banded"
    with pytest.raises(ValueError, match="banded"):
        get_backend("cholmod")


def test_thread_count_can_be_set_at_run_time():
    import torch
    from threadpoolctl import threadpool_limits

    from torchfit.linalg import blas_threads, set_threads

    before_blas, before_torch = blas_threads(), torch.get_num_threads()
    if not before_blas:
        pytest.skip("no BLAS library found by threadpoolctl in this process")
    try:
        set_threads(1)
        assert set(blas_threads().values()) == {1}
        assert torch.get_num_threads() == 1
    finally:
        for count in set(before_blas.values()):
            threadpool_limits(limits=count, user_api="blas")
        torch.set_num_threads(before_torch)
    with pytest.raises(ValueError):
        set_threads(0)
