"""Total variation over groups of the rows of a difference operator.

:func:`check_difference_operator` validates the sparse difference operator ``D`` that a
parameterisation hands over (solvers never build it), its row ``groups`` and an
``offset``; :class:`GroupTV` is ``TV(t) = sum_g ||t_g||_2`` with its proximal map
(group soft thresholding) and dual norm. Used by split Bregman and by the difference
preconditioners.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .base import SolverConfigError


def check_difference_operator(D: Tensor | None, n_params: int, groups: Tensor | None = None,
                              offset: Tensor | None = None, dtype: torch.dtype | None = None,
                              device: torch.device | str | None = None
                              ) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Validate ``D`` (and ``groups``, ``offset``) for ``n_params`` parameters.

    Returns ``(D, groups, offset)`` with ``D`` a coalesced sparse COO tensor of the given
    dtype/device, ``groups`` a LongTensor ``(n_edges,)`` or ``None``. Raises
    :class:`SolverConfigError` naming the argument at fault.
    """
    if D is None:
        raise SolverConfigError("D (the difference operator) is missing: split Bregman needs the "
                                "parameterisation's difference_operator()")
    if not isinstance(D, Tensor) or D.dim() != 2:
        raise SolverConfigError(f"D (the difference operator) must be a 2-D (sparse) tensor, got "
                                f"{type(D).__name__} of shape {tuple(getattr(D, 'shape', ()))}")
    if D.shape[1] != n_params:
        raise SolverConfigError(f"D (the difference operator) has {D.shape[1]} columns but theta "
                                f"has {n_params} parameters")
    if D.shape[0] == 0:
        raise SolverConfigError("D (the difference operator) is empty: no two parameters are "
                                "neighbours (a single cell?), so TV is zero and split Bregman "
                                "has nothing to regularise")
    if D.layout == torch.strided:
        D = D.to_sparse()
    elif D.layout != torch.sparse_coo:
        D = D.to_sparse_coo()
    D = D.coalesce()
    if dtype is not None or device is not None:
        D = D.to(dtype=dtype or D.dtype, device=device or D.device)
    values = D.values()
    if values.numel() == 0 or not bool((values != 0).any()):
        raise SolverConfigError("D (the difference operator) has no non-zero entry")
    if not bool(torch.isfinite(values).all()):
        raise SolverConfigError("D (the difference operator) contains NaN or infinite values")
    n_edges = D.shape[0]
    if groups is not None:
        groups = torch.as_tensor(groups).to(device=D.device)
        if groups.dtype in (torch.float16, torch.float32, torch.float64) or groups.dim() != 1 \
                or groups.numel() != n_edges:
            raise SolverConfigError(f"groups must be an integer vector with one group index per "
                                    f"row of D ({n_edges}), got shape {tuple(groups.shape)}")
        groups = groups.long()
        if bool((groups < 0).any()):
            raise SolverConfigError("groups must be >= 0 (row -> group index)")
    if offset is not None:
        offset = torch.as_tensor(offset).to(dtype=D.dtype, device=D.device)
        if offset.shape != (n_edges,):
            raise SolverConfigError(f"offset must have shape ({n_edges},) (one per row of D), got "
                                    f"{tuple(offset.shape)}")
        if not bool(torch.isfinite(offset).all()):
            raise SolverConfigError("offset contains NaN or infinite values")
    return D, groups, offset


class GroupTV:
    """``TV(t) = sum_g ||t_g||_2`` over groups of the rows of ``t = D theta + c``.

    Args:
        groups: ``(n_rows,)`` group index per row, or ``None`` (every row its own group:
            anisotropic TV, ``sum |t_i|``).
        n_rows: number of rows of ``D``.

    The split Bregman d-step is :meth:`shrink`, the proximal map of ``threshold * TV``
    (group soft thresholding); :meth:`dual_norm` is the norm dual to ``TV`` (max-abs, or
    the largest group norm). A subclass may replace the penalty by another function of
    the group norms by overriding :meth:`value` and :meth:`shrink` consistently (the
    skimage cross-check does, for the smoothed norm of skimage's isotropic variant).
    """

    def __init__(self, groups: Tensor | None, n_rows: int) -> None:
        if groups is None:
            self.groups = None
            self.n_groups = int(n_rows)
        else:
            _, self.groups = torch.unique(groups, return_inverse=True)
            self.n_groups = int(self.groups.max()) + 1

    def group_norms(self, t: Tensor) -> Tensor:
        """``(n_groups,)`` Euclidean norm of every group of ``t``."""
        if self.groups is None:
            return t.abs()
        sq = t.new_zeros(self.n_groups).index_add_(0, self.groups.to(t.device), t * t)
        return torch.sqrt(sq)

    def value(self, t: Tensor) -> float:
        return float(self.group_norms(t).sum())

    def dual_norm(self, w: Tensor) -> float:
        return float(self.group_norms(w).max())

    def shrink(self, t: Tensor, threshold: float) -> Tensor:
        """``argmin_d threshold * TV(d) + 1/2 ||d - t||^2``."""
        if self.groups is None:
            return torch.sign(t) * torch.clamp(t.abs() - threshold, min=0.0)
        norms = self.group_norms(t)
        factor = torch.clamp(norms - threshold, min=0.0) / torch.where(norms > 0, norms, 1.0)
        return t * factor[self.groups.to(t.device)]


__all__ = ["GroupTV", "check_difference_operator"]
