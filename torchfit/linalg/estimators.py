"""Norm estimates of a linear operator known only through its products.

Each function takes the products ``v -> A v`` and/or ``w -> A^T w`` (an ``(m, n)``
operator: a Jacobian, a difference operator) and returns a float or a tensor; none forms
``A``. Their cost is counted in products: ``iterations`` pairs, ``probes`` products.
Random probes are Rademacher vectors (entries ``+-1``) from a seeded or given
``torch.Generator`` on the CPU, cast to the operand's dtype and device, so an estimate is
reproducible bit for bit.
"""
from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor

Product = Callable[[Tensor], Tensor]


def power_norm_sq(matvec: Product, rmatvec: Product, v0: Tensor, iterations: int) -> float:
    """``||A||_2^2``, the largest eigenvalue of ``A^T A``, by power iteration from ``v0``.

    ``iterations`` products ``A^T A v``; the estimate is ``||A^T A v||`` of the last
    normalised ``v`` (from below). A zero or non-finite product ends the iteration with
    the estimate so far (0.0 when it is the first).
    """
    v = v0 / torch.linalg.vector_norm(v0)
    estimate = 0.0
    for _ in range(iterations):
        w = rmatvec(matvec(v))
        norm = float(torch.linalg.vector_norm(w))
        if not math.isfinite(norm) or norm == 0.0:
            return estimate
        estimate = norm
        v = w / norm
    return estimate


def frobenius_norm_sq(matvec: Product, n: int, like: Tensor, probes: int) -> float:
    """Hutchinson's estimate of ``||A||_F^2 = E ||A v||^2`` over ``probes`` Rademacher
    ``v`` of length ``n`` (generator seeded with 0; ``like`` gives dtype and device)."""
    generator = torch.Generator().manual_seed(0)
    total = 0.0
    for _ in range(probes):
        v = (torch.randint(0, 2, (n,), generator=generator) * 2 - 1).to(like)
        total += float(torch.linalg.vector_norm(matvec(v))) ** 2
    return total / probes


def column_norms(rmatvec: Product, rows_like: Tensor, columns_like: Tensor, probes: int,
                 generator: torch.Generator) -> Tensor:
    """The column norms ``||A e_j||`` estimated from ``probes`` products ``A^T w``.

    ``E[(A^T w)_j^2] = ||A e_j||^2`` for Rademacher ``w`` (shape and dtype of
    ``rows_like``, drawn from ``generator``, which advances); relative error about
    ``(2 probes)^{-1/2}``. Returns a tensor like ``columns_like``.
    """
    squares = torch.zeros_like(columns_like)
    for _ in range(probes):
        signs = torch.randint(0, 2, rows_like.shape, generator=generator) * 2 - 1
        squares += rmatvec(signs.to(rows_like)) ** 2
    return (squares / probes).sqrt()


__all__ = ["column_norms", "frobenius_norm_sq", "power_norm_sq"]
