"""Test matrices on grids shared by the backend tests."""
from __future__ import annotations

import numpy as np
import torch

from torchfit.linalg import SparsePattern


def grid_laplacian(nx: int, ny: int, shift: float = 0.1, seed: int = 0):
    """A variable-coefficient 5-point operator on an nx x ny grid (+ shift I), random order."""
    g = np.random.default_rng(seed)
    index = g.permutation(nx * ny).reshape(ny, nx)      # scrambled numbering: RCM must undo it
    rows, cols, vals = [], [], []
    for a, b in list(zip(index[:, :-1].ravel(), index[:, 1:].ravel())) + \
            list(zip(index[:-1, :].ravel(), index[1:, :].ravel())):
        k = float(np.exp(g.uniform(-1, 1)))
        rows += [a, a, b, b]
        cols += [a, b, a, b]
        vals += [k, -k, -k, k]
    n = nx * ny
    rows += list(range(n))
    cols += list(range(n))
    vals += [shift] * n
    pattern = SparsePattern(np.array(rows), np.array(cols), (n, n))
    return pattern, pattern.assemble(torch.tensor(vals))
