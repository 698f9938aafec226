"""What of a body's motion the outputs show: the most deformed frame, the camera, the most
strained region.

All three are rotation-equivariant (a rotated body and animation give the same frame, a
rotated camera, the same tetrahedra), so the pictures of a rotated body are the same
pictures (docs/notes/axes.md):

* :func:`most_deformed_frame`: the frame whose target surface lies farthest (mean over the
  vertices) from the rest surface moved rigidly onto it (best rotation and translation,
  Kabsch): deformation, not a rigid turn of the whole body nor a root bone's rotation.
* :func:`view_axes`: the camera looks along the direction in which the target moves least
  (the smallest principal axis of the displacements over every frame and vertex; among
  equal ones, not along the body's length), so the plane of motion faces it; "up" is the body's long axis (the grid's ``a2``) made
  perpendicular to that; the sign is chosen so that the mean motion goes to the right.
* :func:`most_strained_cells`: the tetrahedra of largest Green strain in a pose (for bodies
  whose rig has no joint: the region whose volume change the run reports).
"""
from __future__ import annotations

import numpy as np

#: the share of the tetrahedra in the most strained region
STRAINED_SHARE = 0.1


def most_deformed_frame(rest: np.ndarray, frames: np.ndarray) -> int:
    """Index of the frame of ``frames`` ``(F, V, 3)`` deformed most from ``rest`` ``(V, 3)``
    once each frame's best rigid motion is removed (module doc)."""
    rest = np.asarray(rest, dtype=np.float64)
    frames = np.asarray(frames, dtype=np.float64)
    centred_rest = rest - rest.mean(axis=0)
    centred = frames - frames.mean(axis=1, keepdims=True)                   # (F, V, 3)
    cross = np.einsum("vi,fvj->fij", centred_rest, centred)                 # (F, 3, 3)
    u, _, vt = np.linalg.svd(cross)
    det = np.sign(np.linalg.det(np.einsum("fij,fjk->fik", u, vt)))
    fix = np.ones((len(frames), 3))
    fix[:, 2] = det
    rotation = np.einsum("fji,fj,fkj->fik", vt, fix, u)     # R = V diag(1, 1, d) U^T
    moved = np.einsum("fij,vj->fvi", rotation, centred_rest)
    residual = np.linalg.norm(centred - moved, axis=-1).mean(axis=1)        # (F,)
    return int(np.argmax(residual))


def view_axes(rest: np.ndarray, frames: np.ndarray, long_axis: np.ndarray) -> np.ndarray:
    """Camera axes ``(3, 3)``, rows ``right, depth, up`` (right-handed): a picture in these
    coordinates seen from ``-depth`` shows the motion side-on (module doc).

    ``rest`` ``(V, 3)``, ``frames`` ``(F, V, 3)``; ``long_axis`` ``(3,)`` the body's longest
    principal axis (``up`` where the view allows)."""
    motion = (np.asarray(frames, dtype=np.float64) - np.asarray(rest)[None]).reshape(-1, 3)
    centred = motion - motion.mean(axis=0)
    spread = centred.T @ centred
    # where the least motion is not one direction (a motion along one line), look across
    # the body rather than along its length
    long_axis = np.asarray(long_axis, dtype=np.float64)
    spread += 1e-3 * np.trace(spread) * np.outer(long_axis, long_axis)
    _, vectors = np.linalg.eigh(spread)
    depth = vectors[:, 0]                                     # the direction of least motion
    up = None
    for candidate in (long_axis, vectors[:, 2], vectors[:, 1]):
        upright = candidate - (candidate @ depth) * depth
        if np.linalg.norm(upright) > 0.3 * np.linalg.norm(candidate):
            up = upright / np.linalg.norm(upright)
            break
    right = np.cross(depth, up)
    if motion.mean(axis=0) @ right < 0:
        depth, right = -depth, -right
    return np.stack([right, depth, up])


def most_strained_cells(rest: np.ndarray, cells: np.ndarray, pose: np.ndarray,
                        share: float = STRAINED_SHARE) -> np.ndarray:
    """Indices of the ``share`` of tetrahedra ``cells`` ``(T, 4)`` with the largest Green
    strain ``|F^T F - I|`` going from ``rest`` to ``pose`` (vertex positions ``(n, 3)``),
    at least one."""
    rest_corners = np.asarray(rest, dtype=np.float64)[cells]
    pose_corners = np.asarray(pose, dtype=np.float64)[cells]
    rest_edges = np.swapaxes(rest_corners[:, 1:] - rest_corners[:, :1], 1, 2)   # (T, 3, 3)
    pose_edges = np.swapaxes(pose_corners[:, 1:] - pose_corners[:, :1], 1, 2)
    gradient = pose_edges @ np.linalg.inv(rest_edges)
    strain = np.linalg.norm(np.swapaxes(gradient, 1, 2) @ gradient - np.eye(3), axis=(1, 2))
    count = max(1, int(round(share * len(cells))))
    return np.sort(np.argsort(-strain, kind="stable")[:count])
