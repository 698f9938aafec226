"""Stacked residuals ``R(theta) = [sqrt(w_1) r_1(theta); sqrt(w_2) r_2(theta); ...]``.

A penalised least-squares problem ``sum_i w_i / 2 ||r_i(theta)||^2`` is itself a least
squares problem ``1/2 ||R(theta)||^2``, so the existing Gauss-Newton and
Levenberg-Marquardt solvers minimise it unchanged once the blocks are stacked into one
residual object with the interface they use (``linearize(theta)`` returning ``r``,
``norm``, ``jvp``, ``vjp``; ``noise_level``; ``projector(theta)``; ``value(theta)``).

Split Bregman's inner problem ``mu/2 ||r(theta)||^2 + beta/2 ||D theta - t||^2`` is such
a stack of the (non-linear) model residual and a :class:`LinearResidual`; the linear
block costs sparse products only, never a solve.

:class:`CachedResidual` keeps the linearisations of the last few points: an outer loop
that hands the end point of one inner solve to the next (split Bregman) re-linearises
there for free instead of running the simulator again, so every distinct parameter
vector is simulated (and factorised) once.

Dense Jacobians (few parameters): a stack provides ``jacobian`` when every block does
(a :class:`LinearResidual` always does); its linearisation's ``jacobian()`` is the
weighted stack of the blocks' Jacobians and ``use_dense()`` makes its products matrix
products, as for :class:`~torchfit.residual.Linearization`.
"""
from __future__ import annotations

import math
from typing import Callable, Protocol, Sequence

import torch
from torch import Tensor

from .preconditioners import compressed_rows


class LinearizationLike(Protocol):
    theta: Tensor
    r: Tensor
    norm: float

    def jvp(self, v: Tensor) -> Tensor: ...

    def vjp(self, w: Tensor) -> Tensor: ...


class ResidualLike(Protocol):
    noise_level: float | None

    def linearize(self, theta: Tensor) -> LinearizationLike: ...

    def value(self, theta: Tensor) -> Tensor: ...

    def projector(self, theta: Tensor) -> Callable[[Tensor], Tensor] | None: ...


def _sparse(matrix: Tensor) -> Tensor:
    if matrix.layout == torch.sparse_coo:
        return matrix.coalesce()
    if matrix.layout == torch.strided:
        return matrix.to_sparse().coalesce()
    return matrix.to_sparse_coo().coalesce()


class _LinearLinearization:
    def __init__(self, owner: "LinearResidual", theta: Tensor) -> None:
        self._owner = owner
        self.theta = theta.detach()
        self.r = owner.value(self.theta)
        self.norm = float(torch.linalg.vector_norm(self.r))
        self.dense = False

    def jacobian(self) -> Tensor:
        return self._owner.jacobian(self.theta)

    def use_dense(self) -> "_LinearLinearization":
        self.dense = True       # the sparse products stay: exact and cheaper
        return self

    def jvp(self, v: Tensor) -> Tensor:
        return self._owner.matvec(v)

    def vjp(self, w: Tensor) -> Tensor:
        return self._owner.rmatvec(w)


class LinearResidual:
    """``r(theta) = A theta - target`` for a (sparse) matrix ``A``; products are exact and free.

    Args:
        A: ``(m, n)`` sparse (COO/CSR) or dense matrix.
        target: ``(m,)`` or ``None`` (zeros). May be replaced between solves
            (:attr:`target` is a plain attribute).
    """

    noise_level = None

    def __init__(self, A: Tensor, target: Tensor | None = None) -> None:
        self.A = _sparse(A)
        self.At = self.A.t().coalesce()
        # CSR copies for the products (one per CGLS iteration; see compressed_rows)
        self._A_rows, self._At_rows = compressed_rows(self.A), compressed_rows(self.At)
        self.target = target if target is not None else self.A.new_zeros(self.A.shape[0])
        self._dense: Tensor | None = None

    def jacobian(self, theta: Tensor) -> Tensor:
        """``A`` as a dense ``(m, n)`` matrix (made once), whatever ``theta``."""
        if self._dense is None:
            self._dense = self.A.to_dense()
        return self._dense

    @property
    def size(self) -> int:
        return int(self.A.shape[0])

    def matvec(self, v: Tensor) -> Tensor:
        return torch.mv(self._A_rows, v)

    def rmatvec(self, w: Tensor) -> Tensor:
        return torch.mv(self._At_rows, w)

    def value(self, theta: Tensor) -> Tensor:
        return self.matvec(theta.detach()) - self.target

    def linearize(self, theta: Tensor) -> _LinearLinearization:
        return _LinearLinearization(self, theta)

    def projector(self, theta: Tensor) -> None:
        return None


class CachedResidual:
    """A residual that remembers the linearisations of the last few points it was asked for.

    ``linearize(theta)`` at one of the ``size`` most recent points (``torch.equal``)
    returns the stored object: no simulation, no factorisation. An outer loop that
    hands the end point of one inner solve to the next re-linearises there for free,
    also when the inner solver tried (and rejected) other points after accepting it.
    Everything else is delegated.

    Attributes:
        evaluations: number of linearisations actually computed, a counter the tests
            compare with the solve counters.
    """

    def __init__(self, residual: ResidualLike, size: int = 3) -> None:
        self.residual = residual
        self.noise_level = residual.noise_level
        self.jacobian = getattr(residual, "jacobian", None)
        self.size = max(1, int(size))
        self._recent: list[LinearizationLike] = []
        self.evaluations = 0

    def _find(self, theta: Tensor) -> LinearizationLike | None:
        for lin in reversed(self._recent):
            if lin.theta.shape == theta.shape and torch.equal(lin.theta, theta):
                return lin
        return None

    def linearize(self, theta: Tensor) -> LinearizationLike:
        found = self._find(theta)
        if found is not None:
            self.restore(found)
            return found
        lin = self.residual.linearize(theta)
        self.evaluations += 1
        self.restore(lin)
        return lin

    def restore(self, lin: LinearizationLike) -> None:
        """Make ``lin`` (a linearisation of this residual) the most recent one."""
        self._recent = [x for x in self._recent if x is not lin][-(self.size - 1):] \
            if self.size > 1 else []
        self._recent.append(lin)

    def value(self, theta: Tensor) -> Tensor:
        found = self._find(theta)
        return found.r if found is not None else self.residual.value(theta)

    def projector(self, theta: Tensor) -> Callable[[Tensor], Tensor] | None:
        return self.residual.projector(theta)


class _ShiftedLinearization:
    """A linearisation with ``r - shift`` in place of ``r`` (same Jacobian)."""

    def __init__(self, lin: LinearizationLike, shift: Tensor) -> None:
        self._lin = lin
        self.theta = lin.theta
        self.r = lin.r - shift
        self.norm = float(torch.linalg.vector_norm(self.r))

    @property
    def dense(self) -> bool:
        return bool(getattr(self._lin, "dense", False))

    def jacobian(self) -> Tensor:
        return self._lin.jacobian()  # type: ignore[attr-defined]

    def use_dense(self) -> "_ShiftedLinearization":
        self._lin.use_dense()  # type: ignore[attr-defined]
        return self

    def jvp(self, v: Tensor) -> Tensor:
        return self._lin.jvp(v)

    def vjp(self, w: Tensor) -> Tensor:
        return self._lin.vjp(w)


class ShiftedResidual:
    """``r(theta) - shift`` for a residual ``r`` and a constant ``(m,)`` ``shift``.

    Split Bregman's data-side Bregman variable (``r(theta) = e`` in place of ``r = 0``,
    "adding back the residual"). The wrapped residual's linearisations (and their cache)
    are reused as they are; only ``r`` and ``norm`` are shifted.
    """

    noise_level = None

    def __init__(self, residual: ResidualLike, shift: Tensor) -> None:
        self.residual = residual
        self.shift = shift
        self.jacobian = getattr(residual, "jacobian", None)

    def linearize(self, theta: Tensor) -> _ShiftedLinearization:
        return _ShiftedLinearization(self.residual.linearize(theta), self.shift)

    def value(self, theta: Tensor) -> Tensor:
        return self.residual.value(theta) - self.shift

    def projector(self, theta: Tensor) -> Callable[[Tensor], Tensor] | None:
        return self.residual.projector(theta)


class StackedLinearization:
    """Linearisation of a :class:`StackedResidual` at one ``theta``."""

    def __init__(self, parts: Sequence[LinearizationLike], scales: Sequence[float],
                 theta: Tensor) -> None:
        self.parts = list(parts)
        self.scales = list(scales)
        self.theta = theta.detach()
        self.sizes = [int(p.r.numel()) for p in self.parts]
        self.r = torch.cat([s * p.r for s, p in zip(self.scales, self.parts)])
        self.norm = float(torch.linalg.vector_norm(self.r))
        self.dense = False
        self._J: Tensor | None = None

    def jacobian(self) -> Tensor:
        """``[sqrt(w_1) J_1; ...]`` dense ``(sum m_i, n)`` (the blocks' own, computed once)."""
        if self._J is None:
            self._J = torch.cat([s * p.jacobian().to(self.r)  # type: ignore[attr-defined]
                                 for s, p in zip(self.scales, self.parts)])
        return self._J

    def use_dense(self) -> "StackedLinearization":
        """From now on ``jvp``/``vjp`` are products with :meth:`jacobian`."""
        self.jacobian()
        self.dense = True
        return self

    def jvp(self, v: Tensor) -> Tensor:
        if self.dense:
            assert self._J is not None
            return self._J @ v.to(self._J)
        return torch.cat([s * p.jvp(v) for s, p in zip(self.scales, self.parts)])

    def vjp(self, w: Tensor) -> Tensor:
        if self.dense:
            assert self._J is not None
            return self._J.T @ w.to(self._J)
        out = None
        for s, p, w_i in zip(self.scales, self.parts, torch.split(w, self.sizes)):
            term = s * p.vjp(w_i)
            out = term if out is None else out + term
        assert out is not None
        return out


class StackedResidual:
    """``R(theta) = [sqrt(w_1) r_1(theta); ...]``, minimised as ``1/2 ||R||^2``.

    Args:
        blocks: residuals (each with ``linearize``/``value``/``projector``).
        weights: ``w_i > 0`` per block.
        projector_from: index of the block whose ``projector`` (gauge) the stack uses;
            the caller guarantees the other blocks do not depend on that direction
            (difference operators annihilate the constant gauge of ``theta = log k``).

    The stack's ``noise_level`` is ``None``: a penalised problem has no discrepancy level
    of its own, its solvers stop on relative decrease.
    """

    noise_level = None

    def __init__(self, blocks: Sequence[ResidualLike], weights: Sequence[float],
                 projector_from: int | None = 0) -> None:
        if len(blocks) != len(weights) or not blocks:
            raise ValueError("need one weight per block and at least one block")
        for w in weights:
            if not (w > 0 and math.isfinite(w)):
                raise ValueError(f"block weights must be positive and finite, got {w}")
        self.blocks = list(blocks)
        self.weights = [float(w) for w in weights]
        self.projector_from = projector_from

    @property
    def scales(self) -> list[float]:
        return [math.sqrt(w) for w in self.weights]

    @property
    def jacobian(self) -> Callable[[Tensor], Tensor] | None:
        """``theta -> [sqrt(w_1) J_1(theta); ...]`` when every block has a ``jacobian``."""
        parts = [getattr(b, "jacobian", None) for b in self.blocks]
        if any(part is None for part in parts):
            return None

        def stacked(theta: Tensor) -> Tensor:
            return torch.cat([s * part(theta) for s, part in zip(self.scales, parts)])

        return stacked

    def linearize(self, theta: Tensor) -> StackedLinearization:
        theta = theta.detach()
        return StackedLinearization([b.linearize(theta) for b in self.blocks], self.scales, theta)

    def value(self, theta: Tensor) -> Tensor:
        return torch.cat([s * b.value(theta) for s, b in zip(self.scales, self.blocks)])

    def projector(self, theta: Tensor) -> Callable[[Tensor], Tensor] | None:
        if self.projector_from is None:
            return None
        return self.blocks[self.projector_from].projector(theta)


__all__ = ["CachedResidual", "LinearResidual", "ShiftedResidual", "StackedLinearization",
           "StackedResidual"]
