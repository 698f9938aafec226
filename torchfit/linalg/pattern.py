"""Sparsity patterns: CSR structure built once per mesh, values recomputed.

Element assembly produces a list of (row, col, value) contributions with duplicates
(every element adds its local matrix). :class:`SparsePattern` turns the (row, col)
lists into a CSR structure once and keeps the scatter index that sums the
contributions into CSR slots, so that assembling new values is one ``index_add``
(vectorised, differentiable, batched over frames, device-agnostic).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch
from torch import Tensor


class SparsePattern:
    """CSR pattern of an ``n_rows x n_cols`` matrix.

    Args:
        rows, cols: ``(n_contrib,)`` integer row/column of every element contribution
            (duplicates allowed; they are summed).
        shape: ``(n_rows, n_cols)``.

    Attributes:
        crow_indices: ``(n_rows + 1,)`` CSR row pointer.
        col_indices: ``(nnz,)`` CSR column of every stored entry.
        row_indices: ``(nnz,)`` row of every stored entry (expanded ``crow_indices``).
        scatter: ``(n_contrib,)`` CSR slot of every contribution.
    """

    def __init__(self, rows: Tensor | np.ndarray, cols: Tensor | np.ndarray,
                 shape: tuple[int, int]) -> None:
        rows_np = np.asarray(torch.as_tensor(rows).cpu(), dtype=np.int64)
        cols_np = np.asarray(torch.as_tensor(cols).cpu(), dtype=np.int64)
        if rows_np.shape != cols_np.shape or rows_np.ndim != 1:
            raise ValueError(f"rows and cols must be 1-D of equal length, got "
                             f"{rows_np.shape} and {cols_np.shape}")
        n_rows, n_cols = int(shape[0]), int(shape[1])
        if rows_np.size and (rows_np.min() < 0 or rows_np.max() >= n_rows
                             or cols_np.min() < 0 or cols_np.max() >= n_cols):
            raise ValueError(f"pattern index out of range for shape {shape}")
        self.shape = (n_rows, n_cols)
        # Sort contributions by (row, col); unique pairs become CSR slots in order.
        key = rows_np * n_cols + cols_np
        unique_keys, scatter = np.unique(key, return_inverse=True)
        row_of_slot = unique_keys // n_cols
        col_of_slot = unique_keys % n_cols
        crow = np.zeros(n_rows + 1, dtype=np.int64)
        np.add.at(crow, row_of_slot + 1, 1)
        np.cumsum(crow, out=crow)
        self.nnz = int(unique_keys.size)
        self.n_contrib = int(key.size)
        self.crow_indices = torch.from_numpy(crow)
        self.col_indices = torch.from_numpy(col_of_slot.astype(np.int64))
        self.row_indices = torch.from_numpy(row_of_slot.astype(np.int64))
        self.scatter = torch.from_numpy(scatter.reshape(-1).astype(np.int64))
        self._device_cache: dict[torch.device, tuple[Tensor, ...]] = {}

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
            (values.detach().cpu().numpy(), self.col_indices.numpy(),
             self.crow_indices.numpy()), shape=self.shape)

    def to_torch(self, values: Tensor) -> Tensor:
        """One matrix as a ``torch.sparse_csr_tensor`` on the device of ``values``."""
        crow, col, _, _ = self._indices(values.device)
        return torch.sparse_csr_tensor(crow, col, values, size=self.shape,
                                       check_invariants=False)

    def submatrix(self, keep_rows: Tensor, keep_cols: Tensor) -> tuple["SparsePattern", Tensor]:
        """Pattern of ``A[keep_rows][:, keep_cols]`` and the CSR slots it takes.

        Used once per mesh to drop Dirichlet rows/columns: afterwards
        ``sub_values = values[..., slots]``.

        Args:
            keep_rows, keep_cols: sorted 1-D index tensors of the rows/cols kept.
        Returns:
            ``(pattern, slots)`` with ``slots`` of shape ``(sub.nnz,)``.
        """
        row_map = -np.ones(self.shape[0], dtype=np.int64)
        row_map[np.asarray(keep_rows.cpu())] = np.arange(len(keep_rows))
        col_map = -np.ones(self.shape[1], dtype=np.int64)
        col_map[np.asarray(keep_cols.cpu())] = np.arange(len(keep_cols))
        new_rows = row_map[self.row_indices.numpy()]
        new_cols = col_map[self.col_indices.numpy()]
        kept = np.nonzero((new_rows >= 0) & (new_cols >= 0))[0]
        sub = SparsePattern(new_rows[kept], new_cols[kept], (len(keep_rows), len(keep_cols)))
        # The kept slots are already sorted by (row, col) in the new numbering, so the
        # sub-pattern's scatter is the identity and ``kept`` lists its CSR slots in order.
        assert np.array_equal(sub.scatter.numpy(), np.arange(kept.size))
        return sub, torch.from_numpy(kept)

    def __repr__(self) -> str:
        return f"SparsePattern(shape={self.shape}, nnz={self.nnz})"
