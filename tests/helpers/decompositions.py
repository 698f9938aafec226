"""Batches of 2x2 and 3x3 matrices that are hard for the small decompositions of the
materials: random, inverted, repeated, nearly repeated, rank-deficient, zero."""
from __future__ import annotations

import torch


DT = torch.float64


def rotation(d: int, seed: int, n: int = 1) -> torch.Tensor:
    """``n`` random ``d x d`` rotations (``det = +1``)."""
    g = torch.Generator().manual_seed(seed)
    Q, _ = torch.linalg.qr(torch.randn(n, d, d, dtype=DT, generator=g))
    Q[..., :, 0] *= torch.sign(torch.linalg.det(Q))[:, None]
    return Q


def hard_batch(d: int, seed: int = 0) -> torch.Tensor:
    """Random, inverted, repeated, nearly repeated, opposite, rank-deficient and zero
    matrices, each also rotated on both sides."""
    g = torch.Generator().manual_seed(seed)
    random = torch.eye(d, dtype=DT) + 0.5 * torch.randn(400, d, d, dtype=DT, generator=g)
    inverted = random[:100].clone()
    inverted[:, :, 0] *= -1
    diagonals = [[1.0] * d, [2.0] * d, [1.0] * (d - 1) + [-1.0], [1.0 + 1e-9] + [1.0] * (d - 1),
                 [3.0] + [1e-12] * (d - 1), [1.0] * (d - 1) + [0.0], [0.0] * d,
                 [-1.0] * d, [1.0, 1.0 - 1e-13] + [0.5] * (d - 2), [1e-8] * d]
    special = torch.diag_embed(torch.tensor(diagonals, dtype=DT))
    n = special.shape[0]
    rotated = rotation(d, seed + 1, n) @ special @ rotation(d, seed + 2, n).transpose(-1, -2)
    return torch.cat([random, inverted, special, rotated])
