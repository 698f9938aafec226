"""A second closed surface for the animation tests: a capsule with a two-bone rig.

Capsule of radius 0.04 m along z, cylinder from z = -0.12 to 0.12 (caps beyond), bones
(0, 0, -0.12) -> (0, 0, 0) -> (0, 0, 0.12), three frames bending the upper bone about the
y axis at the joint by 0, 15 and 30 degrees. The surface frames come from linear blend
skinning with distance weights, plus a small outward bulge on the +x side of the lower half
growing with the bend (something the material can explain).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
import yaml

from torchfit.mesh import DrivenSurface, Skeleton, write_animation
from torchfit.mesh.rig import blend, distance_weights, segment_distances

RADIUS = 0.04
HALF = 0.12
ANGLES = (0.0, 15.0, 30.0)


def capsule() -> trimesh.Trimesh:
    return trimesh.creation.capsule(height=2 * HALF, radius=RADIUS, count=[20, 20])


def bone_transforms(angles=ANGLES) -> np.ndarray:
    T = np.zeros((len(angles), 2, 3, 4))
    T[:, :, :, :3] = np.eye(3)
    for f, degrees in enumerate(angles):
        a = np.radians(degrees)
        R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        T[f, 1, :, :3] = R
        T[f, 1, :, 3] = -R @ np.zeros(3)        # joint at the origin
    return T


def write_capsule(folder: Path, mode: str = "skeleton", frames_as: str = "npz",
                  angles=ANGLES) -> Path:
    """Write the capsule animation; ``mode`` skeleton | driven, ``frames_as`` npz | obj,
    ``angles`` the bend of each frame (degrees)."""
    mesh = capsule()
    rest = np.asarray(mesh.vertices)
    faces = np.asarray(mesh.faces)
    heads = np.array([[0, 0, -HALF], [0, 0, 0.0]])
    tails = np.array([[0, 0, 0.0], [0, 0, HALF]])
    transforms = bone_transforms(angles)
    weights = distance_weights(segment_distances(rest, heads, tails), 1.5 * RADIUS)
    lower = np.clip(-rest[:, 2] / HALF, 0, 1) * np.clip(rest[:, 0] / RADIUS, 0, 1) ** 2
    bulge = np.zeros((len(angles), len(rest), 3))
    bulge[:, :, 0] = 0.004 * (np.asarray(angles) / max(angles))[:, None] * lower[None]
    frames = blend(rest + 0 * bulge[0], weights, transforms) + bulge
    if mode == "skeleton":
        skeleton = Skeleton(heads, tails, transforms, 0.4 * RADIUS, None, ["lower", "upper"])
        manifest = write_animation(folder, rest, faces, frames, skeleton=skeleton)
    else:
        ends = (rest[:, 2] < -HALF - 0.5 * RADIUS) | (rest[:, 2] > HALF + 0.5 * RADIUS)
        manifest = write_animation(folder, rest, faces, frames,
                                   driven=DrivenSurface(ends, 0.006))
    if frames_as == "obj":
        (folder / "frames").mkdir()
        for f, positions in enumerate(frames):
            trimesh.Trimesh(positions, faces, process=False).export(
                str(folder / "frames" / f"pose{f + 1}.obj"))
        (folder / "frames.npz").unlink()
        spec = yaml.safe_load(manifest.read_text())
        spec["frames"] = "frames/pose*.obj"
        manifest.write_text(yaml.safe_dump(spec, sort_keys=False))
    return folder
