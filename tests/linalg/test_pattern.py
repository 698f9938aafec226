"""The vectorised pattern builders: block-structured patterns, Dirichlet sub-patterns,
against the plain scipy/numpy construction."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from torchfit.linalg import FreeMatrixLayout, SparsePattern
from torchfit.mesh import box_tetrahedra

from helpers.linear_system import chain_pattern


def expanded(groups: torch.Tensor, bs: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows and columns of every contribution of dense local matrices on blocks, in the
    order (g, a, i, b, j)."""
    dofs = (groups[:, :, None] * bs + torch.arange(bs)).reshape(groups.shape[0], -1)
    k = dofs.shape[1]
    return (dofs[:, :, None].expand(-1, k, k).reshape(-1),
            dofs[:, None, :].expand(-1, k, k).reshape(-1))


@pytest.mark.parametrize("bs", [1, 2, 3])
def test_dense_blocks_pattern_is_the_plain_pattern(bs):
    mesh = box_tetrahedra(3, 4, 2, (1.0, 1.0, 1.0))
    cells = torch.from_numpy(mesh.cells)
    # plus groups with a repeated block and of other sizes (any k works)
    for groups, n_blocks in ((cells, len(mesh.points)),
                             (torch.tensor([[0, 2, 2], [5, 1, 0], [3, 3, 3]]), 7)):
        rows, cols = expanded(groups, bs)
        n = n_blocks * bs
        plain = SparsePattern(rows, cols, (n, n))
        blocks = SparsePattern.from_dense_blocks(groups, bs, n_blocks)
        for name in ("crow_indices", "col_indices", "row_indices", "scatter"):
            assert torch.equal(getattr(plain, name), getattr(blocks, name)), name
        assert (blocks.nnz, blocks.n_contrib, blocks.shape) == \
            (plain.nnz, plain.n_contrib, plain.shape)
        # and it assembles what scipy's COO sum gives
        contributions = torch.randn(blocks.n_contrib, dtype=torch.float64)
        dense = sp.coo_matrix((contributions.numpy(), (rows.numpy(), cols.numpy())),
                              shape=(n, n)).toarray()
        assert np.allclose(blocks.to_scipy(blocks.assemble(contributions)).toarray(), dense,
                           atol=1e-13)


def test_dense_blocks_rejects_bad_input():
    with pytest.raises(ValueError, match="out of range"):
        SparsePattern.from_dense_blocks(torch.tensor([[0, 4]]), 2, 4)
    with pytest.raises(ValueError, match=r"\(m, k\)"):
        SparsePattern.from_dense_blocks(torch.tensor([0, 1]), 2, 4)


def test_submatrix_is_the_dropped_rows_and_columns_of_a_tet_stiffness_pattern():
    mesh = box_tetrahedra(3, 3, 3, (1.0, 1.0, 1.0))
    cells = torch.from_numpy(mesh.cells)
    pattern = SparsePattern.from_dense_blocks(cells, 3, len(mesh.points))
    n = pattern.shape[0]
    g = torch.Generator().manual_seed(0)
    values = pattern.assemble(torch.randn(pattern.n_contrib, dtype=torch.float64, generator=g))
    keep_rows = torch.nonzero(torch.rand(n, generator=g) > 0.3).reshape(-1)
    keep_cols = torch.nonzero(torch.rand(n, generator=g) > 0.5).reshape(-1)
    sub, slots = pattern.submatrix(keep_rows, keep_cols)
    full = pattern.to_scipy(values).toarray()
    expected = full[np.ix_(keep_rows.numpy(), keep_cols.numpy())]
    assert sub.shape == expected.shape
    assert np.array_equal(sub.to_scipy(values[slots]).toarray(), expected)
    assert torch.equal(sub.scatter, torch.arange(sub.nnz))
    # the stored entries are exactly the kept ones (no explicit zeros added or lost)
    structure = pattern.to_scipy(torch.ones(pattern.nnz, dtype=torch.float64)).toarray()
    assert sub.nnz == int(structure[np.ix_(keep_rows.numpy(), keep_cols.numpy())].sum())
    with pytest.raises(ValueError, match="sorted"):
        pattern.submatrix(keep_rows.flip(0), keep_cols)
    with pytest.raises(ValueError, match="out of range"):
        pattern.submatrix(torch.tensor([0, n]), keep_cols)


def test_pattern_is_built_on_the_device_of_its_input_and_numpy_on_the_cpu():
    pattern = SparsePattern(np.array([0, 1, 1]), np.array([1, 0, 1]), (2, 2))
    assert pattern.device == torch.device("cpu")
    assert pattern.crow_indices.tolist() == [0, 1, 3]
    assert pattern.scatter.tolist() == [0, 1, 2]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_pattern_on_cuda_equals_the_cpu_pattern():
    mesh = box_tetrahedra(4, 3, 5, (1.0, 1.0, 1.0))
    cells = torch.from_numpy(mesh.cells)
    cpu = SparsePattern.from_dense_blocks(cells, 3, len(mesh.points))
    gpu = SparsePattern.from_dense_blocks(cells.cuda(), 3, len(mesh.points))
    assert gpu.device.type == "cuda"
    for name in ("crow_indices", "col_indices", "row_indices", "scatter"):
        assert torch.equal(getattr(cpu, name), getattr(gpu, name).cpu()), name
    keep = torch.arange(0, cpu.shape[0], 2)
    sub_cpu, slots_cpu = cpu.submatrix(keep, keep)
    sub_gpu, slots_gpu = gpu.submatrix(keep.cuda(), keep.cuda())
    assert torch.equal(slots_cpu, slots_gpu.cpu())
    assert torch.equal(sub_cpu.crow_indices, sub_gpu.crow_indices.cpu())


def test_pattern_assembles_like_scipy():
    rng = np.random.default_rng(0)
    rows = rng.integers(0, 7, 40)
    cols = rng.integers(0, 5, 40)
    contrib = rng.standard_normal(40)
    pattern = SparsePattern(rows, cols, (7, 5))
    dense = sp.coo_matrix((contrib, (rows, cols)), shape=(7, 5)).toarray()
    values = pattern.assemble(torch.from_numpy(contrib))
    assert np.allclose(pattern.to_scipy(values).toarray(), dense)
    assert np.allclose(pattern.to_torch(values).to_dense().numpy(), dense)
    x = torch.randn(3, 5)
    assert torch.allclose(pattern.matvec(values, x), x @ torch.from_numpy(dense).T)
    y = torch.randn(7)
    assert torch.allclose(pattern.rmatvec(values, y), torch.from_numpy(dense).T @ y)


def test_submatrix_drops_rows_and_columns():
    pattern, values_of = chain_pattern(6)
    values = values_of(torch.rand(5) + 1)
    keep = torch.tensor([1, 2, 4, 5])
    sub, slots = pattern.submatrix(keep, keep)
    full = pattern.to_scipy(values).toarray()
    assert np.allclose(sub.to_scipy(values[slots]).toarray(), full[np.ix_(keep, keep)])


def test_pattern_rejects_out_of_range():
    with pytest.raises(ValueError, match="out of range"):
        SparsePattern([0, 3], [0, 1], (3, 3))


def test_free_matrix_layout_is_the_frame_stacked_matrix_without_the_dropped_rows():
    """Rows ``f * n_dofs + dof`` of a ``(F * n_dofs, n_cols)`` matrix become rows
    ``position * F + f`` of the kept dofs; the values are gathered, the transpose too;
    repeated entries are flagged (the layout does not sum them)."""
    g = torch.Generator().manual_seed(3)
    n_frames, n_dofs, n_cols = 3, 5, 4
    dense = torch.randn(n_frames * n_dofs, n_cols, generator=g)
    dense[torch.rand(dense.shape, generator=g) < 0.4] = 0.0
    rows, cols = torch.nonzero(dense, as_tuple=True)
    values = dense[rows, cols]
    shuffle = torch.randperm(rows.numel(), generator=g)          # any entry order
    rows, cols, values = rows[shuffle], cols[shuffle], values[shuffle]
    free_positions = torch.tensor([-1, 0, 1, -1, 2])               # dofs 0 and 3 dropped
    layout = FreeMatrixLayout(rows, cols, (n_frames * n_dofs, n_cols), n_frames,
                              free_positions, 3)
    assert layout.unique and layout.matches(rows, cols, (n_frames * n_dofs, n_cols))
    assert not layout.matches(rows, cols, (n_frames * n_dofs, n_cols + 1))
    expected = torch.zeros(3 * n_frames, n_cols)
    for f in range(n_frames):
        for dof, position in enumerate(free_positions.tolist()):
            if position >= 0:
                expected[position * n_frames + f] = dense[f * n_dofs + dof]
    matrix, transpose = layout.matrices(values)
    assert torch.equal(matrix.to_dense(), expected)
    assert torch.equal(transpose.to_dense(), expected.T)
    twice = FreeMatrixLayout(torch.cat([rows, rows[:1]]), torch.cat([cols, cols[:1]]),
                             (n_frames * n_dofs, n_cols), n_frames, free_positions, 3)
    kept = free_positions[rows[0] % n_dofs] >= 0
    assert twice.unique == (not bool(kept))
