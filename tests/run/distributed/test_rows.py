"""torchfit.run.distributed.rows: a Jacobian kept on its ranks gives the dense path's products.

The ranks are emulated in one process (each rank's rows and its part of every product, then
the reduction rank 0 makes: concatenation in frame order, sums in rank order); the real
exchange over torchrun is tests/run/distributed/test_session.py's (slow)."""
from __future__ import annotations

import pytest
import torch

from torchfit.run.distributed.channel import FULL, MATVEC
from torchfit.run.distributed.rows import DistributedRows, RowStore, local_product
from torchfit.run.identifiability import from_gram, from_jacobian
from torchfit.solvers.least_squares import DenseNormalEquations

FRAMES, PER_FRAME, N = 5, 6, 4
BLOCKS = [[0, 2, 4], [1, 3]]              # frames of rank 0 and rank 1 (interleaved)


def row_index(block):
    return (torch.tensor(block)[:, None] * PER_FRAME + torch.arange(PER_FRAME)).reshape(-1)


def emulated(J: torch.Tensor) -> DistributedRows:
    stores = []
    for block in BLOCKS:
        store = RowStore()
        store.add(J[row_index(block)].clone(), 7)
        stores.append(store)

    def exchange(code, ident, operand):
        parts = [local_product(code, store.get(ident), operand, row_index(block))
                 for store, block in zip(stores, BLOCKS)]
        if code in (MATVEC, FULL):      # each rank's rows back in their places
            out = torch.empty((FRAMES * PER_FRAME,) + tuple(parts[0].shape[1:]),
                              dtype=parts[0].dtype)
            for part, block in zip(parts, BLOCKS):
                out[row_index(block)] = part
            return out
        total = parts[0].clone()
        for part in parts[1:]:
            total += part
        return total

    return DistributedRows(7, tuple(J.shape), J.dtype, J.device, exchange)


@pytest.fixture
def J():
    return torch.randn(FRAMES * PER_FRAME, N, dtype=torch.float64,
                       generator=torch.Generator().manual_seed(3))


def test_the_products_are_those_of_the_whole_matrix(J):
    rows = emulated(J)
    x = torch.randn(N, dtype=torch.float64)
    X = torch.randn(N, 3, dtype=torch.float64)
    w = torch.randn(FRAMES * PER_FRAME, dtype=torch.float64)
    torch.testing.assert_close(rows @ x, J @ x, rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(rows @ X, J @ X, rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(rows.T @ w, J.T @ w, rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(rows.T @ rows, J.T @ J, rtol=1e-13, atol=1e-13)
    assert torch.equal(rows.full(), J)
    assert rows.to(w) is rows and rows.detach() is rows and rows.shape == J.shape
    with pytest.raises(TypeError):
        rows.to(torch.float32)
    with pytest.raises(ValueError):
        rows @ torch.zeros(N + 1, dtype=torch.float64)


def test_the_dense_normal_equations_solve_the_same_damped_system(J):
    """LM's dense path on the rows kept on the ranks: the same step as on the tensor (to
    round-off: the Gram matrix is summed per rank)."""
    class Lin:
        def __init__(self, matrix):
            self.matrix, self.theta = matrix, torch.zeros(N, dtype=torch.float64)
            self.r = torch.randn(FRAMES * PER_FRAME, dtype=torch.float64,
                                 generator=torch.Generator().manual_seed(5))

        def jacobian(self):
            return self.matrix

    dense, kept = Lin(J), Lin(emulated(J))
    one = DenseNormalEquations(dense, None).solve(-dense.r, 1e-3)
    two = DenseNormalEquations(kept, None).solve(-kept.r, 1e-3)
    torch.testing.assert_close(two.x, one.x, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(two.Ax, one.Ax, rtol=1e-12, atol=1e-14)


def test_a_store_keeps_the_most_recent_and_names_what_it_dropped():
    store = RowStore(keep=2)
    for ident in range(3):
        store.add(torch.zeros(1, 1), ident)
    assert sorted(store.blocks) == [1, 2] and store.next_id == 3
    with pytest.raises(RuntimeError, match="no longer kept"):
        store.get(0)


def test_identifiability_from_the_gram_matrix_is_that_of_the_jacobian(J):
    """Column norms and singular values from ``J^T J`` (the distributed path) agree with
    those of ``J`` (the SVD) to the digits the squaring leaves."""
    theta = torch.linspace(-1.0, 1.0, N, dtype=torch.float64)
    data = torch.randn(J.shape[0], dtype=torch.float64)
    direct = from_jacobian(J, theta, data)
    squared = from_gram(J.T @ J, theta, data)
    via_rows = from_jacobian(emulated(J), theta, data)
    for report in (squared, via_rows):
        assert report.determined == direct.determined and report.effective_rank == direct.effective_rank
        assert abs(report.sensitivity - direct.sensitivity).max() < 1e-12 * direct.sensitivity.max()
        assert abs(report.singular_values - direct.singular_values).max() < \
            1e-10 * direct.singular_values.max()
