"""A rigged body that is not the arm: a capsule tube along x (or y) with a bending two-bone rig.

Capsule of radius 0.05 m and 0.5 m between the cap centres, centred at ``OFFSET`` (away from
the origin, so that a transposed rotation also misplaces the joint), its axis along ``axis``.
Bones ``base`` and ``tip`` meet at the centre; the tip bends about the third axis by
``angles`` degrees. Frames: linear blend skinning with distance weights (given in the
manifest), plus a bulge of up to ``bulge`` metres on one side of the base half, growing with
the bend (a corrective the check must accept).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from torchfit.mesh import Animation, Skeleton, write_animation
from torchfit.mesh.rig import blend, distance_weights, segment_distances

RADIUS = 0.05
HALF = 0.25
OFFSET = np.array([0.3, 0.1, -0.2])
ANGLES = (0.0, 20.0, 45.0, 70.0, 90.0)


def _frame(axis: str) -> np.ndarray:
    """Rotation taking the capsule's z axis to ``axis`` (columns: images of x, y, z)."""
    if axis == "x":
        return np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    if axis == "y":
        return np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
    return np.eye(3)


def tube_animation(axis: str = "x", angles=ANGLES, bulge: float = 0.015,
                   count: int = 24) -> dict:
    """Rest vertices, faces, frames ``(F, V, 3)`` and the skeleton (weights given)."""
    mesh = trimesh.creation.capsule(height=2 * HALF, radius=RADIUS, count=[count, count])
    R0 = _frame(axis)
    rest = np.asarray(mesh.vertices) @ R0.T + OFFSET
    direction = R0[:, 2]
    heads = np.stack([OFFSET - HALF * direction, OFFSET])
    tails = np.stack([OFFSET, OFFSET + HALF * direction])
    bend_axis = R0[:, 0]                                     # perpendicular to the tube
    transforms = np.zeros((len(angles), 2, 3, 4))
    transforms[:, :, :, :3] = np.eye(3)
    for f, degrees in enumerate(angles):
        a = np.radians(degrees)
        K = np.cross(np.eye(3), bend_axis)                   # cross-product matrix
        R = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
        transforms[f, 1, :, :3] = R
        transforms[f, 1, :, 3] = OFFSET - R @ OFFSET
    weights = distance_weights(segment_distances(rest, heads, tails), 1.5 * RADIUS)
    local = (rest - OFFSET) @ R0                             # capsule coordinates
    side = np.clip(local[:, 1] / RADIUS, 0, 1) ** 2 * np.clip(-local[:, 2] / HALF, 0, 1)
    amount = bulge * (np.asarray(angles) / max(angles))[:, None] * side[None]
    frames = blend(rest, weights, transforms) + amount[..., None] * R0[:, 1]
    skeleton = Skeleton(heads, tails, transforms, 0.4 * RADIUS, weights, ["base", "tip"])
    return {"rest": rest, "faces": np.asarray(mesh.faces), "frames": frames,
            "skeleton": skeleton}


def tube(axis: str = "x", **kwargs) -> Animation:
    """The tube as a loaded :class:`Animation` (not written)."""
    data = tube_animation(axis, **kwargs)
    return Animation(Path(f"tube-{axis}/animation.yaml"), data["rest"], data["faces"],
                     data["frames"], 1.0, data["skeleton"])


def write_tube(folder: Path, axis: str = "x", **kwargs) -> Path:
    """The tube written as an animation folder; returns the folder."""
    data = tube_animation(axis, **kwargs)
    write_animation(folder, data["rest"], data["faces"], data["frames"],
                    skeleton=data["skeleton"])
    return folder
