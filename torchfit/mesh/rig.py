"""Skeletons and linear blend skinning, vectorised over points, bones and frames.

Convention (the animation format's, see :mod:`.animation`): a bone is a rest-pose segment
``head -> tail``; its pose in frame ``f`` is a ``3 x 4`` matrix ``[A | t]`` acting on
column vectors, ``x' = A x + t`` with ``x`` a *rest-pose* position (world coordinates, not
bone-local). Rigid bones have ``A`` a rotation; any invertible ``A`` (affine) is allowed.
A skinned point moves by ``x'(f) = sum_b w_b (A_b(f) x + t_b(f))`` with weights ``w_b >= 0``
summing to one.

Weights from distance (the default): ``w_b`` proportional to ``(d_b + eps)^-power`` over the
bones within ``reach`` of the point (all bones when none is that close), so a point near one
bone follows it and a point near a joint blends the bones that meet there.

Nothing here solves anything (DESIGN.md, layer ``mesh``).
"""
from __future__ import annotations

import numpy as np

from .simplicial import MeshError


def segment_distances(points: np.ndarray, heads: np.ndarray, tails: np.ndarray) -> np.ndarray:
    """Euclidean distance of every point to every bone segment, ``(n, B)``.

    Args:
        points: ``(n, 3)``; heads, tails: ``(B, 3)`` segment ends (a zero-length bone is
            a point).
    """
    points = np.asarray(points, dtype=np.float64)
    heads = np.asarray(heads, dtype=np.float64)
    axis = np.asarray(tails, dtype=np.float64) - heads                    # (B, 3)
    length2 = np.einsum("bi,bi->b", axis, axis)
    rel = points[:, None, :] - heads[None, :, :]                          # (n, B, 3)
    s = np.einsum("nbi,bi->nb", rel, axis) / np.where(length2 > 0, length2, 1.0)
    s = np.clip(s, 0.0, 1.0)
    closest = rel - s[..., None] * axis[None]
    return np.sqrt(np.einsum("nbi,nbi->nb", closest, closest))


def axial_coordinates(points: np.ndarray, heads: np.ndarray,
                      tails: np.ndarray) -> np.ndarray:
    """Projection parameter ``s`` of each point on each bone's line (0 head, 1 tail), ``(n, B)``."""
    axis = np.asarray(tails, dtype=np.float64) - np.asarray(heads, dtype=np.float64)
    length2 = np.einsum("bi,bi->b", axis, axis)
    rel = np.asarray(points, dtype=np.float64)[:, None, :] - np.asarray(heads)[None]
    return np.einsum("nbi,bi->nb", rel, axis) / np.where(length2 > 0, length2, 1.0)


def distance_weights(distances: np.ndarray, reach: float, power: float = 4.0,
                     eps: float | None = None) -> np.ndarray:
    """Skinning weights ``(n, B)`` from point-bone distances ``(n, B)`` (rows sum to one).

    Bones farther than ``reach`` from a point get weight 0 unless no bone is within
    ``reach`` (then every bone counts). ``eps`` (default ``1e-3 reach``) keeps a point on a
    bone finite.
    """
    distances = np.asarray(distances, dtype=np.float64)
    if reach <= 0:
        raise ValueError(f"reach must be positive, got {reach}")
    eps = 1e-3 * reach if eps is None else eps
    raw = (distances + eps) ** (-power)
    near = distances <= reach
    none_near = ~near.any(axis=1, keepdims=True)
    raw = np.where(near | none_near, raw, 0.0)
    return raw / raw.sum(axis=1, keepdims=True)


def blend(points: np.ndarray, weights: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """Linear blend skinning of rest ``points`` ``(n, 3)``: ``(F, n, 3)``.

    Args:
        weights: ``(n, B)`` rows summing to one.
        transforms: ``(F, B, 3, 4)`` ``[A | t]`` per frame and bone.
    """
    points = np.asarray(points, dtype=np.float64)
    transforms = np.asarray(transforms, dtype=np.float64)
    moved = np.einsum("fbij,nj->fbni", transforms[..., :3], points) \
        + transforms[:, :, None, :, 3]                                   # (F, B, n, 3)
    return np.einsum("nb,fbni->fni", np.asarray(weights, dtype=np.float64), moved)


def check_transforms(transforms: np.ndarray, n_bones: int, n_frames: int | None,
                     source: str) -> np.ndarray:
    """``transforms`` as ``(F, B, 3, 4)`` float64; one-line :class:`MeshError` otherwise.

    Accepts ``(F, B, 3, 4)`` or homogeneous ``(F, B, 4, 4)`` (last row dropped after it is
    checked to be ``0 0 0 1``).
    """
    t = np.asarray(transforms, dtype=np.float64)
    if t.ndim != 4 or t.shape[1] != n_bones or t.shape[2:] not in ((3, 4), (4, 4)):
        raise MeshError(f"{source}: bone transforms must have shape (frames, {n_bones}, 3, 4) "
                        f"([A | t], x' = A x + t), got {t.shape}")
    bad = ~np.isfinite(t)
    if bad.any():
        f, b = np.argwhere(bad)[0][:2]
        raise MeshError(f"{source}: the transform of bone {b} in frame {f} is not finite "
                        "(NaN or infinite entries)")
    if t.shape[2] == 4:
        if not np.allclose(t[:, :, 3, :], [0.0, 0.0, 0.0, 1.0]):
            raise MeshError(f"{source}: a 4x4 bone transform must have last row 0 0 0 1")
        t = t[:, :, :3, :]
    if n_frames is not None and t.shape[0] != n_frames:
        raise MeshError(f"{source}: {t.shape[0]} frames of bone transforms for {n_frames} "
                        "frames of animation; give one transform per bone and frame")
    det = np.linalg.det(t[..., :3])
    if (det <= 0).any():
        f, b = np.argwhere(det <= 0)[0]
        raise MeshError(f"{source}: the transform of bone {b} in frame {f} is not invertible "
                        f"or mirrors space (det A = {det[f, b]:.3g})")
    return np.ascontiguousarray(t)
