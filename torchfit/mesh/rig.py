"""What drives a body: skeletons, linear blend skinning, driven surfaces, a tet mesh's drive.

The drive of a tetrahedral mesh says which of its vertices are prescribed, where, and where
Newton starts.

Convention (the animation format's, :mod:`.formats.folder`): a bone is a rest-pose
segment ``head -> tail``; its pose in frame ``f`` is a ``3 x 4`` matrix ``[A | t]`` acting on
column vectors, ``x' = A x + t`` with ``x`` a *rest-pose* position (world coordinates, not
bone-local). Rigid bones have ``A`` a rotation; any invertible ``A`` (affine) is allowed.
A skinned point moves by ``x'(f) = sum_b w_b (A_b(f) x + t_b(f))`` with weights ``w_b >= 0``
summing to one.

Weights from distance (the default): ``w_b`` proportional to ``(d_b + eps)^-power`` over the
bones within ``reach`` of the point (all bones when none is that close), so a point near one
bone follows it and a point near a joint blends the bones that meet there.

The drive (:func:`skeleton_drive`, :func:`surface_drive`) of tetrahedron vertices ``points``
``(n, 3)`` by an animated surface (rest ``(V, 3)``, faces ``(T, 3)``, frames ``(F, V, 3)``)
is a :class:`Drive`; a rig that holds nothing, or everything, is a one-line
:class:`~.simplicial.MeshError`. Lengths in metres. Nothing here solves anything.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from .embedding import boundary_faces
from .simplicial import MeshError


@dataclasses.dataclass
class Skeleton:
    """Bones in the rest pose and their per-frame transforms (lengths in metres).

    Attributes:
        heads, tails: ``(B, 3)`` rest-pose segment ends.
        transforms: ``(F, B, 3, 4)`` ``[A | t]`` with ``x' = A x + t``.
        attach_radius: material points within this distance of a bone follow it.
        weights: ``(V, B)`` skinning weights per rest-surface vertex, or ``None`` (from
            distance).
        names: ``B`` bone names.
        origin: where the rig's quantities came from, for the set-up's rig lines and
            ``rig.json`` (:func:`rig_description`): ``lengths`` (one text per bone),
            ``attach_radius``, ``weights``, each ``"authored: ..."`` (the file gave it) or
            ``"derived: ..."`` (how); empty for a rig the file gives whole (the animation
            folder's segments).
    """

    heads: np.ndarray
    tails: np.ndarray
    transforms: np.ndarray
    attach_radius: float
    weights: np.ndarray | None = None
    names: list[str] = dataclasses.field(default_factory=list)
    origin: dict = dataclasses.field(default_factory=dict)

    @property
    def n_bones(self) -> int:
        return int(self.heads.shape[0])

    def joints(self, tol: float = 1e-9) -> np.ndarray:
        """Rest positions ``(k, 3)`` where one bone's tail meets another's head."""
        gap = np.linalg.norm(self.tails[:, None, :] - self.heads[None, :, :], axis=-1)
        scale = max(float(np.linalg.norm(self.tails - self.heads, axis=1).max()), 1e-300)
        i, j = np.nonzero((gap <= tol * scale) & ~np.eye(self.n_bones, dtype=bool))
        return self.tails[i] if i.size else np.zeros((0, 3))


@dataclasses.dataclass
class DrivenSurface:
    """Surface vertices whose animated motion is prescribed (``mask`` ``(V,)`` bool)."""

    mask: np.ndarray
    tolerance: float

    @property
    def indices(self) -> np.ndarray:
        return np.flatnonzero(self.mask)


@dataclasses.dataclass
class Drive:
    """How a rig holds a tetrahedral mesh in every frame.

    Attributes:
        vertices: ``(k,)`` indices of the prescribed (Dirichlet) tetrahedron vertices.
        positions: ``(F, k, 3)`` their positions in every frame.
        start: ``(F, n, 3)`` where each frame's Newton starts: the prescribed vertices at
            ``positions``, the others moved by the rig (surface vertices with the animated
            surface).
        idle_bones: names of the bones that prescribe no vertex (:func:`idle_bones`): their
            flesh follows only through its neighbours.
        per_bone: ``(B,)`` prescribed vertices nearest to each bone (a skeleton's drive;
            ``None`` for a driven surface).
    """

    vertices: np.ndarray
    positions: np.ndarray
    start: np.ndarray
    idle_bones: list[str] = dataclasses.field(default_factory=list)
    per_bone: np.ndarray | None = None


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
            row_vector = np.allclose(t[:, :, :, 3], [0.0, 0.0, 0.0, 1.0])
            raise MeshError(f"{source}: a 4x4 bone transform must have last row 0 0 0 1" + (
                "; these have it as their last column, the translation in the last row: a "
                "row-vector layout (x' = x M); transpose every matrix" if row_vector else ""))
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


def joint_cells(centroids: np.ndarray, skeleton: Skeleton | None) -> np.ndarray:
    """Indices of the cells (centroids ``(m, 3)``) within ``3 attach_radius`` of a joint of
    ``skeleton`` (a bone's tail meeting another's head); every cell when there is no
    skeleton, no joint, or no cell that close."""
    if skeleton is None or not len(skeleton.joints()):
        return np.arange(len(centroids))
    joints = skeleton.joints()
    distance = np.linalg.norm(centroids[:, None, :] - joints[None], axis=-1).min(axis=1)
    cells = np.flatnonzero(distance <= 3.0 * skeleton.attach_radius)
    return cells if cells.size else np.arange(len(centroids))


def most_rotated_frame(skeleton: Skeleton | None) -> int:
    """The frame in which some bone is rotated most (the full bend), 0 without a skeleton."""
    if skeleton is None:
        return 0
    A = skeleton.transforms[..., :3]
    cosine = np.clip((np.trace(A, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return int(np.argmax(np.arccos(cosine).max(axis=1)))


# -- the drive of a tetrahedral mesh -------------------------------------------------------
def surface_start(points: np.ndarray, rest_vertices: np.ndarray, faces: np.ndarray,
                  frames: np.ndarray) -> np.ndarray:
    """Positions ``(F, n, 3)`` of ``points`` moved with the displacement of the closest
    point of the rest surface (barycentric in its triangle)."""
    import trimesh

    surface = trimesh.Trimesh(rest_vertices, faces, process=False)
    closest, _, triangle = trimesh.proximity.closest_point(surface, points)
    corners = rest_vertices[faces[triangle]]                                  # (n, 3, 3)
    bary = trimesh.triangles.points_to_barycentric(corners, closest)          # (n, 3)
    displacement = frames - rest_vertices[None]                               # (F, V, 3)
    moved = np.einsum("nk,fnkd->fnd", bary, displacement[:, faces[triangle]])
    return points[None] + moved


def idle_bones(distances: np.ndarray, skeleton: Skeleton) -> list[str]:
    """Names of the bones nearest to no material point within ``attach_radius`` (from the
    point-bone ``distances`` ``(n, B)``): bones that drive nothing."""
    attached = distances.min(axis=1) <= skeleton.attach_radius
    driving = np.bincount(distances[attached].argmin(axis=1), minlength=skeleton.n_bones)
    names = list(skeleton.names) or [f"bone{b}" for b in range(skeleton.n_bones)]
    return [names[b] for b in np.flatnonzero(driving == 0)]


def skeleton_drive(points: np.ndarray, cells: np.ndarray, skeleton: Skeleton,
                   rest_vertices: np.ndarray, faces: np.ndarray, frames: np.ndarray) -> Drive:
    """Tetrahedron vertices within ``attach_radius`` of a bone are prescribed, moved by linear
    blend skinning (the skeleton's weights carried inward from the nearest rest-surface
    vertex, else weights from distance); Newton starts from the skinned pose with the mesh's
    boundary vertices on the animated surface. Bones that prescribe no vertex are named in
    ``Drive.idle_bones``."""
    distances = segment_distances(points, skeleton.heads, skeleton.tails)   # (n, B)
    attached = distances.min(axis=1) <= skeleton.attach_radius
    if not attached.any():
        raise MeshError(
            f"no material point lies within attach_radius={skeleton.attach_radius:.4g} m of any "
            f"bone (nearest: {distances.min():.4g} m); put the bones inside the body or raise "
            "skeleton.attach_radius")
    if attached.all():
        raise MeshError(
            f"every material point lies within attach_radius={skeleton.attach_radius:.4g} m of "
            "a bone, so nothing is left to simulate; lower skeleton.attach_radius")
    if skeleton.weights is not None:
        # weights given per rest-surface vertex: carried inward from the nearest one
        _, nearest = cKDTree(rest_vertices).query(points)
        weights = skeleton.weights[nearest]
    else:
        weights = distance_weights(distances, skeleton.attach_radius)
    rigged = blend(points, weights, skeleton.transforms)                    # (F, n, 3)
    dirichlet = np.flatnonzero(attached)
    start = rigged.copy()
    boundary = np.unique(boundary_faces(cells)[0])
    start[:, boundary] = surface_start(points[boundary], rest_vertices, faces, frames)
    positions = rigged[:, dirichlet]
    start[:, dirichlet] = positions
    per_bone = np.bincount(distances[dirichlet].argmin(axis=1), minlength=skeleton.n_bones)
    return Drive(dirichlet, positions, start, idle_bones(distances, skeleton), per_bone)


def rig_description(skeleton: Skeleton, drive: Drive | None = None) -> dict:
    """The rig as the set-up prints it and ``rig.json`` keeps it: per bone its name, rest
    head and tail (metres), length and where the length came from, and (with the
    ``drive``) the prescribed vertices nearest to it; the attach radius and the weights with
    their origins (:attr:`Skeleton.origin`; ``"authored: ..."`` where it is empty)."""
    names = list(skeleton.names) or [f"bone{b}" for b in range(skeleton.n_bones)]
    lengths = np.linalg.norm(skeleton.tails - skeleton.heads, axis=1)
    origin = skeleton.origin
    lengths_from = origin.get("lengths") or ["authored: the file's bone segment"] * len(names)
    weights_from = origin.get("weights") or (
        "authored: the file's skinning weights" if skeleton.weights is not None else
        "derived: from each vertex's distance to the bones (reach attach_radius)")
    bones = [{"name": name, "head_m": skeleton.heads[b].tolist(),
              "tail_m": skeleton.tails[b].tolist(), "length_m": float(lengths[b]),
              "length_from": lengths_from[b]} for b, name in enumerate(names)]
    if drive is not None and drive.per_bone is not None:
        for bone, n in zip(bones, drive.per_bone):
            bone["driven_vertices"] = int(n)
    return {"bones": bones, "attach_radius_m": float(skeleton.attach_radius),
            "attach_radius_from": origin.get("attach_radius",
                                             "authored: the file's attach radius"),
            "weights_from": weights_from}


def rig_lines(description: dict) -> list[str]:
    """The console's lines of a :func:`rig_description`: one per bone, then the radius and
    the weights (``authored``/``derived`` and how)."""
    lines = []
    for bone in description["bones"]:
        driven = f", {bone['driven_vertices']:,} driven vertices" \
            if "driven_vertices" in bone else ""
        lines.append(f"bone {bone['name']}: {bone['length_m']:.4g} m{driven}; length "
                     f"{bone['length_from']}")
    lines.append(f"attach radius {description['attach_radius_m']:.4g} m: "
                 f"{description['attach_radius_from']}")
    lines.append(f"weights {description['weights_from']}")
    return lines


def surface_drive(points: np.ndarray, driven: DrivenSurface, rest_vertices: np.ndarray,
                  faces: np.ndarray, frames: np.ndarray) -> Drive:
    """Tetrahedron vertices within ``driven.tolerance`` of the driven surface region (its
    whole triangles, else its vertices) are prescribed; every vertex moves with the closest
    point of the animated surface (:func:`surface_start`)."""
    import trimesh

    full = driven.mask[faces].all(axis=1)
    if full.any():
        region = trimesh.Trimesh(rest_vertices, faces[full], process=False)
        _, distance, _ = trimesh.proximity.closest_point(region, points)
    else:
        distance, _ = cKDTree(rest_vertices[driven.mask]).query(points)
    near = distance <= driven.tolerance
    if not near.any():
        raise MeshError(
            f"no tetrahedron vertex lies within driven.tolerance={driven.tolerance:.4g} m of "
            f"the driven surface (nearest: {distance.min():.4g} m); raise driven.tolerance")
    if near.all():
        raise MeshError(
            "every tetrahedron vertex lies within driven.tolerance of the driven surface, so "
            "nothing is left to simulate; lower driven.tolerance")
    start = surface_start(points, rest_vertices, faces, frames)
    dirichlet = np.flatnonzero(near)
    positions = start[:, dirichlet]
    start[:, dirichlet] = positions
    return Drive(dirichlet, positions, start)
