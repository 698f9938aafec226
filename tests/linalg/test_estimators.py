"""Norm estimates from products (torchfit.linalg.estimators): power iteration, Hutchinson's
Frobenius estimate, column norms from random probes."""
import math

import pytest
import torch

from torchfit.linalg.estimators import column_norms, frobenius_norm_sq, power_norm_sq


def matrix(m=7, n=5, seed=0):
    return torch.randn(m, n, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def test_power_iteration_reaches_the_largest_eigenvalue_of_AtA_from_below():
    A = matrix()
    exact = float(torch.linalg.matrix_norm(A, ord=2)) ** 2
    estimates = [power_norm_sq(lambda v: A @ v, lambda w: A.T @ w, torch.ones(5, dtype=A.dtype), k)
                 for k in (1, 5, 200)]
    assert all(e <= exact * (1 + 1e-12) for e in estimates)
    assert estimates[0] <= estimates[1] <= estimates[2]
    assert estimates[-1] == pytest.approx(exact, rel=1e-10)


def test_power_iteration_stops_on_a_zero_or_non_finite_product():
    zero = torch.zeros(3, 4, dtype=torch.float64)
    assert power_norm_sq(lambda v: zero @ v, lambda w: zero.T @ w, torch.ones(4), 10) == 0.0
    calls = []

    def broken(v):
        calls.append(1)
        return v * (math.nan if len(calls) > 2 else 2.0)

    # A^T A v = 2 v twice, then a NaN product: the estimate so far
    assert power_norm_sq(broken, lambda w: w, torch.ones(3, dtype=torch.float64), 10) == \
        pytest.approx(2.0)
    assert len(calls) == 3


def test_hutchinson_is_exact_for_a_diagonal_and_reproducible():
    a = torch.tensor([1.0, -2.0, 3.0, 0.5], dtype=torch.float64)
    estimate = frobenius_norm_sq(lambda v: a * v, 4, a, probes=3)
    assert estimate == pytest.approx(float((a * a).sum()), rel=1e-15)
    A = matrix(40, 30, seed=1)
    one = frobenius_norm_sq(lambda v: A @ v, 30, A, probes=200)
    assert one == frobenius_norm_sq(lambda v: A @ v, 30, A, probes=200)      # seeded
    assert one == pytest.approx(float((A * A).sum()), rel=0.1)
    like32 = torch.zeros(1, dtype=torch.float32)
    seen = []
    frobenius_norm_sq(lambda v: seen.append(v.dtype) or v, 3, like32, probes=1)
    assert seen == [torch.float32]


def test_column_norms_from_probes():
    a = torch.tensor([1.0, -2.0, 3.0], dtype=torch.float64)
    generator = torch.Generator().manual_seed(0)
    state = generator.get_state()
    norms = column_norms(lambda w: a * w, a, torch.zeros(3, dtype=torch.float64), 4, generator)
    assert torch.equal(norms, a.abs())                                   # diagonal: exact
    assert not torch.equal(generator.get_state(), state)                 # the generator advanced
    A = matrix(60, 8, seed=2)
    estimate = column_norms(lambda w: A.T @ w, torch.zeros(60, dtype=A.dtype),
                            torch.zeros(8, dtype=A.dtype), 400, torch.Generator().manual_seed(1))
    assert torch.allclose(estimate, torch.linalg.vector_norm(A, dim=0), rtol=0.1)


def test_column_norms_are_the_levenberg_marquardt_probes_bit_for_bit():
    """The loop Levenberg-Marquardt's column scaling ran inline before it moved here."""
    A = matrix(9, 4, seed=3)
    r, theta = torch.zeros(9, dtype=A.dtype), torch.zeros(4, dtype=A.dtype)
    generator = torch.Generator().manual_seed(5)
    squares = torch.zeros_like(theta)
    for _ in range(16):
        signs = torch.randint(0, 2, r.shape, generator=generator) * 2 - 1
        squares += (A.T @ signs.to(r)) ** 2
    inline = (squares / 16).sqrt()
    moved = column_norms(lambda w: A.T @ w, r, theta, 16, torch.Generator().manual_seed(5))
    assert torch.equal(inline, moved)
