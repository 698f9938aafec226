"""``banded``: LAPACK banded Cholesky (``cholesky_banded``) after a reverse Cuthill-McKee
ordering made once per pattern, for long, thin meshes (CPU). A matrix that is not symmetric
positive definite (an indefinite Newton tangent), or a pattern whose band is too wide, goes
to the ``scipy`` backend instead."""
from __future__ import annotations

import dataclasses
import weakref

import numpy as np
import scipy.linalg as sla
from scipy.sparse.csgraph import reverse_cuthill_mckee
import torch
from torch import Tensor

from ..counters import count_factorization, count_solve
from ..errors import SingularMatrixError, cpu_only
from ..pattern import SparsePattern
from .superlu import ScipyBackend, ScipyFactor


class BandedFactor:
    """Banded Cholesky factor of ``P A P^T`` (upper form) with the RCM permutation ``P``."""

    def __init__(self, band: np.ndarray, perm: np.ndarray, dtype: torch.dtype) -> None:
        self._band = band
        self._perm = perm
        self._dtype = dtype

    def solve(self, rhs: Tensor, transpose: bool = False) -> Tensor:
        # A is symmetric: A^T x = b is the same solve.
        if rhs.device.type != "cpu":
            raise cpu_only("banded", rhs.device)
        count_solve(rhs)
        b = rhs.detach().numpy()
        x = np.empty_like(b)
        x[self._perm] = sla.cho_solve_banded((self._band, False), b[self._perm],
                                             check_finite=False)
        return torch.from_numpy(x).to(self._dtype)


class _BandPlan:
    """Per pattern: RCM permutation and where every CSR slot of the upper triangle goes."""

    def __init__(self, pattern: SparsePattern) -> None:
        n = pattern.shape[0]
        structure = pattern.to_scipy(torch.ones(pattern.nnz, dtype=torch.float64))
        self.perm = np.asarray(reverse_cuthill_mckee(structure.tocsr(), symmetric_mode=True),
                               dtype=np.int64)
        inverse = np.empty(n, dtype=np.int64)
        inverse[self.perm] = np.arange(n)
        rows = inverse[pattern.row_indices.cpu().numpy()]
        cols = inverse[pattern.col_indices.cpu().numpy()]
        upper = rows <= cols
        self.slots = np.nonzero(upper)[0]
        self.bandwidth = int((cols - rows)[upper].max()) if upper.any() else 0
        # upper form of LAPACK: ab[u + i - j, j] = A[i, j] for i <= j
        self.flat_index = (self.bandwidth + rows[upper] - cols[upper]) * n + cols[upper]
        self.n = n


@dataclasses.dataclass
class BandedBackend:
    """RCM + LAPACK banded Cholesky for SPD matrices with a narrow band (CPU).

    Falls back to :class:`ScipyBackend` when the matrix is not symmetric, not positive
    definite, or its RCM bandwidth exceeds ``max_bandwidth_fraction`` of its size.
    """

    max_bandwidth_fraction: float = 0.1
    name: str = "banded"

    def __post_init__(self) -> None:
        self._plans: "weakref.WeakKeyDictionary[SparsePattern, _BandPlan]" = weakref.WeakKeyDictionary()
        self._fallback = ScipyBackend()

    def plan(self, pattern: SparsePattern) -> _BandPlan:
        plan = self._plans.get(pattern)
        if plan is None:
            plan = _BandPlan(pattern)
            self._plans[pattern] = plan
        return plan

    def factorize(self, pattern: SparsePattern, values: Tensor, symmetric: bool) -> "BandedFactor | ScipyFactor":
        if values.device.type != "cpu":
            raise cpu_only("banded", values.device)
        if not symmetric:
            return self._fallback.factorize(pattern, values, symmetric)
        plan = self.plan(pattern)
        if plan.bandwidth > max(8, self.max_bandwidth_fraction * plan.n):
            return self._fallback.factorize(pattern, values, symmetric)
        if not torch.isfinite(values).all():
            raise SingularMatrixError("system matrix has NaN or infinite entries")
        band = np.zeros((plan.bandwidth + 1, plan.n))
        band.reshape(-1)[plan.flat_index] = values.detach().numpy()[plan.slots]
        try:
            factor = sla.cholesky_banded(band, lower=False, overwrite_ab=True, check_finite=False)
        except np.linalg.LinAlgError:
            # not positive definite (e.g. an indefinite Newton tangent): pivoted LU
            return self._fallback.factorize(pattern, values, symmetric)
        count_factorization()
        return BandedFactor(factor, plan.perm, values.dtype)
