"""Surfaces as DCCs write them: seam vertices welded for the simulation, the file's own back.

A DCC writes a vertex once per distinct set of corner attributes: a glTF exporter splits
every vertex on a UV seam or a sharp edge (a closed limb of 520 points comes out as 1,080),
an OBJ or a USD mesh may carry split normals or an Edge Split. The copies lie at one
position and move together, but as a surface they are separate: every seam edge is a
boundary edge, and the body reads as open (not watertight) with duplicate vertices.

:func:`weld_seams` merges the vertices that coincide in the rest pose *and* in every frame
(within ``tolerance`` times the rest bounding box's diagonal): the animation then holds the
welded surface (what is tetrahedralised, embedded, fitted and drawn), and
``Animation.file_vertices`` ``(V_file,)`` (the welded vertex of each file vertex) and
``Animation.file_faces`` keep the file's own; :meth:`~torchfit.mesh.Animation.file_points` maps
any per-vertex array back, so that every output (OBJ frames, the USD point cache, a
per-vertex field) has the file's vertex count and order. Vertices that coincide at rest but
part in some frame (lips, eyelids) stay apart. A welded vertex takes the mean of its copies'
skinning weights and the first copy's region label; it is driven if any copy is. Faces
that collapse (two corners welded together) are dropped from the simulation surface only.
Nothing here reads a file.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from ..animation import Animation
from ..simplicial import pair_groups

#: copies closer than this fraction of the rest bounding box's diagonal are one vertex
TOLERANCE = 1e-6


def seam_groups(rest: np.ndarray, frames: np.ndarray, tolerance: float = TOLERANCE
                ) -> np.ndarray | None:
    """The welded vertex of every vertex ``(V,)`` (numbered in order of first appearance),
    or ``None`` when no two vertices coincide in the rest pose and every frame."""
    rest = np.asarray(rest, dtype=np.float64)
    diagonal = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0))) or 1.0
    radius = tolerance * diagonal
    pairs = cKDTree(rest).query_pairs(radius, output_type="ndarray")
    if not len(pairs):
        return None
    apart = np.linalg.norm(frames[:, pairs[:, 0]] - frames[:, pairs[:, 1]], axis=-1).max(0)
    pairs = pairs[apart <= radius]
    if not len(pairs):
        return None
    # numbered in order of their first vertex, so an unwelded surface keeps its order
    return pair_groups(pairs, len(rest))


def weld_seams(animation: Animation, tolerance: float = TOLERANCE) -> Animation:
    """``animation`` on its welded surface (module docstring); unchanged where nothing
    coincides."""
    from ..surface import surface_warnings
    import trimesh

    groups = seam_groups(animation.rest_vertices, animation.frames, tolerance)
    if groups is None:
        return animation
    n = int(groups.max()) + 1
    first = np.full(n, len(groups), dtype=np.int64)
    np.minimum.at(first, groups, np.arange(len(groups)))
    counts = np.bincount(groups, minlength=n).astype(np.float64)
    faces = groups[animation.faces]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) \
        & (faces[:, 0] != faces[:, 2])
    faces = faces[keep]
    skeleton = animation.skeleton
    if skeleton is not None and skeleton.weights is not None:
        weights = np.zeros((n, skeleton.weights.shape[1]))
        np.add.at(weights, groups, skeleton.weights)
        weights /= counts[:, None]
        skeleton = dataclasses.replace(skeleton, weights=weights / weights.sum(1, keepdims=True))
    driven = animation.driven
    if driven is not None:
        mask = np.zeros(n, dtype=bool)
        np.logical_or.at(mask, groups, driven.mask)
        driven = dataclasses.replace(driven, mask=mask)
    labels = None if animation.region_labels is None else animation.region_labels[first]
    rest = animation.rest_vertices[first]
    return dataclasses.replace(
        animation, rest_vertices=rest, faces=faces, frames=animation.frames[:, first],
        skeleton=skeleton, driven=driven, region_labels=labels,
        warnings=surface_warnings(trimesh.Trimesh(rest, faces, process=False)),
        file_vertices=groups, file_faces=np.asarray(animation.faces))
