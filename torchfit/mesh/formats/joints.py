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
  else one from the data (:func:`end_extent`): the rest vertices its weights dominate,
  projected on the joint's axis (the direction from its parent joint), reach ``s_max``
  along it; a flat end (the flesh keeps its thickness to ``s_max``) puts the tail there, a
  rounded end (a cap: the thickness falls to nothing over the end's radius) puts it at the
  cap's centre, one end radius short of ``s_max``; the bone covers at least half of
  ``s_max``. A root joint without children takes the principal axis of its vertices. A
  joint whose weights dominate fewer than ``MIN_REGION`` vertices (a tiny region) takes the
  vertices where its weight is at least half its largest instead; with none of either it
  stays a point (the rig check then names it if it drives no material:
  :func:`~.rig.idle_bones`).

``attach_radius`` (material within it of a bone follows the rig) comes from the file where
it says (the readers' ``torchfit:attachRadius``), else it is ``0.4`` times the median
distance of the rest surface to its nearest bone (the ratio of the procedural arm's and the
test tube's authored radius to their flesh radius). Either way the skeleton says where each
quantity came from (:attr:`~.rig.Skeleton.origin`, printed at set-up and written to the
run's ``rig.json``).

Measured (2026-12-07, docs/notes/dcc_rigs.md): the test tube (a capsule whose bones end at
its caps' centres) as a UsdSkel stage of joints only derives its tip bone 0.2500 m (authored
0.25; 0.2646 before) and the attach radius 0.0200 m (authored 0.02); Blender's limb (flat
caps) its end bone 0.1667 m from USD and glTF alike, Blender's own length (0.1167 before);
the procedural arm's forearm, whose bone ends at the surface's rounded pole, 0.2431 m
against 0.28 (a rounded end like the tube's: the two conventions cannot both be met) and
the radius 0.0159 m against 0.017.

A degenerate joint tree is refused in one line: joints with weight that coincide
(:func:`check_joint_placement`: a stage whose joints all sit at the origin skins its frames
exactly and still gives bones without length or place), or bones whose weighted vertices lie
far from them (:func:`check_bone_placement`). Refused rather than rebuilt from the weights:
a rebuilt joint is a guess the animator never made, and the fix in the DCC is one step.
:func:`bone_joints` is the way back (bones to a joint tree, for the writers). Nothing here
reads a file or solves anything.
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
                         bone_lengths: np.ndarray | None = None,
                         authored_as: tuple[str, str] = ("the file's attach radius",
                                                         "the file's bone length")) -> Skeleton:
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
        authored_as: how the file names its authored radius and lengths, for
            :attr:`~.rig.Skeleton.origin` (``("the stage's torchfit:attachRadius", ...)``).
    """
    parents = np.asarray(parents, dtype=np.int64)
    weights = normalized_weights(joint_weights, source)
    positions = np.asarray(joint_positions, dtype=np.float64)
    rest = np.asarray(rest_vertices, dtype=np.float64)
    check_joint_placement(positions, np.asarray(parents), weights, rest, joint_names, source)
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
    heads = positions[joint_of_bone]
    tails = positions[child_of_bone]
    lengths_from = ["authored: the joint to its child joint"] * len(joint_of_bone)
    ends = np.flatnonzero(joint_of_bone == child_of_bone)
    if ends.size:
        tails[ends], how = end_bone_tails(positions, parents, weights, rest_vertices,
                                          joint_of_bone[ends], bone_lengths, authored_as[1])
        for k, text in zip(ends, how):
            lengths_from[k] = text
    check_bone_placement(heads, tails, joint_of_bone, weights, rest, joint_names, source)
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
    radius_from = f"authored: {authored_as[0]}"
    if attach_radius is None:
        attach_radius = default_attach_radius(rest_vertices, heads, tails)
        radius_from = (f"derived: {ATTACH_RATIO:g} x the median distance of the rest surface "
                       "to its nearest bone")
    if not (np.isfinite(attach_radius) and attach_radius > 0):
        raise AnimationError(f"{source}: attach radius {attach_radius!r} must be a positive "
                             "length")
    origin = {"lengths": lengths_from, "attach_radius": radius_from,
              "weights": "authored: the file's skinning weights (a joint's weight split "
                         "equally between its bones)"}
    return Skeleton(heads, tails, transforms, float(attach_radius), bone_weights, names,
                    origin)


def end_bone_tails(positions: np.ndarray, parents: np.ndarray, weights: np.ndarray,
                   rest_vertices: np.ndarray, joints: np.ndarray,
                   bone_lengths: np.ndarray | None = None,
                   authored_as: str = "the file's bone length"
                   ) -> tuple[np.ndarray, list[str]]:
    """Tails ``(len(joints), 3)`` of the bones of end joints ``joints`` (module docstring)
    and, per bone, how its length was found (authored, or derived and how).

    Args:
        positions: ``(J, 3)`` rest joint positions; parents ``(J,)``; weights ``(V, J)``
            normalised; rest_vertices ``(V, 3)``; bone_lengths ``(J,)`` or ``None``.
    """
    rest = np.asarray(rest_vertices, dtype=np.float64)
    dominant = np.argmax(weights, axis=1)
    tails = positions[joints].copy()
    how = ["derived: none (no vertex gives the end joint a direction: a point)"] * len(joints)
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
            how[k] = f"authored: {authored_as}"
            continue
        rel = rest[region] - head
        along = rel @ axis
        if not along.size or float(along.max()) <= 0:
            continue
        radial = np.linalg.norm(rel - along[:, None] * axis, axis=1)
        extent, rounding = end_extent(along, radial)
        tails[k] = head + extent * axis
        how[k] = ("derived: the extent of the vertices its weights dominate along its axis "
                  + (f"less the rounded end's radius {rounding:.3g} m (a cap's centre)"
                     if rounding > 0 else "(a flat end)"))
    return tails, how


#: flesh at least this fraction of an end's radius from the axis has its full thickness
FULL_THICKNESS = 0.95


def end_extent(along: np.ndarray, radial: np.ndarray) -> tuple[float, float]:
    """An end bone's length and its end's rounding (metres) from its region's vertices:
    ``along`` ``(n,)`` their positions along its axis, ``radial`` ``(n,)`` their distances
    from it.

    The end's radius ``r`` is the largest distance from the axis within two median radii of
    the farthest vertex ``s_max``; the flesh has its full thickness up to ``s_full``, the
    farthest vertex at least ``FULL_THICKNESS r`` from the axis. A hemisphere of radius
    ``r`` keeps that thickness to ``sqrt(1 - FULL_THICKNESS^2) r`` past its centre, so
    ``(s_max - s_full) / (1 - sqrt(1 - FULL_THICKNESS^2))`` (at most ``r``) is the end's
    rounding: ``0`` for a flat end (the tail at ``s_max``), ``r`` for a cap (the tail at its
    centre). The length is at least ``s_max / 2``.
    """
    reach = float(along.max())
    near_end = along >= reach - 2.0 * float(np.median(radial))
    end_radius = float(radial[near_end].max())
    if end_radius <= 0:
        return reach, 0.0
    full = float(along[radial >= FULL_THICKNESS * end_radius].max())
    cap_share = 1.0 - np.sqrt(1.0 - FULL_THICKNESS ** 2)
    rounding = min((reach - full) / cap_share, end_radius)
    length = max(reach - rounding, 0.5 * reach)
    return length, reach - length


#: joints closer than this fraction of the body's size (its rest bounding-box diagonal)
#: coincide
COINCIDENT = 1e-6
#: a bone whose vertices (those its weights dominate) lie a median distance beyond this
#: fraction of the body's size from it is misplaced
FAR_FROM_FLESH = 0.25


def check_joint_placement(positions: np.ndarray, parents: np.ndarray, weights: np.ndarray,
                          rest_vertices: np.ndarray, names: list[str], source: str) -> None:
    """Refuse (one :class:`~..animation.AnimationError` line) weighted joints that coincide
    with their parent joint (``COINCIDENT``): the bone between them has no length. Such a
    stage can skin its frames exactly (the skinning needs only the bind transforms), but the
    bones that hold the material have no length and no place in the body
    (:func:`check_bone_placement` refuses bones away from it). Siblings that share a point
    (two thighs and a spine from one hip) are a rig, not a fault.

    Args:
        positions: ``(J, 3)`` rest joint positions (metres); parents ``(J,)`` (``-1``: a
            root); weights ``(V, J)`` normalised; rest_vertices ``(V, 3)``; names ``J``.
    """
    size = float(np.linalg.norm(rest_vertices.max(axis=0) - rest_vertices.min(axis=0)))
    parents = np.asarray(parents, dtype=np.int64)
    weighted = weights.max(axis=0) > 0
    child = np.flatnonzero(parents >= 0)
    parent = parents[child]
    # a weightless root on its first joint moves nothing: only pairs weighted on both sides
    short = np.linalg.norm(positions[child] - positions[parent], axis=-1) <= \
        COINCIDENT * max(size, 1e-300)
    short &= weighted[child] & weighted[parent]
    if short.any():
        together = sorted({int(j) for pair in zip(parent[short], child[short]) for j in pair})
        where = positions[together[0]]
        raise AnimationError(
            f"{source}: joints {_named(names, together)} coincide (all at "
            f"({where[0]:.4g}, {where[1]:.4g}, {where[2]:.4g}) m in the rest pose), so "
            "their bones have no length and hold no flesh; the skinning may still "
            "reproduce the frames, but the bind transforms must place each joint where "
            "it bends (in the DCC: apply the armature's rest pose and re-export)")


def check_bone_placement(heads: np.ndarray, tails: np.ndarray, joint_of_bone: np.ndarray,
                         weights: np.ndarray, rest_vertices: np.ndarray, names: list[str],
                         source: str) -> None:
    """Refuse (one line) bones far from their flesh: a weighted joint whose vertices (those
    its weights dominate) lie a median distance beyond ``FAR_FROM_FLESH`` of the body's size
    from its nearest bone.

    Args:
        heads, tails: ``(B, 3)`` the bones (end bones with their tails); joint_of_bone
            ``(B,)``; weights ``(V, J)`` normalised; rest_vertices ``(V, 3)``; names ``J``
            joint names.
    """
    size = float(np.linalg.norm(rest_vertices.max(axis=0) - rest_vertices.min(axis=0)))
    dominant = np.argmax(weights, axis=1)
    distances = segment_distances(rest_vertices, heads, tails)          # (V, B)
    far = []
    for j in np.unique(joint_of_bone):
        region = (dominant == j) & (weights[:, j] > 0)
        if not region.any():
            continue
        distance = float(np.median(distances[region][:, joint_of_bone == j].min(axis=1)))
        if distance > FAR_FROM_FLESH * size:
            far.append((int(j), distance))
    if far:
        j, distance = max(far, key=lambda item: item[1])
        raise AnimationError(
            f"{source}: the bones of joint{'s' if len(far) > 1 else ''} "
            f"{_named(names, [k for k, _ in far])} lie far from "
            f"the vertices their weights dominate (joint {names[j]}: a median {distance:.3g} "
            f"m away on a body {size:.3g} m across; at most {FAR_FROM_FLESH:g} of it is "
            "accepted); the bind transforms must place each joint inside the flesh it moves "
            "(in the DCC: apply the armature's rest pose and re-export)")


def _named(names: list[str], joints: list[int], limit: int = 6) -> str:
    """``base, tip`` (the first ``limit`` of them, then ``and 3 more``)."""
    shown = ", ".join(names[j] for j in joints[:limit])
    return shown + (f" and {len(joints) - limit} more" if len(joints) > limit else "")


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
