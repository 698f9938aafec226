"""The banded (RCM + LAPACK banded Cholesky) backend: agreement with SuperLU, fallbacks."""
from __future__ import annotations

import pytest
import torch

from torchfit.linalg import BandedBackend, ScipyBackend, counting, get_backend

from helpers.grid_matrices import grid_laplacian
from helpers.linear_system import gradients, linear_equilibrium


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


def test_banded_equilibrium_gradients():
    """The differentiable linear solve (a linear equilibrium on the grid matrix) with the
    banded factor: gradients match finite differences and SuperLU's."""
    pattern, values = grid_laplacian(12, 3)
    eq, shift, fixed = linear_equilibrium(pattern, values, "banded")
    assert type(eq.solution(shift, fixed, None).factors[0]).__name__ == "BandedFactor"
    assert torch.autograd.gradcheck(lambda s, f: eq(s, f),
                                    (shift.requires_grad_(), fixed.requires_grad_()))
    # the parameter and Dirichlet-value gradients are those of the direct solver
    grads = [gradients(linear_equilibrium(pattern, values, backend)[0], shift, fixed)
             for backend in ("banded", "scipy")]
    for banded, superlu in zip(*grads):
        assert torch.allclose(banded, superlu, atol=1e-10)


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
