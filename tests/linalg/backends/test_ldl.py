"""The ``ldl`` backend (qdldl): agreement with SuperLU, one ordering per pattern, live
factors that stay valid, fallbacks for matrices an unpivoted ``L D L^T`` must not take."""
from __future__ import annotations

import gc

import pytest
import torch

from torchfit.linalg import (BackendDeviceError, ScipyBackend, SingularMatrixError,
                             SparsePattern, counting, get_backend)
from torchfit.linalg.backends.ldl import LdlBackend

from helpers.grid_matrices import grid_laplacian
from helpers.linear_system import gradients, linear_equilibrium


def test_ldl_solve_matches_superlu_and_counts():
    pattern, values = grid_laplacian(20, 15)          # scrambled numbering
    rhs = torch.randn(pattern.shape[0], 3, dtype=torch.float64,
                      generator=torch.Generator().manual_seed(1))
    backend = get_backend("ldl")
    with counting() as count:
        factor = backend.factorize(pattern, values, symmetric=True)
        x = factor.solve(rhs)
        x1 = factor.solve(rhs[:, 0], transpose=True)
    assert count.as_dict() == {"factorizations": 1, "solves": 2, "rhs_columns": 4,
                               "analyses": 1}
    assert type(factor).__name__ == "LdlFactor" and backend.fallbacks == 0
    ref = ScipyBackend().factorize(pattern, values, True).solve(rhs)
    assert torch.allclose(x, ref, rtol=0, atol=1e-11)
    assert torch.allclose(x1, ref[:, 0], rtol=0, atol=1e-11)
    assert torch.allclose(pattern.matvec(values, x1), rhs[:, 0], rtol=0, atol=1e-10)


def test_one_analysis_per_pattern_and_live_factors_stay_valid():
    """A second factor of the pattern (the first one alive) gets a solver of its own; a
    factor that was garbage collected gives its solver (and its ordering) to the next one,
    which re-runs only the numeric factorisation."""
    pattern, values = grid_laplacian(12, 9, seed=3)
    backend = LdlBackend(fallback=ScipyBackend())
    plan = backend.plan(pattern)
    rhs = torch.randn(pattern.shape[0], dtype=torch.float64,
                      generator=torch.Generator().manual_seed(2))
    first = backend.factorize(pattern, values, True)
    second = backend.factorize(pattern, 2.0 * values, True)
    assert plan.analyses == 2
    # each factor still solves its own matrix
    assert torch.allclose(pattern.matvec(values, first.solve(rhs)), rhs, atol=1e-10)
    assert torch.allclose(pattern.matvec(2.0 * values, second.solve(rhs)), rhs, atol=1e-10)
    del first
    gc.collect()
    for scale in (3.0, 4.0, 5.0):                    # reuse: no further analysis
        factor = backend.factorize(pattern, scale * values, True)
        assert torch.allclose(pattern.matvec(scale * values, factor.solve(rhs)), rhs,
                              atol=1e-10)
        del factor
    assert plan.analyses == 2
    # another backend object shares the plan (an equilibrium makes one of its own)
    assert get_backend("ldl").plan(pattern) is plan


def test_ldl_hands_indefinite_nonsymmetric_and_singular_matrices_to_superlu():
    pattern, values = grid_laplacian(10, 6, shift=-2.0)        # indefinite
    backend = LdlBackend(fallback=ScipyBackend())
    factor = backend.factorize(pattern, values, symmetric=True)
    assert type(factor).__name__ == "ScipyFactor" and backend.fallbacks == 1
    rhs = torch.randn(pattern.shape[0], dtype=torch.float64)
    assert torch.allclose(pattern.matvec(values, factor.solve(rhs)), rhs, atol=1e-9)
    # the indefinite attempt left its solver in the pool: the next SPD matrix reuses it
    spd_values = grid_laplacian(10, 6)[1]
    factor = backend.factorize(pattern, spd_values, symmetric=True)
    assert type(factor).__name__ == "LdlFactor" and backend.plan(pattern).analyses == 1
    # nonsymmetric matrices are never factorised without pivoting
    assert type(backend.factorize(pattern, values, symmetric=False)).__name__ == "ScipyFactor"
    # a singular matrix (pure Neumann Laplacian) is reported by SuperLU, not solved
    singular = SparsePattern(torch.tensor([0, 0, 1, 1]), torch.tensor([0, 1, 0, 1]), (2, 2))
    with pytest.raises(SingularMatrixError):
        backend.factorize(singular, torch.tensor([1.0, -1.0, -1.0, 1.0],
                                                 dtype=torch.float64), True)
    with pytest.raises(SingularMatrixError, match="NaN"):
        backend.factorize(pattern, torch.full_like(values, float("nan")), True)


def test_ldl_equilibrium_gradients_match_superlu():
    """The differentiable linear solve (a linear equilibrium on the grid matrix) with the
    ldl factor: gradients match finite differences and SuperLU's."""
    pattern, values = grid_laplacian(8, 5)
    eq, shift, fixed = linear_equilibrium(pattern, values, "ldl")
    assert type(eq.solution(shift, fixed, None).factors[0]).__name__ == "LdlFactor"
    assert torch.autograd.gradcheck(lambda s, f: eq(s, f),
                                    (shift.requires_grad_(), fixed.requires_grad_()))
    grads = [gradients(linear_equilibrium(pattern, values, backend)[0], shift, fixed)
             for backend in ("ldl", "scipy")]
    for ldl, superlu in zip(*grads):
        assert torch.allclose(ldl, superlu, rtol=0, atol=1e-10)


def test_ldl_refuses_tensors_off_the_cpu_by_name():
    """Checked on the ``meta`` device, which every machine has (CUDA tensors take the same
    branch: ``device.type != 'cpu'``)."""
    pattern, values = grid_laplacian(4, 3)
    backend = get_backend("ldl")
    with pytest.raises(BackendDeviceError, match="the ldl backend runs on the CPU"):
        backend.factorize(pattern, values.to("meta"), True)
    factor = backend.factorize(pattern, values, True)
    with pytest.raises(BackendDeviceError, match="the ldl backend runs on the CPU"):
        factor.solve(torch.zeros(pattern.shape[0], dtype=torch.float64, device="meta"))
