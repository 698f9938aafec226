"""Sparsity patterns: CSR structure built once per mesh, values recomputed.

Element assembly produces a list of (row, col, value) contributions with duplicates
(every element adds its local matrix). :class:`SparsePattern` turns the (row, col)
lists into a CSR structure once and keeps the scatter index that sums the
contributions into CSR slots, so that assembling new values is one ``index_add``
(vectorised, differentiable, batched over frames, device-agnostic).

Building a pattern is vectorised torch on the device of its inputs: ``torch.unique`` of
the (row, col) keys for arbitrary contributions, and, for sums of dense local matrices on blocks (every
vertex of a finite element carrying ``d`` dofs), :meth:`SparsePattern.from_dense_blocks`,
which sorts only the block pairs (``(d+1)^2`` per tetrahedron instead of ``(4 d)^2``)
and computes every slot by arithmetic. The Dirichlet sub-pattern
(:meth:`SparsePattern.submatrix`) is a gather and a mask, no sort.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch
from torch import Tensor


def csr_matrix(crow: Tensor, col: Tensor, values: Tensor, size: tuple[int, int]) -> Tensor:
    """``torch.sparse_csr_tensor`` without invariant checks (the structure is built here,
    sorted and in range) and without torch's one-time "beta" warning, which would reach
    every user of a product built on it (torchfit changes no process-wide filter)."""
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta",
                                category=UserWarning)
        return torch.sparse_csr_tensor(crow, col, values, size, check_invariants=False)


def _crow(sorted_rows: Tensor, n_rows: int) -> Tensor:
    """CSR row pointers of row indices sorted ascending."""
    counts = torch.bincount(sorted_rows, minlength=n_rows)
    return torch.cat([counts.new_zeros(1), torch.cumsum(counts, 0)])


def coo_to_csr(rows: Tensor, cols: Tensor, values: Tensor, size: tuple[int, int]) -> Tensor:
    """CSR ``(size)`` of COO entries (duplicates summed), built once per operator."""
    coo = torch.sparse_coo_tensor(torch.stack([rows, cols]), values, size,
                                  check_invariants=False).coalesce()
    r, c = coo.indices()
    return csr_matrix(_crow(r, size[0]), c.contiguous(), coo.values(), size)


def _as_index(values: Tensor | np.ndarray | list, device: torch.device | None = None) -> Tensor:
    """A 1-D int64 tensor (numpy and lists become CPU tensors)."""
    index = torch.as_tensor(np.asarray(values) if not isinstance(values, Tensor) else values,
                            device=device)
    return index.to(torch.long)


def _exclusive_cumsum(counts: Tensor) -> Tensor:
    """``[0, c0, c0 + c1, ...]`` (length ``len(counts) + 1``)."""
    out = torch.zeros(counts.numel() + 1, dtype=torch.long, device=counts.device)
    torch.cumsum(counts, 0, out=out[1:])
    return out


def _check_range(rows: Tensor, cols: Tensor, shape: tuple[int, int]) -> None:
    if rows.numel() and (int(rows.min()) < 0 or int(rows.max()) >= shape[0]
                         or int(cols.min()) < 0 or int(cols.max()) >= shape[1]):
        raise ValueError(f"pattern index out of range for shape {shape}")


class SparsePattern:
    """CSR pattern of an ``n_rows x n_cols`` matrix.

    Args:
        rows, cols: ``(n_contrib,)`` integer row/column of every element contribution
            (duplicates allowed; they are summed). Tensors stay on their device (the
            pattern is built and kept there); numpy arrays and lists are used on the CPU.
        shape: ``(n_rows, n_cols)``.

    Attributes (int64, on the device the pattern was built on):
        crow_indices: ``(n_rows + 1,)`` CSR row pointer.
        col_indices: ``(nnz,)`` CSR column of every stored entry.
        row_indices: ``(nnz,)`` row of every stored entry (expanded ``crow_indices``).
        scatter: ``(n_contrib,)`` CSR slot of every contribution.
        device: where the index tensors live (copies for other devices are made once,
            on first use, by the methods taking values there).
    """

    def __init__(self, rows: Tensor | np.ndarray, cols: Tensor | np.ndarray,
                 shape: tuple[int, int]) -> None:
        rows_t = _as_index(rows)
        cols_t = _as_index(cols, rows_t.device)
        if rows_t.shape != cols_t.shape or rows_t.dim() != 1:
            raise ValueError(f"rows and cols must be 1-D of equal length, got "
                             f"{tuple(rows_t.shape)} and {tuple(cols_t.shape)}")
        n_rows, n_cols = int(shape[0]), int(shape[1])
        _check_range(rows_t, cols_t, (n_rows, n_cols))
        # Sort contributions by (row, col); unique pairs become CSR slots in order.
        key = rows_t * n_cols + cols_t
        unique_keys, scatter = torch.unique(key, sorted=True, return_inverse=True)
        self._set(unique_keys // n_cols, unique_keys % n_cols, scatter.reshape(-1),
                  (n_rows, n_cols))

    def _set(self, row_of_slot: Tensor, col_of_slot: Tensor, scatter: Tensor,
             shape: tuple[int, int]) -> None:
        """Store a CSR structure given row and column of every slot (sorted by row, then
        column) and the slot of every contribution."""
        self.shape = (int(shape[0]), int(shape[1]))
        counts = torch.bincount(row_of_slot, minlength=self.shape[0])
        self.nnz = int(row_of_slot.numel())
        self.n_contrib = int(scatter.numel())
        self.crow_indices = _exclusive_cumsum(counts)
        self.col_indices = col_of_slot
        self.row_indices = row_of_slot
        self.scatter = scatter
        self.device = row_of_slot.device
        self._device_cache: dict[torch.device, tuple[Tensor, ...]] = {}

    @classmethod
    def _from_sorted_slots(cls, rows: Tensor, cols: Tensor, shape: tuple[int, int]
                           ) -> "SparsePattern":
        """A pattern whose contributions are its slots: ``(rows, cols)`` already distinct
        and sorted by (row, col) (no sort; the scatter is the identity)."""
        pattern = cls.__new__(cls)
        pattern._set(rows, cols, torch.arange(rows.numel(), device=rows.device), shape)
        return pattern

    @classmethod
    def from_dense_blocks(cls, groups: Tensor | np.ndarray, block_size: int,
                          n_blocks: int) -> "SparsePattern":
        """The pattern of a sum of dense local matrices on blocks of ``block_size``
        consecutive rows/columns (``n_blocks * block_size`` square).

        Row ``g`` of ``groups`` ``(m, k)`` lists the blocks that local matrix ``g`` couples
        (``(k * block_size)^2`` entries, local index ``a * block_size + i`` for block
        ``groups[g, a]``, component ``i``). Contributions are ordered as those local
        matrices flattened row-major: ``(g, a, i, b, j)``, the order of
        ``K.reshape(m, -1)`` for local matrices ``K`` ``(m, k bs, k bs)``. The result is
        identical (CSR and scatter) to ``SparsePattern(rows, cols, shape)`` with the
        expanded rows and columns, but only the ``m k^2`` block pairs are sorted: the slot
        of entry ``(i, j)`` of block pair ``(A, B)`` is
        ``bs^2 start[A] + i bs deg[A] + bs pos(B in row A) + j`` (``deg[A]`` blocks in
        block row ``A``, the first at block slot ``start[A]``). Vectorised torch on the
        device of ``groups``.
        """
        groups_t = _as_index(groups)
        if groups_t.dim() != 2:
            raise ValueError(f"groups must be (m, k) block indices, got {tuple(groups_t.shape)}")
        bs, n_blocks = int(block_size), int(n_blocks)
        if bs < 1:
            raise ValueError(f"block_size must be >= 1, got {block_size}")
        device = groups_t.device
        m, k = groups_t.shape
        n = n_blocks * bs
        if groups_t.numel() and (int(groups_t.min()) < 0 or int(groups_t.max()) >= n_blocks):
            raise ValueError(f"block index out of range [0, {n_blocks})")
        block_a = groups_t[:, :, None].expand(m, k, k)
        block_b = groups_t[:, None, :].expand(m, k, k)
        unique_keys, pair_slot = torch.unique(block_a * n_blocks + block_b, sorted=True,
                                              return_inverse=True)
        pair_row = unique_keys // n_blocks
        pair_col = unique_keys % n_blocks
        degree = torch.bincount(pair_row, minlength=n_blocks)
        start = _exclusive_cumsum(degree)[:-1]
        position = torch.arange(unique_keys.numel(), device=device) - start[pair_row]
        # slot of (pair p, i, j) = base[p] + i * bs * deg[row p] + j
        base = bs * bs * start[pair_row] + bs * position                  # (P,)
        row_stride = bs * degree[pair_row]                                 # (P,)
        comp = torch.arange(bs, device=device)
        # CSR arrays in order: scalar row A bs + i holds the columns of block row A's
        # pairs, (pair_col[p] bs + j for p in the row, for j), the same for every i
        row_length = (bs * degree).repeat_interleave(bs)                    # (n,)
        crow = _exclusive_cumsum(row_length)
        nnz = int(crow[-1])
        row_of_slot = torch.repeat_interleave(torch.arange(n, device=device), row_length,
                                              output_size=nnz)
        columns = (pair_col[:, None] * bs + comp).reshape(-1)              # (P bs,) pair order
        block_row = torch.arange(n, device=device) // bs
        offset = start[block_row] * bs - crow[:-1]                         # per scalar row
        col_of_slot = columns[torch.arange(nnz, device=device)
                              + torch.repeat_interleave(offset, row_length, output_size=nnz)]
        # contributions (g, a, i, b, j)
        pair_slot = pair_slot.reshape(m, k, k)
        block_base = base[pair_slot]                                       # (m, a, b)
        block_stride = row_stride[pair_slot]                               # (m, a, b)
        scatter = (block_base[:, :, None, :, None]
                   + comp[None, None, :, None, None] * block_stride[:, :, None, :, None]
                   + comp[None, None, None, None, :])                      # (m, a, i, b, j)
        pattern = cls.__new__(cls)
        pattern._set(row_of_slot, col_of_slot, scatter.reshape(-1), (n, n))
        return pattern

    # -- index tensors on the device of the values --------------------------------
    def _indices(self, device: torch.device) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        if device not in self._device_cache:
            self._device_cache[device] = tuple(
                t.to(device) for t in (self.crow_indices, self.col_indices,
                                       self.row_indices, self.scatter))
        return self._device_cache[device]  # type: ignore[return-value]

    def assemble(self, contributions: Tensor) -> Tensor:
        """Sum element contributions into CSR values.

        Args:
            contributions: ``(..., n_contrib)`` values in the order of ``rows/cols``.
        Returns:
            ``(..., nnz)`` CSR values (differentiable w.r.t. the contributions).
        """
        if contributions.shape[-1] != self.n_contrib:
            raise ValueError(f"expected {self.n_contrib} contributions, got "
                             f"{contributions.shape[-1]}")
        scatter = self._indices(contributions.device)[3]
        out = contributions.new_zeros(*contributions.shape[:-1], self.nnz)
        return out.index_add(-1, scatter, contributions)

    def matvec(self, values: Tensor, x: Tensor) -> Tensor:
        """``A x`` in torch (differentiable in both, any device).

        Args:
            values: ``(nnz,)`` or ``(B, nnz)`` CSR values.
            x: ``(B, n_cols)`` or ``(n_cols,)``.
        Returns:
            ``(B, n_rows)`` (or ``(n_rows,)`` when both inputs are unbatched).
        """
        _, col, row, _ = self._indices(x.device)
        products = values * x[..., col]
        out = products.new_zeros(*products.shape[:-1], self.shape[0])
        return out.index_add(-1, row, products)

    def rmatvec(self, values: Tensor, y: Tensor) -> Tensor:
        """``A^T y`` with the same conventions as :meth:`matvec`."""
        _, col, row, _ = self._indices(y.device)
        products = values * y[..., row]
        out = products.new_zeros(*products.shape[:-1], self.shape[1])
        return out.index_add(-1, col, products)

    def diagonal(self, values: Tensor) -> Tensor:
        """Diagonal of the matrix, ``(..., min(shape))`` (zeros where not stored)."""
        _, col, row, _ = self._indices(values.device)
        on_diag = row == col
        out = values.new_zeros(*values.shape[:-1], min(self.shape))
        return out.index_add(-1, row[on_diag], values[..., on_diag])

    def to_scipy(self, values: Tensor) -> sp.csr_matrix:
        """One matrix (``values`` of shape ``(nnz,)``) as a scipy CSR matrix."""
        return sp.csr_matrix(
            (values.detach().cpu().numpy(), self.col_indices.cpu().numpy(),
             self.crow_indices.cpu().numpy()), shape=self.shape)

    def to_torch(self, values: Tensor) -> Tensor:
        """One matrix as a ``torch.sparse_csr_tensor`` on the device of ``values``."""
        crow, col, _, _ = self._indices(values.device)
        return torch.sparse_csr_tensor(crow, col, values, size=self.shape,
                                       check_invariants=False)

    def submatrix(self, keep_rows: Tensor, keep_cols: Tensor) -> tuple["SparsePattern", Tensor]:
        """Pattern of ``A[keep_rows][:, keep_cols]`` and the CSR slots it takes.

        Used once per mesh to drop Dirichlet rows/columns: afterwards
        ``sub_values = values[..., slots]``. A gather and a mask on the pattern's device
        (the kept slots are already in CSR order of the sub-matrix: no sort).

        Args:
            keep_rows, keep_cols: sorted 1-D index tensors of the rows/cols kept.
        Returns:
            ``(pattern, slots)`` with ``slots`` of shape ``(sub.nnz,)``, both on the
            pattern's device.
        """
        keep_rows_t = _as_index(keep_rows).to(self.device).reshape(-1)
        keep_cols_t = _as_index(keep_cols).to(self.device).reshape(-1)
        for name, keep, size in (("keep_rows", keep_rows_t, self.shape[0]),
                                 ("keep_cols", keep_cols_t, self.shape[1])):
            if keep.numel() and (int(keep.min()) < 0 or int(keep.max()) >= size):
                raise ValueError(f"{name} out of range [0, {size})")
            if keep.numel() > 1 and not bool((keep[1:] > keep[:-1]).all()):
                raise ValueError(f"{name} must be sorted and without duplicates")
        row_map = torch.full((self.shape[0],), -1, dtype=torch.long, device=self.device)
        row_map[keep_rows_t] = torch.arange(keep_rows_t.numel(), device=self.device)
        col_map = torch.full((self.shape[1],), -1, dtype=torch.long, device=self.device)
        col_map[keep_cols_t] = torch.arange(keep_cols_t.numel(), device=self.device)
        new_rows = row_map[self.row_indices]
        new_cols = col_map[self.col_indices]
        kept = torch.nonzero((new_rows >= 0) & (new_cols >= 0)).reshape(-1)
        # The kept slots are already sorted by (row, col) in the new numbering (the maps
        # are increasing), so the sub-pattern's scatter is the identity.
        sub = SparsePattern._from_sorted_slots(new_rows[kept], new_cols[kept],
                                               (keep_rows_t.numel(), keep_cols_t.numel()))
        return sub, kept

    def __repr__(self) -> str:
        return f"SparsePattern(shape={self.shape}, nnz={self.nnz})"


class FreeMatrixLayout:
    """The CSR structure of a frame-stacked matrix with some rows dropped and the kept rows
    renumbered, and of its transpose, built once per entry pattern.

    The matrix is given as COO entries ``(rows, cols)`` of shape ``(F * n_dofs, n_cols)``
    (row ``f * n_dofs + dof``, e.g. a model's ``dR/dparams``); ``free_positions``
    ``(n_dofs,)`` maps a dof to its row among the ``n_free`` kept ones (``-1``: dropped,
    e.g. a Dirichlet dof). The result has ``n_free * F`` rows, row ``position * F + f``.
    :meth:`matrices` then only gathers the values (two ``index_select``), where building
    CSR from COO entries each time costs more than a factorisation. ``unique`` is False
    when two entries share a position (the layout then does not sum them: do not use it).
    """

    def __init__(self, rows: Tensor, cols: Tensor, shape: tuple[int, int], n_frames: int,
                 free_positions: Tensor, n_free: int) -> None:
        self.rows, self.cols, self.shape = rows.clone(), cols.clone(), tuple(shape)
        n_dofs = shape[0] // n_frames
        frame = torch.div(rows, n_dofs, rounding_mode="floor")
        position = free_positions.to(rows.device)[rows % n_dofs]
        kept = torch.nonzero(position >= 0).reshape(-1)
        free_rows = position[kept] * n_frames + frame[kept]
        kept_cols = cols[kept]
        n_rows, n_cols = n_free * n_frames, shape[1]
        key = free_rows * n_cols + kept_cols
        self.unique = bool(torch.unique(key).numel() == key.numel())
        self.size = (n_rows, n_cols)
        order = torch.argsort(key)
        self.perm = kept[order]
        self.crow = _crow(free_rows[order], n_rows)
        self.col = kept_cols[order].contiguous()
        order_t = torch.argsort(kept_cols * n_rows + free_rows)
        self.perm_t = kept[order_t]
        self.crow_t = _crow(kept_cols[order_t], n_cols)
        self.col_t = free_rows[order_t].contiguous()

    def matches(self, rows: Tensor, cols: Tensor, shape: tuple[int, int]) -> bool:
        """Whether the entries ``(rows, cols)`` of ``shape`` are this layout's pattern."""
        return tuple(shape) == self.shape and rows.shape == self.rows.shape and \
            torch.equal(rows, self.rows) and torch.equal(cols, self.cols)

    def matrices(self, values: Tensor) -> tuple[Tensor, Tensor]:
        """The CSR matrix ``(n_free * F, n_cols)`` of the entries' ``values`` and its
        transpose."""
        matrix = csr_matrix(self.crow, self.col, values.index_select(0, self.perm), self.size)
        transpose = csr_matrix(self.crow_t, self.col_t, values.index_select(0, self.perm_t),
                               (self.size[1], self.size[0]))
        return matrix, transpose
