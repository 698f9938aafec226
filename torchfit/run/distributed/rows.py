"""A dense Jacobian whose row blocks stay on their ranks: the products the dense path needs.

Under ``torchrun`` (:mod:`.split`) every rank computes the rows of ``J = d forward /
d theta`` of its own poses, ``(P_rank n_obs 3, n)`` (the frames that repeat a pose share its
rows: ``J^T J`` weights them by their frame count, ``J^T w`` takes ``w`` summed per pose,
``J x`` is expanded to every frame on rank 0), and keeps them (:class:`RowStore`:
the two most recent Jacobians, by id). Rank 0's :class:`DistributedRows` stands for the
whole ``(m, n)`` matrix where the solvers expect a dense ``J``
(:class:`~torchfit.residual.Linearization`, ``DenseNormalEquations``, the identifiability
report) and supports exactly the products they form:

- ``J.T @ J``: the Gram matrix ``J^T J`` ``(n, n)``, each rank's ``J_k^T J_k``;
- ``J.T @ w``: ``J^T w`` ``(n,)`` or ``(n, c)``, each rank's ``J_k^T w_k`` of its rows of ``w``;
- ``J @ x``: ``J x`` ``(m,)`` or ``(m, c)``, each rank's rows, concatenated in frame order;
- :meth:`DistributedRows.full` (the whole matrix on rank 0: tests, small problems only).

The partial sums are gathered to rank 0 and added there in rank order: the traffic of an
all-reduce (``n^2`` doubles per rank for the Gram matrix, 295 KB for the arm's 192
parameters, against 110 MB of rows per rank when ``J`` was gathered) with a fixed order of
summation, so a run is bit-reproducible for a given number of processes (an exact resume),
and equal to the one-process run to round-off (measured: ``docs/notes/distributed.md``).
Anything else a tensor would allow raises ``TypeError``: a new use of ``J`` in the solvers
must be added here, not silently gathered.
"""
from __future__ import annotations

from typing import Any, Callable

import torch
from torch import Tensor

from .channel import FULL, GRAM, MATVEC, RMATVEC


class RowStore:
    """This rank's rows of the most recent Jacobians, by id (``keep`` of them)."""

    def __init__(self, keep: int = 2) -> None:
        self.keep = keep
        self.blocks: dict[int, Tensor] = {}
        self.next_id = 0        # rank 0's: the id of its next Jacobian, sent with the command

    def add(self, rows: Tensor, ident: int) -> None:
        """Keep ``rows`` ``(m_rank, n)`` as Jacobian ``ident`` (rank 0's number), dropping
        the oldest beyond ``keep``."""
        self.next_id = max(self.next_id, ident + 1)
        self.blocks[ident] = rows
        for old in sorted(self.blocks)[:-self.keep]:
            del self.blocks[old]

    def get(self, ident: int) -> Tensor:
        if ident not in self.blocks:
            raise RuntimeError(f"the distributed Jacobian {ident} is no longer kept (only the "
                               f"{self.keep} most recent are); linearise again")
        return self.blocks[ident]


def local_product(code: int, rows: Tensor, operand: Tensor | None,
                  row_index: Tensor, weights: Tensor | None = None) -> Tensor:
    """This rank's part of a product: ``J_k x`` (its rows), ``J_k^T w_k`` (``w_k``: its
    rows ``row_index`` (int64) of ``w``), ``J_k^T W J_k`` (``weights``: per row, how many frames
    share it; ``None``: one each) or the rows themselves."""
    if code == MATVEC:
        assert operand is not None
        return rows @ operand.to(rows)
    if code == RMATVEC:
        assert operand is not None
        return rows.T @ operand[row_index.to(operand.device)].to(rows)
    if code == GRAM:
        return rows.T @ (rows if weights is None else rows * weights[:, None])
    if code == FULL:
        return rows
    raise ValueError(f"unknown row command {code}")


class DistributedRows:
    """Rank 0's handle of a Jacobian ``(m, n)`` whose rows stay on the ranks (module
    docstring). ``exchange(code, ident, operand)`` runs a product on every rank and returns
    the reduced result on rank 0 (:meth:`.split.FrameSplit.row_product`)."""

    def __init__(self, ident: int, shape: tuple[int, int], dtype: torch.dtype,
                 device: torch.device, exchange: Callable[[int, int, Tensor | None], Tensor]
                 ) -> None:
        self.ident = ident
        self.shape = torch.Size(shape)
        self.dtype = dtype
        self.device = device
        self._exchange = exchange

    # -- what a dense J is asked for -------------------------------------------------------
    def detach(self) -> "DistributedRows":
        return self

    def to(self, *args: Any, **kwargs: Any) -> "DistributedRows":
        """Itself where the dtype and device are already these (the products convert their
        operands); a conversion of the rows themselves is not supported."""
        target = args[0] if args else kwargs.get("dtype")
        dtype = target.dtype if isinstance(target, Tensor) else kwargs.get("dtype", target)
        if dtype is not None and not isinstance(dtype, torch.dtype):
            dtype = None
        if dtype not in (None, self.dtype):
            raise TypeError(f"a distributed Jacobian stays {self.dtype}, asked for {dtype}")
        return self

    def numel(self) -> int:
        return int(self.shape[0] * self.shape[1])

    def dim(self) -> int:
        return 2

    @property
    def T(self) -> "_Transposed":
        return _Transposed(self)

    def __matmul__(self, other: Any) -> Tensor:
        if not isinstance(other, Tensor):
            return NotImplemented
        if other.shape[0] != self.shape[1]:
            raise ValueError(f"J @ x: x has {other.shape[0]} rows, J {self.shape[1]} columns")
        return self._exchange(MATVEC, self.ident, other.detach())

    def gram(self) -> Tensor:
        """``J^T J`` ``(n, n)`` (summed over the ranks in rank order)."""
        return self._exchange(GRAM, self.ident, None)

    def full(self) -> Tensor:
        """The whole ``(m, n)`` matrix on rank 0 (gathered: for tests and small problems)."""
        return self._exchange(FULL, self.ident, None)

    def __repr__(self) -> str:
        return f"DistributedRows(id={self.ident}, shape={tuple(self.shape)})"


class _Transposed:
    """``J.T`` of a :class:`DistributedRows`: ``J.T @ J`` and ``J.T @ w`` only."""

    def __init__(self, rows: DistributedRows) -> None:
        self.rows = rows

    def __matmul__(self, other: Any) -> Tensor:
        if other is self.rows:
            return self.rows.gram()
        if not isinstance(other, Tensor):
            raise TypeError("J.T @ ... of a distributed Jacobian takes J itself or a tensor")
        if other.shape[0] != self.rows.shape[0]:
            raise ValueError(f"J^T w: w has {other.shape[0]} rows, J {self.rows.shape[0]}")
        return self.rows._exchange(RMATVEC, self.rows.ident, other.detach())
