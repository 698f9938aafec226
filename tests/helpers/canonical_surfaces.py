"""One closed surface in the representations a DCC may write it in (for the canonical-mesh tests).

A tapered, flattened capsule (no symmetry that leaves its principal frame open: moments
apart, a third moment along its length), and copies of it: vertices and faces permuted
(corners turned), split along a seam (glTF), float32, turned by a general rotation, scaled
by 100 and moved. Each copy comes with the map ``(scale, R, t)`` from the original's
coordinates to its own: ``x' = scale * R x + t``.
"""
from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation


def tapered_capsule() -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (V, 3), faces (k, 3))``: about 0.3 x 0.2 x 0.9 long, thicker at -z."""
    mesh = trimesh.creation.capsule(height=0.6, radius=0.15, count=[12, 12])
    v = np.asarray(mesh.vertices, dtype=np.float64).copy()
    taper = 1.0 - 0.35 * (v[:, 2] - v[:, 2].min()) / np.ptp(v[:, 2])
    v[:, 0] *= taper
    v[:, 1] *= 0.7 * taper
    v[:, 0] += 2.0 * np.maximum(v[:, 0], 0.0) ** 2        # one side fuller: no mirror
    return v + np.array([0.01, -0.02, 0.03]), np.asarray(mesh.faces, dtype=np.int64)


def permuted(vertices, faces, seed: int = 0):
    """Vertices and faces in another order, each face's corners turned (orientation kept)."""
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(vertices))
    new_index = np.empty_like(order)
    new_index[order] = np.arange(len(order))
    f = new_index[faces][rng.permutation(len(faces))]
    turn = rng.integers(0, 3, len(f))
    f = f[np.arange(len(f))[:, None], (turn[:, None] + np.arange(3)) % 3]
    return vertices[order], f


def seam_split(vertices, faces):
    """Every vertex shared by faces on both sides of the plane x = mean copied for the
    faces on the +x side (a glTF seam): more vertices, the same triangles."""
    side = vertices[faces].mean(axis=1)[:, 0] > vertices[:, 0].mean()
    plus, minus = np.unique(faces[side]), np.unique(faces[~side])
    shared = np.intersect1d(plus, minus)
    copy = np.full(len(vertices), -1, dtype=np.int64)
    copy[shared] = len(vertices) + np.arange(len(shared))
    f = faces.copy()
    on_seam = side[:, None] & (copy[f] >= 0)
    f[on_seam] = copy[f[on_seam]]
    return np.concatenate([vertices, vertices[shared]]), f


def turned(vertices, scale: float = 100.0, seed: int = 3):
    """``(scale * R x + t, (scale, R, t))`` with a general rotation ``R``."""
    R = Rotation.from_euler("xyz", [37.0, -71.0, 113.0], degrees=True).as_matrix()
    t = np.array([1.5, -0.25, 4.0]) * scale
    return scale * vertices @ R.T + t, (scale, R, t)
