"""The differentiable sparse linear solve ``x = A(values)^{-1} b``.

One ``torch.autograd.Function`` (``setup_context`` style):

* forward: factorise ``A`` (or take the cached factor for these values) and solve;
* backward: one adjoint solve ``A^T lam = g``; ``dL/db = lam`` and
  ``dL/dvalues[e] = -lam[row_e] x[col_e]`` on the sparsity pattern;
* jvp: ``dx = A^{-1} (db - dA x)``, one solve with the same factor.

Factorisations are kept in a small :class:`FactorCache` keyed by the matrix values, so
every backward, jvp and further right-hand side at the same matrix reuses them.
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Any

import torch
from torch import Tensor

from .backends import Backend, Factor, get_backend
from .pattern import SparsePattern


class FactorCache:
    """Least-recently-used cache of factorisations keyed by (pattern, matrix values).

    A lookup compares values with ``torch.equal`` (O(nnz), far cheaper than any
    factorisation), so it is exact: a factor is reused only for the very same matrix.
    """

    def __init__(self, max_size: int = 2) -> None:
        self.max_size = max_size
        self._entries: OrderedDict[int, tuple[SparsePattern, Tensor, Factor]] = OrderedDict()
        self._next_key = 0

    def get(self, pattern: SparsePattern, values: Tensor, backend: Backend,
            symmetric: bool) -> Factor:
        for key, (pat, vals, factor) in self._entries.items():
            if pat is pattern and vals.shape == values.shape and vals.device == values.device \
                    and torch.equal(vals, values):
                self._entries.move_to_end(key)
                return factor
        factor = backend.factorize(pattern, values.detach(), symmetric)
        self._entries[self._next_key] = (pattern, values.detach().clone(), factor)
        self._next_key += 1
        while len(self._entries) > self.max_size:
            self._entries.popitem(last=False)
        return factor

    def clear(self) -> None:
        self._entries.clear()


DEFAULT_CACHE = FactorCache()


def _values_times_x(pattern: SparsePattern, dvalues: Tensor, x: Tensor) -> Tensor:
    """``dA x`` for ``x`` of shape ``(n,)`` or ``(n, c)``."""
    if x.dim() == 1:
        return pattern.matvec(dvalues, x)
    return pattern.matvec(dvalues, x.T).T


class _SparseSolve(torch.autograd.Function):
    @staticmethod
    def forward(values: Tensor, rhs: Tensor, pattern: SparsePattern, backend: Backend,
                symmetric: bool, cache: FactorCache) -> Tensor:  # type: ignore[override]
        factor = cache.get(pattern, values, backend, symmetric)
        return factor.solve(rhs).to(rhs.device)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple, output: Tensor) -> None:
        values, rhs, pattern, backend, symmetric, cache = inputs
        ctx.pattern = pattern
        # Keep the factor itself (not only the cache entry): backward must never refactorise.
        ctx.factor = cache.get(pattern, values.detach(), backend, symmetric)
        ctx.save_for_backward(output)
        ctx.save_for_forward(values, output)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad_x: Tensor) -> tuple:  # type: ignore[override]
        (x,) = ctx.saved_tensors
        lam = ctx.factor.solve(grad_x, transpose=True).to(grad_x.device)
        grad_values = None
        if ctx.needs_input_grad[0]:
            _, col, row, _ = ctx.pattern._indices(x.device)
            if x.dim() == 1:
                grad_values = -lam[row] * x[col]
            else:
                grad_values = -(lam[row] * x[col]).sum(dim=1)
        grad_rhs = lam if ctx.needs_input_grad[1] else None
        return grad_values, grad_rhs, None, None, None, None

    @staticmethod
    def jvp(ctx: Any, dvalues: Tensor | None, drhs: Tensor | None, *_: Any) -> Tensor:  # type: ignore[override]
        values, x = ctx.saved_tensors
        rhs_tangent = torch.zeros_like(x) if drhs is None else drhs.clone()
        if dvalues is not None:
            rhs_tangent = rhs_tangent - _values_times_x(ctx.pattern, dvalues, x)
        return ctx.factor.solve(rhs_tangent).to(x.device)


def sparse_solve(pattern: SparsePattern, values: Tensor, rhs: Tensor,
                 backend: str | Backend = "scipy", symmetric: bool = True,
                 cache: FactorCache | None = None) -> Tensor:
    """Differentiable solve of ``A x = rhs`` with ``A`` given by CSR ``values`` on ``pattern``.

    Args:
        pattern: the square CSR pattern of ``A``.
        values: ``(nnz,)`` CSR values (gradient flows to them on the pattern).
        rhs: ``(n,)`` or ``(n, c)`` right-hand side(s), sharing one factorisation.
        backend: ``'scipy'`` (CPU direct) or ``'cg'`` (torch, any device).
        symmetric: whether ``A`` is symmetric (SPD for ``'cg'``).
        cache: factor cache; defaults to a process-wide one of size 2.
    Returns:
        ``x`` with the shape of ``rhs``.
    """
    if pattern.shape[0] != pattern.shape[1]:
        raise ValueError(f"sparse_solve needs a square matrix, got {pattern.shape}")
    if values.shape != (pattern.nnz,):
        raise ValueError(f"values must have shape ({pattern.nnz},), got {tuple(values.shape)}")
    if rhs.shape[0] != pattern.shape[0] or rhs.dim() > 2:
        raise ValueError(f"rhs must be ({pattern.shape[0]},) or ({pattern.shape[0]}, c), "
                         f"got {tuple(rhs.shape)}")
    return _SparseSolve.apply(values, rhs, pattern, get_backend(backend), symmetric,
                              cache if cache is not None else DEFAULT_CACHE)
