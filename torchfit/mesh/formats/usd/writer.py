"""Writing USD (the extra ``usd``): a skinned rig, simulated frames, a tetrahedral mesh.

:func:`write_skinned_usd` writes the animation format's rig (bones, per-frame ``[A | t]``,
per-vertex weights, rest-pose corrective shapes) as a stage that
:func:`.reader.load_usd` (and any UsdSkel client) poses back to the same frames:

- joints: one per bone at its head, moved by the bone's transform, carrying the bone's weight;
  a bone whose tail starts no other bone gets an end joint there (child of the bone's joint,
  same motion, no weight). A bone is the child of the bone whose tail is its head. So
  :func:`..joints.skeleton_from_joints` reads the same bones back.
- bind transforms: translations to the joints' rest positions; the rest pose the bind pose;
  the ``SkelAnimation`` holds each joint's local translation, rotation and scale per frame
  (time codes ``0 .. F-1`` at ``fps``), the corrective shapes' weights as blend-shape weights.
- ``torchfit:attachRadius`` on the skeleton; lengths in metres (``metersPerUnit`` 1), the
  stage's ``upAxis`` Z unless ``up_axis`` says Y (the coordinates are written as given).

Bone transforms must be rigid (rotation and translation; a USD joint holds no shear).

:func:`write_point_cache_usd` writes frames ``(F, V, 3)`` as a mesh prim whose ``points``
and ``extent`` hold one time sample per frame; given the user's stage (``over``), the new
layer has it as a sublayer and converts metres to its ``metersPerUnit``, so the TD opens
(or references) one layer and sees the simulated body next to the original.
:func:`write_tet_mesh_usd` writes a ``UsdGeom.TetMesh`` (points, tetrahedra, surface
faces) with per-tetrahedron fields as ``uniform`` primvars ``primvars:torchfit:<name>`` and
the material as the deformable-physics draft names it (per tetrahedron, and a physics
material bound to the TetMesh). :func:`write_vertex_field_usd` writes a per-vertex field as
a primvar on an ``over`` of the user's own mesh prim.
"""
from __future__ import annotations

import os
from typing import Any
from pathlib import Path

import numpy as np

from ..joints import bone_joints
from ...rig import Skeleton


def _quaternions(rotations: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` (w, x, y, z) of rotation matrices ``(..., 3, 3)``."""
    from scipy.spatial.transform import Rotation

    xyzw = Rotation.from_matrix(rotations.reshape(-1, 3, 3)).as_quat()
    return np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1).reshape(*rotations.shape[:-2], 4)


def write_skinned_usd(path: str | Path, rest_vertices: np.ndarray, faces: np.ndarray,
                      skeleton: Skeleton, shapes: dict[str, np.ndarray] | None = None,
                      shape_weights: np.ndarray | None = None, fps: float = 24.0,
                      up_axis: str = "Z") -> Path:
    """Write a skinned mesh, its skeleton and animation to ``path`` (``.usda``/``.usdc``);
    ``up_axis`` ``"Y"`` or ``"Z"``: the stage's ``upAxis`` (the points are not turned).

    Args:
        rest_vertices: ``(V, 3)`` metres; faces ``(T, 3)``.
        skeleton: bones, rigid transforms ``(F, B, 3, 4)``, weights ``(V, B)`` (required).
        shapes: name -> ``(V, 3)`` rest-pose offsets (blend shapes), applied before skinning
            with ``shape_weights`` ``(F, K)`` (columns in the order of ``shapes``).
    """
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt

    if skeleton.weights is None:
        raise ValueError("write_skinned_usd needs the skeleton's per-vertex weights")
    if up_axis.upper() not in ("Y", "Z"):
        raise ValueError(f"up_axis must be 'Y' or 'Z' (USD's up axes), got {up_axis!r}")
    shapes = shapes or {}
    paths, parents, positions, mover = bone_joints(skeleton)
    F, J = skeleton.transforms.shape[0], len(paths)
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up_axis.upper() == "Y" else
                           UsdGeom.Tokens.z)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(F - 1)
    stage.SetTimeCodesPerSecond(fps)
    root = UsdSkel.Root.Define(stage, "/Rig")
    stage.SetDefaultPrim(root.GetPrim())
    usd_skeleton = UsdSkel.Skeleton.Define(stage, "/Rig/Skeleton")
    bind = np.tile(np.eye(4), (J, 1, 1))
    bind[:, 3, :3] = positions                                       # row vectors: [x, 1] @ M
    usd_skeleton.CreateJointsAttr(paths)
    usd_skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray.FromNumpy(bind))
    local_rest = bind.copy()
    has_parent = parents >= 0
    local_rest[has_parent, 3, :3] -= positions[parents[has_parent]]
    usd_skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray.FromNumpy(local_rest))
    usd_skeleton.GetPrim().CreateAttribute("torchfit:attachRadius", Sdf.ValueTypeNames.Double
                                           ).Set(float(skeleton.attach_radius))
    # joint (skeleton-space) transforms per frame: bind, then the bone's motion
    motion = np.tile(np.eye(4), (F, J, 1, 1))
    A = skeleton.transforms[:, mover][..., :3]
    t = skeleton.transforms[:, mover][..., 3]
    motion[..., :3, :3] = np.swapaxes(A, -1, -2)                     # row-vector form
    motion[..., 3, :3] = t
    world = np.einsum("jab,fjbc->fjac", bind, motion)
    local = world.copy()
    inverse_parent = np.linalg.inv(world[:, np.maximum(parents, 0)])
    local[:, has_parent] = np.einsum("fjab,fjbc->fjac", world[:, has_parent],
                                     inverse_parent[:, has_parent])
    animation = UsdSkel.Animation.Define(stage, "/Rig/Skeleton/Animation")
    animation.CreateJointsAttr(paths)
    translations = animation.CreateTranslationsAttr()
    rotations = animation.CreateRotationsAttr()
    scales = animation.CreateScalesAttr()
    quaternions = _quaternions(np.swapaxes(local[..., :3, :3], -1, -2))
    if shapes:
        animation.CreateBlendShapesAttr(list(shapes))
        shape_attr = animation.CreateBlendShapeWeightsAttr()
    for f in range(F):
        translations.Set(Vt.Vec3fArray.FromNumpy(local[f, :, 3, :3].astype(np.float32)), f)
        rotations.Set(Vt.QuatfArray([Gf.Quatf(*map(float, q)) for q in quaternions[f]]), f)
        scales.Set(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)] * J), f)
        if shapes:
            shape_attr.Set(Vt.FloatArray([float(w) for w in shape_weights[f]]), f)
    UsdSkel.BindingAPI.Apply(usd_skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [animation.GetPath()])
    mesh = UsdGeom.Mesh.Define(stage, "/Rig/Body")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(rest_vertices, np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(faces)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([int(i) for i in np.ravel(faces)]))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([usd_skeleton.GetPath()])
    weights = np.zeros((len(rest_vertices), J))
    weights[:, :skeleton.n_bones] = skeleton.weights
    order = np.argsort(-weights, axis=1, kind="stable")
    size = int((weights > 0).sum(axis=1).max())
    indices = order[:, :size]
    binding.CreateJointIndicesPrimvar(False, size).Set(
        Vt.IntArray([int(i) for i in indices.ravel()]))
    binding.CreateJointWeightsPrimvar(False, size).Set(
        Vt.FloatArray([float(w) for w in np.take_along_axis(weights, indices, 1).ravel()]))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1))
    if shapes:
        targets = []
        for name, offsets in shapes.items():
            shape = UsdSkel.BlendShape.Define(stage, f"/Rig/Body/{name}")
            moved = np.flatnonzero(np.abs(offsets).max(axis=1) > 0)
            shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(
                np.asarray(offsets[moved], np.float32)))
            shape.CreatePointIndicesAttr(Vt.IntArray([int(i) for i in moved]))
            targets.append(shape.GetPath())
        binding.CreateBlendShapesAttr(list(shapes))
        binding.CreateBlendShapeTargetsRel().SetTargets(targets)
    stage.GetRootLayer().Save()
    return Path(path)


def write_point_cache_usd(path: str | Path, faces: np.ndarray, frames: np.ndarray, *,
                          prim: str = "/Simulated", times: list[float] | None = None,
                          over: str | Path | None = None, fps: float = 24.0) -> Path:
    """Write ``frames`` ``(F, V, 3)`` (metres, world) as a time-sampled mesh at ``prim``
    (missing ancestors are defined as plain ``Xform`` prims; an existing ancestor with a
    transform of its own would move the frames: choose a path under untransformed prims).

    Args:
        faces: ``(T, 3)`` triangles of the frames' vertices.
        times: the time code of each frame (default ``0 .. F-1``).
        over: the user's stage: sublayered under the new layer, whose ``metersPerUnit``,
            up axis and time codes per second are taken from it (lengths converted).
    """
    from pxr import Sdf, Usd, UsdGeom, Vt

    frames = np.asarray(frames, dtype=np.float64)
    times = list(range(len(frames))) if times is None else [float(t) for t in times]
    if len(times) != len(frames):
        raise ValueError(f"{len(times)} times for {len(frames)} frames")
    path = Path(path)
    stage = Usd.Stage.CreateNew(str(path))
    scale = 1.0
    if over is not None:
        original = Usd.Stage.Open(str(over))
        scale = float(UsdGeom.GetStageMetersPerUnit(original))
        UsdGeom.SetStageUpAxis(stage, UsdGeom.GetStageUpAxis(original))
        stage.SetTimeCodesPerSecond(original.GetTimeCodesPerSecond())
        relative = os.path.relpath(Path(over).resolve(), path.resolve().parent)
        stage.GetRootLayer().subLayerPaths.append(Path(relative).as_posix())
    else:
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
        stage.SetTimeCodesPerSecond(fps)
    UsdGeom.SetStageMetersPerUnit(stage, scale)
    stage.SetStartTimeCode(min(times))
    stage.SetEndTimeCode(max(times))
    for parent in Sdf.Path(prim).GetPrefixes()[:-1]:
        if not stage.GetPrimAtPath(parent):
            UsdGeom.Xform.Define(stage, parent)
    mesh = UsdGeom.Mesh.Define(stage, prim)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(faces)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([int(i) for i in np.ravel(faces)]))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    points, extent = mesh.CreatePointsAttr(), mesh.CreateExtentAttr()
    for time, positions in zip(times, frames / scale):
        points.Set(Vt.Vec3fArray.FromNumpy(positions.astype(np.float32)), time)
        extent.Set(Vt.Vec3fArray.FromNumpy(np.stack([positions.min(0), positions.max(0)])
                                           .astype(np.float32)), time)
    stage.GetRootLayer().Save()
    return path


#: the applied API schemas of the deformable-physics draft's material (codeless schemas)
MATERIAL_SCHEMAS = ("OmniPhysicsBaseMaterialAPI", "OmniPhysicsDeformableMaterialAPI")
#: the draft's names of the material properties written per tetrahedron
MATERIAL_PROPERTIES = ("youngsModulus", "poissonsRatio", "density")


def write_tet_mesh_usd(path: str | Path, points: np.ndarray, cells: np.ndarray,
                       fields: dict[str, np.ndarray] | None = None, *,
                       prim: str = "/Body", material: dict[str, np.ndarray] | None = None,
                       custom: dict[str, str | float] | None = None,
                       units: dict[str, str] | None = None) -> Path:
    """Write a tetrahedral mesh (``points`` ``(n, 3)`` metres, ``cells`` ``(m, 4)``) as a
    ``UsdGeom.TetMesh`` with each field ``(m,)`` as a per-tetrahedron primvar
    ``primvars:torchfit:<name>``.

    ``material``: ``youngsModulus``, ``poissonsRatio``, ``density`` ``(m,)`` each, as the
    deformable-physics draft names them (docs/guide/dcc.md): per tetrahedron as ``uniform``
    primvars ``primvars:<name>``, and a ``UsdShade.Material`` ``<prim>/PhysicsMaterial``
    with the draft's ``OmniPhysicsDeformableMaterialAPI`` (``omniphysics:youngsModulus``,
    ``omniphysics:poissonsRatio``) and ``OmniPhysicsBaseMaterialAPI``
    (``omniphysics:density``) holding their volume-weighted means, bound to the TetMesh for
    the ``physics`` purpose. ``custom``: ``customData`` on the TetMesh and the material
    (units, where the values come from). ``units``: per field or material name, its unit
    (``Pa``, ``relative to problem.E0``, ``kg/m^3``), written on that attribute as
    ``customData`` ``torchfit:units`` and in its ``documentation``."""
    from pxr import Sdf, Usd, UsdGeom, UsdShade, Vt

    points = np.asarray(points, dtype=np.float64)
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    tet = UsdGeom.TetMesh.Define(stage, prim)
    tet.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
    tet.CreateTetVertexIndicesAttr(Vt.Vec4iArray.FromNumpy(np.asarray(cells, np.int32)))
    tet.CreateSurfaceFaceVertexIndicesAttr(UsdGeom.TetMesh.ComputeSurfaceFaces(tet))
    tet.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(
        np.stack([points.min(0), points.max(0)]).astype(np.float32)))
    primvars = UsdGeom.PrimvarsAPI(tet.GetPrim())
    for name, values in (fields or {}).items():
        values = np.asarray(values, dtype=np.float64).reshape(-1)
        if values.shape != (len(cells),):
            raise ValueError(f"field {name} has {values.size} values for {len(cells)} "
                             "tetrahedra")
        created = primvars.CreatePrimvar(f"torchfit:{name}", Sdf.ValueTypeNames.DoubleArray,
                                         UsdGeom.Tokens.uniform)
        created.Set(Vt.DoubleArray.FromNumpy(values))
        _label(created.GetAttr(), name, units)
    for key, value in (custom or {}).items():
        tet.GetPrim().SetCustomDataByKey(key, value)
    if material:
        volumes = np.abs(np.linalg.det(points[cells[:, 1:]] - points[cells[:, :1]])) / 6.0
        shade = UsdShade.Material.Define(stage, f"{prim}/PhysicsMaterial")
        for schema in MATERIAL_SCHEMAS:
            shade.GetPrim().AddAppliedSchema(schema)
        for name in MATERIAL_PROPERTIES:
            values = np.asarray(material[name], dtype=np.float64).reshape(-1)
            if values.shape != (len(cells),):
                raise ValueError(f"material {name} has {values.size} values for "
                                 f"{len(cells)} tetrahedra")
            created = primvars.CreatePrimvar(name, Sdf.ValueTypeNames.FloatArray,
                                             UsdGeom.Tokens.uniform)
            created.Set(Vt.FloatArray.FromNumpy(values.astype(np.float32)))
            _label(created.GetAttr(), name, units)
            mean = shade.GetPrim().CreateAttribute(f"omniphysics:{name}",
                                                   Sdf.ValueTypeNames.Float)
            mean.Set(float(values @ volumes / volumes.sum()))
            _label(mean, name, units, "the volume-weighted mean")
        for key, value in (custom or {}).items():
            shade.GetPrim().SetCustomDataByKey(key, value)
        UsdShade.MaterialBindingAPI.Apply(tet.GetPrim()).Bind(
            shade, UsdShade.Tokens.weakerThanDescendants, "physics")
    stage.SetDefaultPrim(tet.GetPrim())
    stage.GetRootLayer().Save()
    return Path(path)


def _label(attribute: Any, name: str, units: dict[str, str] | None, what: str = "") -> None:
    """Write ``units[name]`` on ``attribute`` (``customData`` ``torchfit:units`` and its
    ``documentation``), so that a DCC shows what the numbers are."""
    if not units or name not in units:
        return
    attribute.SetCustomDataByKey("torchfit:units", units[name])
    attribute.SetDocumentation(f"{name}{' (' + what + ')' if what else ''}: {units[name]}")


def write_vertex_field_usd(path: str | Path, name: str, values: np.ndarray, *,
                           over: str | Path | None = None, prim: str = "",
                           rest: np.ndarray | None = None, faces: np.ndarray | None = None,
                           custom: dict[str, str | float] | None = None,
                           units: dict[str, str] | None = None) -> Path:
    """A per-vertex field ``values`` ``(V,)`` as the primvar ``primvars:<name>`` (``vertex``
    interpolation) on the user's mesh: given the user's stage ``over`` and its mesh ``prim``,
    a layer that sublayers the stage and holds an ``over`` of the prim (the DCC opens this
    layer and sees the field on its own mesh); otherwise a ``Mesh`` ``/Rest`` of ``rest``
    ``(V, 3)`` metres and ``faces`` ``(T, 3)``. ``custom``: ``customData`` on the primvar's
    attribute; ``units``: ``{name: unit}``, as for :func:`write_tet_mesh_usd`."""
    from pxr import Sdf, Usd, UsdGeom, Vt

    values = np.asarray(values, dtype=np.float64).reshape(-1)
    path = Path(path)
    stage = Usd.Stage.CreateNew(str(path))
    if over is not None:
        original = Usd.Stage.Open(str(over))
        UsdGeom.SetStageMetersPerUnit(stage, UsdGeom.GetStageMetersPerUnit(original))
        UsdGeom.SetStageUpAxis(stage, UsdGeom.GetStageUpAxis(original))
        stage.SetTimeCodesPerSecond(original.GetTimeCodesPerSecond())
        if original.HasAuthoredTimeCodeRange():
            stage.SetStartTimeCode(original.GetStartTimeCode())
            stage.SetEndTimeCode(original.GetEndTimeCode())
        relative = os.path.relpath(Path(over).resolve(), path.resolve().parent)
        stage.GetRootLayer().subLayerPaths.append(Path(relative).as_posix())
        target = stage.OverridePrim(prim)
        if original.GetDefaultPrim():
            stage.SetDefaultPrim(stage.GetPrimAtPath(original.GetDefaultPrim().GetPath()))
    else:
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
        mesh = UsdGeom.Mesh.Define(stage, prim or "/Rest")
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(rest, np.float32)))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(faces)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([int(i) for i in np.ravel(faces)]))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        target = mesh.GetPrim()
        stage.SetDefaultPrim(target)
    primvar = UsdGeom.PrimvarsAPI(target).CreatePrimvar(
        name, Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex)
    primvar.Set(Vt.FloatArray.FromNumpy(values.astype(np.float32)))
    for key, value in (custom or {}).items():
        primvar.GetAttr().SetCustomDataByKey(key, value)
    _label(primvar.GetAttr(), name, units)
    stage.GetRootLayer().Save()
    return path
