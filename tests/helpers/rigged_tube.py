"""A rigged body that is not the arm: a capsule tube along x (or y) with a bending two-bone rig.

Capsule of radius 0.05 m and 0.5 m between the cap centres, centred at ``OFFSET`` (away from
the origin, so that a transposed rotation also misplaces the joint), its axis along ``axis``.
Bones ``base`` and ``tip`` meet at the centre; the tip bends about the third axis by
``angles`` degrees. Frames: linear blend skinning with distance weights (given in the
manifest), plus a bulge of up to ``bulge`` metres on one side of the base half, growing with
the bend (a corrective the check must accept).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from torchfit.mesh import Animation, Skeleton, write_animation
from torchfit.mesh.rig import blend, distance_weights, segment_distances

RADIUS = 0.05
HALF = 0.25
OFFSET = np.array([0.3, 0.1, -0.2])
ANGLES = (0.0, 20.0, 45.0, 70.0, 90.0)


def _frame(axis: str) -> np.ndarray:
    """Rotation taking the capsule's z axis to ``axis`` (columns: images of x, y, z)."""
    if axis == "x":
        return np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    if axis == "y":
        return np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
    return np.eye(3)


def tube_animation(axis: str = "x", angles=ANGLES, bulge: float = 0.015,
                   count: int = 24) -> dict:
    """Rest vertices, faces, frames ``(F, V, 3)`` and the skeleton (weights given)."""
    mesh = trimesh.creation.capsule(height=2 * HALF, radius=RADIUS, count=[count, count])
    R0 = _frame(axis)
    rest = np.asarray(mesh.vertices) @ R0.T + OFFSET
    direction = R0[:, 2]
    heads = np.stack([OFFSET - HALF * direction, OFFSET])
    tails = np.stack([OFFSET, OFFSET + HALF * direction])
    bend_axis = R0[:, 0]                                     # perpendicular to the tube
    transforms = np.zeros((len(angles), 2, 3, 4))
    transforms[:, :, :, :3] = np.eye(3)
    for f, degrees in enumerate(angles):
        a = np.radians(degrees)
        K = np.cross(np.eye(3), bend_axis)                   # cross-product matrix
        R = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
        transforms[f, 1, :, :3] = R
        transforms[f, 1, :, 3] = OFFSET - R @ OFFSET
    weights = distance_weights(segment_distances(rest, heads, tails), 1.5 * RADIUS)
    local = (rest - OFFSET) @ R0                             # capsule coordinates
    side = np.clip(local[:, 1] / RADIUS, 0, 1) ** 2 * np.clip(-local[:, 2] / HALF, 0, 1)
    amount = bulge * (np.asarray(angles) / max(angles))[:, None] * side[None]
    frames = blend(rest, weights, transforms) + amount[..., None] * R0[:, 1]
    skeleton = Skeleton(heads, tails, transforms, 0.4 * RADIUS, weights, ["base", "tip"])
    return {"rest": rest, "faces": np.asarray(mesh.faces), "frames": frames,
            "skeleton": skeleton}


def tube(axis: str = "x", **kwargs) -> Animation:
    """The tube as a loaded :class:`Animation` (not written)."""
    data = tube_animation(axis, **kwargs)
    return Animation(Path(f"tube-{axis}/animation.yaml"), data["rest"], data["faces"],
                     data["frames"], 1.0, data["skeleton"])


def write_tube(folder: Path, axis: str = "x", **kwargs) -> Path:
    """The tube written as an animation folder; returns the folder."""
    data = tube_animation(axis, **kwargs)
    write_animation(folder, data["rest"], data["faces"], data["frames"],
                    skeleton=data["skeleton"])
    return folder


def write_tube_stage(path: Path, axis: str = "x", at_origin: bool = False, **kwargs) -> Path:
    """The tube as a third-party UsdSkel stage (usd-core): joints ``base`` and ``base/tip``
    at the bones' heads, no end joint, no ``torchfit:boneLength`` nor ``torchfit:attachRadius``
    (the reader derives them), the tube's weights and transforms (no bulge: UsdSkel skins the
    frames). ``at_origin``: every joint's bind transform the identity (all joints at the
    origin), the animation chosen so that the skinning still gives the same frames."""
    from pxr import Gf, Usd, UsdGeom, UsdSkel, Vt
    from scipy.spatial.transform import Rotation

    data = tube_animation(axis, bulge=0.0, **kwargs)
    skeleton = data["skeleton"]

    def homogeneous(transform: np.ndarray) -> np.ndarray:
        m = np.eye(4)
        m[:3] = transform
        return m

    def translation(t: np.ndarray) -> np.ndarray:
        m = np.eye(4)
        m[:3, 3] = t
        return m

    bind = [np.eye(4), np.eye(4)] if at_origin else \
        [translation(skeleton.heads[0]), translation(skeleton.heads[1])]
    row = lambda m: Gf.Matrix4d(*np.asarray(m.T, dtype=np.float64).ravel().tolist())  # noqa: E731
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdSkel.Root.Define(stage, "/Root")
    usd_skeleton = UsdSkel.Skeleton.Define(stage, "/Root/Skeleton")
    joints = ["base", "base/tip"]
    usd_skeleton.CreateJointsAttr(joints)
    usd_skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray([row(b) for b in bind]))
    rest_local = [bind[0], np.linalg.inv(bind[0]) @ bind[1]]
    usd_skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray([row(m) for m in rest_local]))
    animation = UsdSkel.Animation.Define(stage, "/Root/Skeleton/Animation")
    animation.CreateJointsAttr(joints)
    for f, transforms in enumerate(skeleton.transforms):
        # skinning = world @ inverse(bind) = the bone's transform: world = transform @ bind
        world = [homogeneous(transforms[b]) @ bind[b] for b in range(2)]
        local = [world[0], np.linalg.inv(world[0]) @ world[1]]
        quats = [Rotation.from_matrix(m[:3, :3]).as_quat() for m in local]
        animation.CreateTranslationsAttr().Set(
            Vt.Vec3fArray([Gf.Vec3f(*map(float, m[:3, 3])) for m in local]), float(f))
        animation.CreateRotationsAttr().Set(Vt.QuatfArray(
            [Gf.Quatf(float(q[3]), float(q[0]), float(q[1]), float(q[2])) for q in quats]),
            float(f))
        animation.CreateScalesAttr().Set(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)] * 2), float(f))
    UsdSkel.BindingAPI.Apply(usd_skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [animation.GetPath()])
    mesh = UsdGeom.Mesh.Define(stage, "/Root/Tube")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(data["rest"].astype(np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(data["faces"])))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(data["faces"].ravel().tolist()))
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([usd_skeleton.GetPath()])
    binding.CreateJointIndicesPrimvar(False, 2).Set(Vt.IntArray([0, 1] * len(data["rest"])))
    binding.CreateJointWeightsPrimvar(False, 2).Set(
        Vt.FloatArray(skeleton.weights.ravel().tolist()))
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(len(skeleton.transforms) - 1)
    stage.SetDefaultPrim(root.GetPrim())
    stage.GetRootLayer().Save()
    return path
