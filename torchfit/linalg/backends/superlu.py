"""``scipy``: SuperLU, in symmetric mode for SPD systems (minimum degree ordering on
``A^T + A``, diagonal pivoting), the general COLAMD / partial-pivoting LU otherwise; CPU only,
always there."""
from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse.linalg as spla
import torch
from torch import Tensor

from ..counters import count_factorization, count_solve
from ..errors import SingularMatrixError, cpu_only
from ..pattern import SparsePattern


class ScipyFactor:
    def __init__(self, lu: "spla.SuperLU", symmetric: bool, dtype: torch.dtype) -> None:
        self._lu = lu
        self._symmetric = symmetric
        self._dtype = dtype

    def solve(self, rhs: Tensor, transpose: bool = False) -> Tensor:
        if rhs.device.type != "cpu":
            raise cpu_only("scipy", rhs.device)
        count_solve(rhs)
        trans = "T" if (transpose and not self._symmetric) else "N"
        x = self._lu.solve(np.ascontiguousarray(rhs.detach().numpy()), trans=trans)
        return torch.from_numpy(np.asarray(x)).to(self._dtype)


@dataclasses.dataclass
class ScipyBackend:
    """Direct sparse LU from scipy (SuperLU), symmetric mode for SPD matrices."""

    name: str = "scipy"

    def factorize(self, pattern: SparsePattern, values: Tensor, symmetric: bool) -> ScipyFactor:
        if values.device.type != "cpu":
            raise cpu_only("scipy", values.device)
        if not torch.isfinite(values).all():
            raise SingularMatrixError("system matrix has NaN or infinite entries")
        matrix = pattern.to_scipy(values).tocsc()
        try:
            if symmetric:
                # SPD: fill-reducing ordering of A^T + A, no off-diagonal pivoting.
                lu = spla.splu(matrix, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                               options={"SymmetricMode": True})
            else:
                lu = spla.splu(matrix)
        except RuntimeError as err:
            raise SingularMatrixError(
                f"sparse factorisation failed ({err}); the system is singular: check "
                "that every connected part of the model has a Dirichlet (fixed) node and "
                "that all stiffnesses are positive") from err
        count_factorization()
        return ScipyFactor(lu, symmetric, values.dtype)
