"""A body's principal frame, and its tetrahedralisation in that frame (rotation-invariant).

**Frame** (:func:`principal_frame`, of the tetrahedra or of a triangle surface): origin at
the centroid (of the volume or of the surface); axes the eigenvectors of the exact second
moments, ordered by increasing extent (``a0``, ``a1``, ``a2``: the longest last). Where two
moments agree within :data:`ROUND` (a round cross-section, a disc) the shape does not
determine them: in their plane the axes are those of the target's motion (the displacement
of the animation from the rest surface), the direction of most motion first. Signs: ``a0``
and ``a2`` point where the body's third moment along them is positive (the long tail of its
volume; the arm: towards the thinner wrist), and where the body is symmetric along one
(standardised third moment below :data:`SYMMETRIC`) where its mean motion goes; ``a1 = a2
x a0`` (right-handed). Every rule is rotation-equivariant; only a body symmetric in shape
*and* motion is left to the eigen-solver's choice.

**Tetrahedralisation** (:func:`tetrahedralize_in_frame`): fTetWild's mesh depends on the
orientation, order and round-off of its input and changes from build to build (even with one
thread); the canonical cache is what fixes it. The rest surface is welded (a seam's copies
are one vertex, their motion the mean), its principal frame found
(:func:`body_surface`), and it is handed over in canonical form
(:func:`torchfit.mesh.tetwild.canonical.canonical_surface`: in that frame, divided by its
radius, rounded, in canonical order) to the canonical cache, which returns the stored
tetrahedra mapped back into the file's coordinates. So one surface gets one mesh whatever
its axes, units, format, dtype, vertex or face order or seams (docs/notes/axes.md: what
is and is not invariant; the promise is the cache's, :mod:`torchfit.mesh.tetwild.canonical`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ...mesh import (CanonicalSurface, TetMesh, TetOptions, canonical_surface,
                     tetrahedralize_canonical, welded_surface)

#: two second moments closer than this (relative) are one round group (shape says nothing)
ROUND = 0.1
#: a standardised third moment below this is a symmetric body along that axis
SYMMETRIC = 0.02


def principal_frame(points: np.ndarray, cells: np.ndarray,
                    displacement: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(origin (3,), axes (3, 3))`` of a body (module doc: the rules); rows of ``axes``
    are ``a0, a1, a2``.

    Args:
        points, cells: a tetrahedral mesh ``(n, 3)``, ``(n_tets, 4)`` (the solid's
            moments) or a triangle surface ``(n, 3)``, ``(n_faces, 3)`` (the surface's).
        displacement: ``(..., 3)`` the target's displacement from rest (any number of
            frames and vertices), for the round groups and symmetric signs; ``None``: none.
    """
    corners = np.asarray(points, dtype=np.float64)[np.asarray(cells)]          # (T, k, 3)
    edges = corners[:, 1:] - corners[:, :1]
    if corners.shape[1] == 4:
        sizes, denominator = np.abs(np.linalg.det(edges)) / 6.0, 20.0         # volumes
    else:
        sizes, denominator = np.linalg.norm(np.cross(edges[:, 0], edges[:, 1]), axis=1) / 2, 12.0
    total = sizes.sum()          # a broken (flat) surface: equal weights; tetrahedralize says
    weights = sizes / total if total > 0 else np.full(len(sizes), 1.0 / max(len(sizes), 1))
    centroids = corners.mean(axis=1)
    origin = weights @ centroids
    offsets = centroids - origin
    # exact second moments: per tetrahedron V / 20 (sum q q^T + s s^T), per triangle A / 12
    # (the same sum), with q its corners about the origin and s their sum
    q = corners - origin
    second = np.einsum("tki,tkj->tij", q, q) + np.einsum("ti,tj->tij", q.sum(1), q.sum(1))
    moments, vectors = np.linalg.eigh(np.einsum("t,tij->ij", weights, second) / denominator)
    axes = vectors.T.copy()                                                    # ascending
    motion = np.zeros((1, 3)) if displacement is None else \
        np.asarray(displacement, dtype=np.float64).reshape(-1, 3)
    for group in _round_groups(moments):
        basis = axes[group]                                                    # (k, 3)
        projected = motion @ basis.T                                           # (m, k)
        spread, turn = np.linalg.eigh(projected.T @ projected)
        if len(group) and spread.max() > 0 and np.all(np.diff(spread) > ROUND * spread.max()):
            axes[group] = (turn[:, ::-1].T @ basis)                            # most motion first
    mean_motion = motion.mean(axis=0)
    scale = np.sqrt(np.maximum(moments.max(), 1e-300))
    for a in (0, 2):
        along = offsets @ axes[a]
        spread = float(weights @ along ** 2)
        skew = float(weights @ along ** 3) / spread ** 1.5 if spread > 1e-200 else 0.0
        moved = float(mean_motion @ axes[a])
        if abs(skew) >= SYMMETRIC:
            flip = skew < 0
        elif abs(moved) > 1e-9 * scale:
            flip = moved < 0
        else:
            flip = False
        if flip:
            axes[a] = -axes[a]
    axes[1] = np.cross(axes[2], axes[0])
    return origin, axes


def _round_groups(moments: np.ndarray) -> list[list[int]]:
    """Index groups of neighbouring ascending moments within :data:`ROUND` of each other."""
    groups: list[list[int]] = []
    current = [0]
    for i in (1, 2):
        if moments[i] - moments[i - 1] <= ROUND * max(moments[i], 1e-300):
            current.append(i)
        else:
            groups.append(current)
            current = [i]
    groups.append(current)
    return [g for g in groups if len(g) > 1]


def body_surface(rest: np.ndarray, faces: np.ndarray,
                 displacement: np.ndarray | None) -> CanonicalSurface:
    """The canonical form of the rest surface ``rest`` ``(V, 3)``, ``faces`` in the
    principal frame of its welded surface (module doc); ``displacement`` ``(F, V, 3)``
    (averaged over a seam's copies) settles round shapes."""
    groups, vertices, welded_faces = welded_surface(rest, faces)
    motion = None
    if displacement is not None:
        moved = np.asarray(displacement, dtype=np.float64)
        moved = moved.reshape(-1, moved.shape[-2], 3)
        n = len(vertices)
        motion = np.zeros((len(moved), n, 3))
        np.add.at(motion, (slice(None), groups), moved)
        motion /= np.bincount(groups, minlength=n)[None, :, None]
    origin, axes = principal_frame(vertices, welded_faces, motion)
    return canonical_surface(vertices, welded_faces, origin, axes)


def tetrahedralize_in_frame(rest: np.ndarray, faces: np.ndarray,
                            displacement: np.ndarray | None, options: TetOptions,
                            cache_dir: str | Path | None) -> TetMesh:
    """The tetrahedral mesh of the surface ``rest`` ``(V, 3)``, ``faces`` from the canonical
    cache (:func:`body_surface`, :func:`~torchfit.mesh.tetwild.canonical.tetrahedralize_canonical`),
    in the surface's coordinates; ``displacement`` ``(F, V, 3)`` settles round shapes."""
    return tetrahedralize_canonical(body_surface(rest, faces, displacement), options,
                                    cache_dir=cache_dir)
