"""Frames that repeat a pose: found once, simulated once, expanded back to every frame.

A rigged body's frame is fixed by its Dirichlet (drive) positions; two frames whose drive
positions agree to ``POSE_TOLERANCE`` times the drive's extent have the same equilibrium.
:func:`distinct_poses` returns the frames to simulate and, for every frame, its pose; the
problem simulates the distinct poses only and indexes the result back to ``(F, ...)``
(autograd through the index sums a repeated pose's gradients: each frame's residual is its
own targets minus the shared simulation, weighted as the data say).
"""
from __future__ import annotations

import torch
from torch import Tensor

#: Frames whose drive positions differ by at most this fraction of the drive's extent
#: (the largest coordinate range over all frames) share one simulation.
POSE_TOLERANCE = 1e-9


def distinct_poses(positions: Tensor, tolerance: float = POSE_TOLERANCE
                   ) -> tuple[Tensor, Tensor] | None:
    """``(poses, pose_of_frame)`` for drive positions ``(F, n_driven, d)``: the first frame
    of every distinct pose ``(P,)`` and each frame's index among them ``(F,)``; ``None``
    when every frame is its own pose (nothing to share)."""
    n_frames = positions.shape[0]
    flat = positions.reshape(n_frames, -1)
    extent = float((flat.max(0).values - flat.min(0).values).max()) if flat.numel() else 0.0
    limit = tolerance * max(extent, 1e-300)
    # each frame's pose is the first frame it matches (a frame matches itself); one row
    # of the (F, F) comparison at a time: F x n_driven d memory, not F^2 x n_driven d
    first = torch.stack([torch.argmax(((flat - row).abs().amax(-1) <= limit).to(torch.int8))
                         for row in flat])
    poses, pose_of_frame = torch.unique(first, sorted=True, return_inverse=True)
    if poses.numel() == n_frames:
        return None
    return poses, pose_of_frame
