"""From a DCC's joint tree to the animation format's bones: what the USD and glTF readers share.

A DCC skeleton (UsdSkel, a glTF skin) is a tree of joints, each with a bind position and a
per-frame skinning transform, and skinning weights per joint. The animation format
(:mod:`.rig`) has bones: rest-pose segments ``head -> tail`` with a transform each, weights
per bone. :func:`skeleton_from_joints` maps one to the other:

- every joint with children gives one bone per child, ``joint -> child`` (rest positions),
  moved by the joint's transform; the joint's weight is split equally between them (they
  move alike, so the skinned points are unchanged);
- a joint without children (an end joint: a hand, a foot, a fingertip, a tail's last bone)
  gives a bone only where some vertex has weight on it (an end joint without weight, such as
  a wrist tip, is no bone), and that bone has an extent (:func:`end_bone_tails`): an
  authored length where the file has one (USD ``torchfit:boneLength``, glTF ``extras``),
  else one from the data: the rest vertices its weights dominate, projected on the joint's
  axis (the direction from its parent joint), reach ``s_max`` along it; the bone ends one
  flesh radius (the median distance of those vertices from the axis) short of that, so it
  stays inside the body, and covers at least half of ``s_max``. A root joint without
  children takes the principal axis of its vertices. A joint whose weights dominate fewer
  than ``MIN_REGION`` vertices (a tiny region) takes the vertices where its weight is at
  least half its largest instead; with none of either it stays a point (the rig check then
  names it if it drives no material: :func:`~.rig.idle_bones`).

``attach_radius`` (material within it of a bone follows the rig) comes from the file where
it says (the readers' ``torchfit:attachRadius``), else it is ``0.4`` times the median
distance of the rest surface to its nearest bone (the procedural arm's ratio of attach
radius to body radius). :func:`bone_joints` is the way back (bones to a joint tree, for the
writers). Nothing here reads a file or solves anything.
"""
from __future__ import annotations

import numpy as np

from ..animation import AnimationError
from ..rig import Skeleton, check_transforms, segment_distances
from ..simplicial import MeshError

#: attach_radius by default: this fraction of the median distance of the surface to a bone
ATTACH_RATIO = 0.4
#: an end joint whose weights dominate fewer rest vertices than this has a tiny region
MIN_REGION = 3


def fan_triangles(counts: np.ndarray, indices: np.ndarray, source: str) -> np.ndarray:
    """Triangles ``(T, 3)`` of polygons (``counts`` vertices each, ``indices`` flat) by fans
    from each polygon's first vertex, the polygon's winding and vertex order kept."""
    counts = np.asarray(counts, dtype=np.int64).reshape(-1)
    indices = np.asarray(indices, dtype=np.int64).reshape(-1)
    if (counts < 3).any() or counts.sum() != indices.size:
        raise AnimationError(f"{source}: the face vertex counts ({int(counts.sum())} corners, "
                             f"smallest {int(counts.min()) if counts.size else 0}) do not match "
                             f"the {indices.size} face vertex indices (every face needs >= 3)")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    n_triangles = counts - 2
    face = np.repeat(np.arange(counts.size), n_triangles)
    k = np.arange(n_triangles.sum()) - np.repeat(np.cumsum(n_triangles) - n_triangles,
                                                 n_triangles)
    first = starts[face]
    return np.stack([indices[first], indices[first + k + 1], indices[first + k + 2]], axis=1)


def row_vector_transforms(matrices: np.ndarray) -> np.ndarray:
    """``[A | t]`` ``(..., 3, 4)`` (``x' = A x + t``) of 4x4 matrices acting on row vectors
    (``[x, 1] @ M``, USD's convention)."""
    return np.ascontiguousarray(np.swapaxes(np.asarray(matrices, dtype=np.float64), -1, -2)
                                [..., :3, :])


def normalized_weights(weights: np.ndarray, source: str) -> np.ndarray:
    """Per-vertex weights ``(V, J)`` scaled to sum to one; one line for a vertex without any."""
    weights = np.asarray(weights, dtype=np.float64)
    if not np.isfinite(weights).all() or (weights < 0).any():
        raise AnimationError(f"{source}: skinning weights must be finite and >= 0")
    sums = weights.sum(axis=1, keepdims=True)
    if (sums <= 0).any():
        v = int(np.flatnonzero(sums[:, 0] <= 0)[0])
        raise AnimationError(f"{source}: vertex {v} has all skinning weights zero; give every "
                             "vertex an influence")
    return weights / sums


def default_attach_radius(rest_vertices: np.ndarray, heads: np.ndarray,
                          tails: np.ndarray) -> float:
    """``ATTACH_RATIO`` times the median distance of the rest vertices to their nearest bone."""
    nearest = segment_distances(rest_vertices, heads, tails).min(axis=1)
    return float(ATTACH_RATIO * np.median(nearest))


def skeleton_from_joints(joint_positions: np.ndarray, parents: np.ndarray,
                         joint_transforms: np.ndarray, joint_weights: np.ndarray,
                         joint_names: list[str], attach_radius: float | None,
                         rest_vertices: np.ndarray, source: str,
                         bone_lengths: np.ndarray | None = None) -> Skeleton:
    """The animation format's :class:`~.rig.Skeleton` of a joint hierarchy (lengths in metres).

    Args:
        joint_positions: ``(J, 3)`` rest (bind) positions; parents: ``(J,)`` parent index,
            ``-1`` at a root.
        joint_transforms: ``(F, J, 3, 4)`` ``[A | t]`` per frame and joint on rest positions.
        joint_weights: ``(V, J)`` skinning weights per rest vertex (normalised here).
        attach_radius: metres, or ``None`` for :func:`default_attach_radius`.
        rest_vertices: ``(V, 3)`` metres (the end bones' extents, the default radius).
        bone_lengths: ``(J,)`` authored lengths of end joints' bones (metres; ``NaN`` or
            ``<= 0``: from the data), or ``None``.
    """
    parents = np.asarray(parents, dtype=np.int64)
    weights = normalized_weights(joint_weights, source)
    used = weights.max(axis=0) > 0
    joint_of_bone, child_of_bone = [], []
    for j in range(len(parents)):
        children = np.flatnonzero(parents == j)
        if children.size:
            joint_of_bone += [j] * children.size
            child_of_bone += children.tolist()
        elif used[j]:
            joint_of_bone.append(j)
            child_of_bone.append(j)
    if not joint_of_bone:
        raise AnimationError(f"{source}: the skeleton has no bone (no joint with a child or a "
                             "skinning weight)")
    joint_of_bone = np.asarray(joint_of_bone)
    child_of_bone = np.asarray(child_of_bone)
    positions = np.asarray(joint_positions, dtype=np.float64)
    heads = positions[joint_of_bone]
    tails = positions[child_of_bone]
    ends = np.flatnonzero(joint_of_bone == child_of_bone)
    if ends.size:
        tails[ends] = end_bone_tails(positions, parents, weights, rest_vertices,
                                     joint_of_bone[ends], bone_lengths)
    shares = np.bincount(joint_of_bone, minlength=len(parents))[joint_of_bone]
    bone_weights = weights[:, joint_of_bone] / shares
    try:
        transforms = check_transforms(np.asarray(joint_transforms)[:, joint_of_bone],
                                      len(joint_of_bone), None, source)
    except MeshError as err:
        raise AnimationError(str(err)) from err
    names = [joint_names[j] if np.sum(joint_of_bone == j) == 1
             else f"{joint_names[j]}->{joint_names[c]}"
             for j, c in zip(joint_of_bone, child_of_bone)]
    if attach_radius is None:
        attach_radius = default_attach_radius(rest_vertices, heads, tails)
    if not (np.isfinite(attach_radius) and attach_radius > 0):
        raise AnimationError(f"{source}: attach radius {attach_radius!r} must be a positive "
                             "length")
    return Skeleton(heads, tails, transforms, float(attach_radius), bone_weights, names)


def end_bone_tails(positions: np.ndarray, parents: np.ndarray, weights: np.ndarray,
                   rest_vertices: np.ndarray, joints: np.ndarray,
                   bone_lengths: np.ndarray | None = None) -> np.ndarray:
    """Tails ``(len(joints), 3)`` of the bones of end joints ``joints`` (module docstring).

    Args:
        positions: ``(J, 3)`` rest joint positions; parents ``(J,)``; weights ``(V, J)``
            normalised; rest_vertices ``(V, 3)``; bone_lengths ``(J,)`` or ``None``.
    """
    rest = np.asarray(rest_vertices, dtype=np.float64)
    dominant = np.argmax(weights, axis=1)
    tails = positions[joints].copy()
    for k, j in enumerate(joints):
        head = positions[j]
        region = dominant == j
        if region.sum() < MIN_REGION:
            region = weights[:, j] >= 0.5 * weights[:, j].max()
        axis = _joint_axis(positions, parents, j, rest[region] - head)
        if axis is None:
            continue
        authored = np.nan if bone_lengths is None else float(bone_lengths[j])
        if np.isfinite(authored) and authored > 0:
            tails[k] = head + authored * axis
            continue
        rel = rest[region] - head
        along = rel @ axis
        reach = float(along.max()) if along.size else 0.0
        if reach <= 0:
            continue
        radius = float(np.median(np.linalg.norm(rel - along[:, None] * axis, axis=1)))
        tails[k] = head + max(reach - radius, 0.5 * reach) * axis
    return tails


def _joint_axis(positions: np.ndarray, parents: np.ndarray, joint: int,
                offsets: np.ndarray) -> np.ndarray | None:
    """The unit axis of an end joint: from its parent joint to it; for a root (or a joint on
    its parent), the principal direction of ``offsets`` (its region's vertices from the
    joint), pointing to their side; ``None`` when neither gives a direction."""
    parent = int(parents[joint])
    if parent >= 0:
        axis = positions[joint] - positions[parent]
        length = float(np.linalg.norm(axis))
        if length > 1e-12 * max(float(np.abs(positions).max()), 1.0):
            return axis / length
    if len(offsets) < 2:
        return None
    centred = offsets - offsets.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    axis = vt[0]
    if float(offsets.mean(axis=0) @ axis) < 0:
        axis = -axis
    return axis


def bone_joints(skeleton: Skeleton, tol: float = 1e-9) -> tuple[list[str], np.ndarray,
                                                               np.ndarray, np.ndarray]:
    """The joint tree of a bone set: joint paths, parents ``(J,)``, rest positions ``(J, 3)``
    and which bone moves each joint ``(J,)`` (the first ``B`` joints are the bones')."""
    B = skeleton.n_bones
    scale = max(float(np.linalg.norm(skeleton.tails - skeleton.heads, axis=1).max()), 1e-300)
    gap = np.linalg.norm(skeleton.tails[:, None] - skeleton.heads[None], axis=-1)
    starts = (gap <= tol * scale) & ~np.eye(B, dtype=bool)          # tail of b starts bone c
    parents = np.array([int(np.flatnonzero(starts[:, c])[0]) if starts[:, c].any() else -1
                        for c in range(B)])
    ends = [b for b in range(B) if not starts[b].any()]
    parents = np.concatenate([parents, ends]).astype(np.int64)
    positions = np.concatenate([skeleton.heads, skeleton.tails[ends]])
    mover = np.concatenate([np.arange(B), ends]).astype(np.int64)
    names = list(skeleton.names) or [f"bone{b}" for b in range(B)]
    local = [names[b] for b in range(B)] + [f"{names[b]}_end" for b in ends]
    paths: list[str] = []
    for j in range(len(parents)):
        chain, k = [], j
        while k >= 0:
            chain.append(local[k])
            k = parents[k]
        paths.append("/".join(reversed(chain)))
    return paths, parents, positions, mover
