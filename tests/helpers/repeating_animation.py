"""An animation whose frames repeat poses: a tube along x bent at its middle, and back.

A closed cylinder of radius 0.03 m along x from -0.1 to 0.1 m, two bones
(-0.1, 0, 0) -> (0, 0, 0) -> (0.1, 0, 0); the outer bone turns about the y axis at the joint
by :data:`ANGLES` degrees (the animation bends one way, plays back, bends the other way and
back), with a small outward bulge on the +z side of the inner half growing with the bend
(something a material can explain). Frames with the same angle are the same pose, bit for
bit: :data:`POSES` lists the frames of each distinct pose.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from torchfit.mesh import Skeleton, write_animation
from torchfit.mesh.rig import blend, distance_weights, segment_distances

RADIUS = 0.03
HALF = 0.1
#: outer bone's angle per frame (degrees): 0, 12, 24, 12, 0, -12, -24, -12
ANGLES = (0.0, 12.0, 24.0, 12.0, 0.0, -12.0, -24.0, -12.0)
#: frames of each distinct pose, in order of first appearance
POSES = [[0, 4], [1, 3], [2], [5, 7], [6]]


def tube() -> trimesh.Trimesh:
    mesh = trimesh.creation.cylinder(radius=RADIUS, height=2 * HALF, sections=16)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    return mesh


def bone_transforms(angles=ANGLES) -> np.ndarray:
    """``(F, 2, 3, 4)``: the inner bone fixed, the outer one turned about y at the origin."""
    T = np.zeros((len(angles), 2, 3, 4))
    T[:, :, :, :3] = np.eye(3)
    for f, degrees in enumerate(angles):
        a = np.radians(degrees)
        T[f, 1, :, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    return T


def write_tube(folder: Path, angles=ANGLES) -> Path:
    """Write the tube's animation folder (frames in ``frames.npz``); returns ``folder``."""
    mesh = tube()
    rest = np.asarray(mesh.vertices)
    heads = np.array([[-HALF, 0, 0], [0.0, 0, 0]])
    tails = np.array([[0.0, 0, 0], [HALF, 0, 0]])
    transforms = bone_transforms(angles)
    weights = distance_weights(segment_distances(rest, heads, tails), 1.5 * RADIUS)
    inner = np.clip(-rest[:, 0] / HALF, 0, 1) * np.clip(rest[:, 2] / RADIUS, 0, 1) ** 2
    bend = np.abs(np.asarray(angles)) / max(abs(a) for a in angles)
    bulge = np.zeros((len(angles), len(rest), 3))
    bulge[:, :, 2] = 0.003 * bend[:, None] * inner[None]
    frames = blend(rest, weights, transforms) + bulge
    skeleton = Skeleton(heads, tails, transforms, 0.4 * RADIUS, None, ["inner", "outer"])
    write_animation(folder, rest, np.asarray(mesh.faces), frames, skeleton=skeleton)
    return folder
