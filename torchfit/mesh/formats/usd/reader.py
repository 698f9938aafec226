"""A USD stage as an animation: a UsdSkel-skinned mesh or a point cache (the extra ``usd``).

``problem.path=<file>.usd|.usda|.usdc|.usdz`` reads, with Pixar's ``usd-core`` (``pxr``,
imported only here and only then), one mesh prim of the stage into the same
:class:`~torchfit.mesh.Animation` as the folder format:

- **a skinned mesh** (a ``UsdGeom.Mesh`` with ``SkelBindingAPI`` bound to a
  ``UsdSkel.Skeleton`` with a ``SkelAnimation``): rest points (the ``points`` at the default
  time, else at the first frame) and faces (polygons as fans from their first vertex, order
  and winding kept), the joints, their bind transforms and per-frame skinning transforms, the
  weights and joint indices (any ``elementSize``, ``constant`` or ``vertex`` interpolation,
  indices in the mesh's own ``skel:joints`` order where it has one). The frames are the posed
  points UsdSkel computes (blend shapes, then ``SkinningQuery.ComputeSkinnedPoints`` with the
  ``geomBindTransform``), so the targets are what the TD sees; rest and frames are in the
  skeleton's space, placed in the world by the skeleton prim's transform (the skinned mesh's
  own transform is ignored, as UsdSkel says; with ``skel:skinningMethod`` dualQuaternion the
  frames are UsdSkel's, the interior's drive stays linear). Bones: the joints' segments
  (:func:`..joints.skeleton_from_joints`: an end joint's bone reaches over the vertices its
  weights dominate, or ``torchfit:boneLength``, a float array on the skeleton prim with one
  length per joint in stage units, 0 where the data decide); ``attach_radius`` from the
  float attribute ``torchfit:attachRadius`` (stage units) on the mesh or skeleton, else the
  default there; the skeleton says which was authored and which derived, and a degenerate
  joint tree (weighted joints that coincide, bones away from their flesh) is refused there.
- **a point cache**: a mesh whose ``points`` are time-sampled; the driven vertices are the
  primvar ``primvars:torchfit:driven`` (bool or int per vertex, nonzero: driven), the
  tolerance ``torchfit:drivenTolerance`` (stage units; default: the mean edge length of the
  rest surface). Rest: ``points`` at the default time, else the first sample; each frame
  placed in the world by the mesh's transform at its time.

Which prim: ``problem.prim`` (a prim path); by default the one skinned mesh, else the one
point cache. Frames: every authored time sample (joint transforms and blend-shape weights of
the animation, or the points), in time order; ``problem.frames`` picks among them by index.
Units: lengths are multiplied by the stage's ``metersPerUnit``. The coordinates are kept as
authored (a Y-up stage stays Y-up); the stage's ``upAxis`` (``UsdGeom.GetStageUpAxis``: Y
or Z) is the animation's ``up`` (``(0, 1, 0)`` or ``(0, 0, 1)``), which the pictures stand
the body on.
USD matrices act on row vectors, ``[x, 1] @ M``. Errors are one line
(:class:`~torchfit.mesh.AnimationError`).
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

import numpy as np

from ...animation import Animation, AnimationError
from ..joints import fan_triangles, row_vector_transforms, skeleton_from_joints
from ...rig import DrivenSurface

SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
_log = logging.getLogger(__name__)


def _pxr(path: Path) -> Any:
    try:
        from pxr import Usd, UsdGeom, UsdSkel, Vt  # noqa: F401
    except ImportError as err:
        raise AnimationError(f"{path}: reading USD needs the optional extra 'usd': pip install "
                             f"'torchfit[usd]' (Pixar's usd-core) ({err})") from err
    import pxr

    return pxr


def open_stage(path: Path) -> Any:
    """``Usd.Stage.Open(path)``, or :class:`AnimationError` in one line where the file is not a
    stage (random bytes, a ``.npy``): the USD library's reason (the first quoted message of
    its C++ errors, which it raises as ``pxr.Tf.ErrorException`` of many lines)."""
    pxr = _pxr(path)
    try:
        stage = pxr.Usd.Stage.Open(str(path))
    except Exception as err:  # noqa: BLE001 - pxr raises Tf errors of many kinds
        quoted = [line.rsplit(" : ", 1)[-1].strip(" '") for line in str(err).splitlines()
                  if " : " in line]
        why = quoted[0] if quoted else (str(err).strip().splitlines() or [type(err).__name__])[-1]
        raise AnimationError(f"{path}: cannot open it as a USD stage ({why}); give a USD "
                             "file (.usd, .usda, .usdc)") from None
    if stage is None:
        raise AnimationError(f"{path}: cannot open it as a USD stage; give a USD file (.usd, "
                             ".usda, .usdc)")
    return stage


def _matrix(m: Any) -> np.ndarray:
    return np.array(m, dtype=np.float64).reshape(4, 4)


def _apply(points: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """Points ``(..., 3)`` times a row-vector 4x4 matrix."""
    return points @ matrix[:3, :3] + matrix[3, :3]


def _candidates(pxr: Any, stage: Any) -> tuple[dict[str, tuple[Any, Any]], list[str]]:
    """Skinned meshes (path -> (skeleton query, skinning query)) and time-sampled meshes."""
    Usd, UsdGeom, UsdSkel = pxr.Usd, pxr.UsdGeom, pxr.UsdSkel
    cache = UsdSkel.Cache()
    skinned: dict[str, tuple[Any, Any]] = {}
    predicate = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
    for prim in stage.Traverse(predicate):
        if prim.IsA(UsdSkel.Root):
            cache.Populate(UsdSkel.Root(prim), predicate)
            for binding in cache.ComputeSkelBindings(UsdSkel.Root(prim), predicate):
                skeleton_query = cache.GetSkelQuery(binding.GetSkeleton())
                for target in binding.GetSkinningTargets():
                    if target.GetPrim().IsA(UsdGeom.Mesh):
                        skinned[str(target.GetPrim().GetPath())] = (skeleton_query, target)
    cached = [str(p.GetPath()) for p in stage.Traverse(predicate) if p.IsA(UsdGeom.Mesh)
              and str(p.GetPath()) not in skinned
              and UsdGeom.Mesh(p).GetPointsAttr().GetNumTimeSamples() >= 1]
    return skinned, cached


def _pick(path: Path, prim: str, skinned: dict, cached: list[str]) -> str:
    if prim:
        if prim not in skinned and prim not in cached:
            raise AnimationError(f"{path}: problem.prim={prim} is neither a skinned mesh nor a "
                                 "mesh with time-sampled points (skinned: "
                                 f"{', '.join(skinned) or 'none'}; point caches: "
                                 f"{', '.join(cached) or 'none'})")
        return prim
    for kind, paths in (("skinned meshes", list(skinned)), ("point caches", cached)):
        if len(paths) > 1:
            raise AnimationError(f"{path}: {len(paths)} {kind} ({', '.join(paths[:4])}); choose "
                                 "one with problem.prim=<prim path>")
        if paths:
            return paths[0]
    raise AnimationError(f"{path}: no skinned mesh (a UsdGeom.Mesh bound to a UsdSkel.Skeleton "
                         "under a SkelRoot) and no mesh with time-sampled points in the stage")


def _surface(pxr: Any, mesh: Any, where: str, time: Any) -> tuple[np.ndarray, np.ndarray]:
    points = mesh.GetPointsAttr().Get(pxr.Usd.TimeCode.Default())
    if points is None:
        points = mesh.GetPointsAttr().Get(time)
    counts = mesh.GetFaceVertexCountsAttr().Get(time)
    indices = mesh.GetFaceVertexIndicesAttr().Get(time)
    if points is None or not len(points) or counts is None or indices is None:
        raise AnimationError(f"{where}: the mesh has no points or no faces")
    rest = np.array(points, dtype=np.float64).reshape(-1, 3)
    faces = fan_triangles(np.array(counts), np.array(indices), where)
    if faces.size and (faces.min() < 0 or faces.max() >= len(rest)):
        raise AnimationError(f"{where}: a face refers to a point out of range [0, {len(rest)})")
    return rest, faces


def _length_attribute(prims: list[Any], name: str) -> float | None:
    for prim in prims:
        attr = prim.GetAttribute(name)
        if attr and attr.HasAuthoredValue():
            return float(attr.Get())
    return None


def _bone_lengths(skeleton_prim: Any, n_joints: int, where: str) -> np.ndarray | None:
    """``torchfit:boneLength`` of the skeleton prim: one length per joint in the skeleton's
    order (stage units; ``<= 0``: from the data), or ``None`` where it is not authored."""
    attr = skeleton_prim.GetAttribute("torchfit:boneLength")
    if not attr or not attr.HasAuthoredValue():
        return None
    values = np.array(attr.Get(), dtype=np.float64).reshape(-1)
    if values.shape != (n_joints,):
        raise AnimationError(f"{where}: torchfit:boneLength on {skeleton_prim.GetPath()} has "
                             f"{values.size} values for {n_joints} joints; give one per joint "
                             "(0 where the length comes from the skinning weights)")
    return values


def _influences(query: Any, n_points: int, joint_index: dict[str, int], where: str
                ) -> np.ndarray:
    """Weights ``(V, J)`` in the skeleton's joint order."""
    size = query.GetNumInfluencesPerComponent()
    result = query.ComputeJointInfluences()
    if not result:
        raise AnimationError(f"{where}: cannot read skel:jointIndices and skel:jointWeights")
    indices, weights = (np.array(a) for a in result)
    rows = n_points if query.GetInterpolation() == "vertex" else 1
    if indices.size != rows * size or weights.size != rows * size:
        raise AnimationError(f"{where}: {weights.size} joint weights and {indices.size} joint "
                             f"indices for {rows} {'points' if rows > 1 else 'constant row'} x "
                             f"elementSize {size}; the weights must match the points")
    order = query.GetJointOrder()
    names = [str(n) for n in order] if order else list(joint_index)
    missing = [n for n in names if n not in joint_index]
    if missing:
        raise AnimationError(f"{where}: skel:joints names {missing[0]}, not a joint of the "
                             "skeleton")
    to_skeleton = np.array([joint_index[n] for n in names], dtype=np.int64)
    if indices.size and (indices.min() < 0 or indices.max() >= len(names)):
        raise AnimationError(f"{where}: a joint index lies outside [0, {len(names)})")
    out = np.zeros((rows, len(joint_index)))
    row = np.repeat(np.arange(rows), size)
    np.add.at(out, (row, to_skeleton[indices.reshape(-1)]), weights.reshape(-1))
    return np.broadcast_to(out, (n_points, len(joint_index))).copy()


def _skinned(pxr: Any, path: Path, prim: Any, skeleton_query: Any, query: Any,
             scale: float) -> Animation:
    Usd, UsdGeom, UsdSkel, Vt = pxr.Usd, pxr.UsdGeom, pxr.UsdSkel, pxr.Vt
    where = f"{path}:{prim.GetPath()}"
    anim = skeleton_query.GetAnimQuery()
    if not anim:
        raise AnimationError(f"{where}: the skeleton {skeleton_query.GetSkeleton().GetPath()} "
                             "has no SkelAnimation (skel:animationSource); nothing moves")
    times = sorted(set(anim.GetJointTransformTimeSamples())
                   | set(anim.GetBlendShapeWeightTimeSamples()))
    codes = [Usd.TimeCode(t) for t in times] or [Usd.TimeCode.EarliestTime()]
    rest_local, faces = _surface(pxr, UsdGeom.Mesh(prim), where, codes[0])
    skeleton_prim = skeleton_query.GetSkeleton().GetPrim()
    xformable = UsdGeom.Xformable(skeleton_prim)
    world = np.stack([_matrix(xformable.ComputeLocalToWorldTransform(c)) for c in codes])
    geom_bind = _matrix(query.GetGeomBindTransform())
    rest_skel = _apply(rest_local, geom_bind)
    joints = [str(j) for j in skeleton_query.GetJointOrder()]
    joint_index = {name: j for j, name in enumerate(joints)}
    weights = _influences(query, len(rest_local), joint_index, where)
    # blend shapes (in the mesh's space) before skinning, as UsdSkel evaluates them
    blend = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(prim)) if query.HasBlendShapes() \
        else None
    frames = np.empty((len(codes), len(rest_local), 3))
    skinning = np.empty((len(codes), len(skeleton_query.GetJointOrder()), 4, 4))
    for f, code in enumerate(codes):
        points = Vt.Vec3fArray.FromNumpy(rest_local.astype(np.float32))
        if blend is not None:
            shape_weights = anim.ComputeBlendShapeWeights(code)
            mapper = query.GetBlendShapeMapper()
            if mapper and not mapper.IsNull():
                shape_weights = mapper.Remap(shape_weights)
            sub_weights, shape_indices, sub_indices = blend.ComputeSubShapeWeights(shape_weights)
            blend.ComputeDeformedPoints(sub_weights, shape_indices, sub_indices,
                                        blend.ComputeBlendShapePointIndices(),
                                        blend.ComputeSubShapePointOffsets(), points)
        transforms = skeleton_query.ComputeSkinningTransforms(code)
        if not query.ComputeSkinnedPoints(transforms, points, code):
            raise AnimationError(f"{where}: UsdSkel cannot skin the mesh at time "
                                 f"{code.GetValue()} (see USD's diagnostics above)")
        frames[f] = _apply(np.array(points, dtype=np.float64), world[f])
        skinning[f] = np.array(transforms, dtype=np.float64).reshape(-1, 4, 4)
    bind = np.array(skeleton_query.GetJointWorldBindTransforms(),
                    dtype=np.float64).reshape(-1, 4, 4)
    to_rest = np.linalg.inv(world[0])
    # x_world' = x_world @ inv(W_0) @ S_j(f) @ W_f, as column-vector [A | t]
    joint_matrices = np.einsum("ab,fjbc,fcd->fjad", to_rest, skinning, world)
    rest = _apply(rest_skel, world[0])
    positions = _apply(bind[:, 3, :3], world[0])
    parents = np.array(skeleton_query.GetTopology().GetParentIndices(), dtype=np.int64)
    transforms = row_vector_transforms(joint_matrices)
    transforms[..., 3] *= scale
    radius = _length_attribute([prim, skeleton_prim], "torchfit:attachRadius")
    lengths = _bone_lengths(skeleton_prim, len(joints), where)
    skeleton = skeleton_from_joints(positions * scale, parents, transforms, weights,
                                    [j.rsplit("/", 1)[-1] for j in joints],
                                    None if radius is None else radius * scale, rest * scale,
                                    where, None if lengths is None else lengths * scale,
                                    authored_as=("the stage's torchfit:attachRadius",
                                                 "the stage's torchfit:boneLength"))
    names = [f"{path.name}:{prim.GetPath()}@{c.GetValue():g}" for c in codes]
    return _animation(path, rest * scale, faces, frames * scale, scale, names, skeleton=skeleton,
                      prim=str(prim.GetPath()))


def _point_cache(pxr: Any, path: Path, prim: Any, scale: float) -> Animation:
    Usd, UsdGeom = pxr.Usd, pxr.UsdGeom
    where = f"{path}:{prim.GetPath()}"
    mesh = UsdGeom.Mesh(prim)
    attr = mesh.GetPointsAttr()
    codes = [Usd.TimeCode(t) for t in attr.GetTimeSamples()]
    rest_local, faces = _surface(pxr, mesh, where, codes[0])
    xformable = UsdGeom.Xformable(prim)
    frames = np.empty((len(codes), len(rest_local), 3))
    for f, code in enumerate(codes):
        points = np.array(attr.Get(code), dtype=np.float64).reshape(-1, 3)
        if points.shape != rest_local.shape:
            raise AnimationError(f"{where}: time {code.GetValue():g} has {len(points)} points but "
                                 f"the rest has {len(rest_local)}; every sample needs the rest's "
                                 "point count and order")
        frames[f] = _apply(points, _matrix(xformable.ComputeLocalToWorldTransform(code)))
    rest = _apply(rest_local, _matrix(xformable.ComputeLocalToWorldTransform(codes[0])))
    primvar = UsdGeom.PrimvarsAPI(prim).GetPrimvar("torchfit:driven")
    if not primvar or not primvar.HasAuthoredValue():
        raise AnimationError(f"{where}: a point cache needs its driven vertices: author the "
                             "primvar primvars:torchfit:driven (bool or int per point)")
    raw = np.array(primvar.Get(), dtype=np.float64).reshape(-1)
    if raw.shape != (len(rest),):
        raise AnimationError(f"{where}: primvars:torchfit:driven has {raw.size} values for "
                             f"{len(rest)} points; give one per point")
    mask = raw != 0
    if not mask.any() or mask.all():
        raise AnimationError(f"{where}: primvars:torchfit:driven marks "
                             f"{'no' if not mask.any() else 'every'} point; drive some but not "
                             "all of the surface")
    tolerance = _length_attribute([prim], "torchfit:drivenTolerance")
    if tolerance is None:
        edges = rest[faces] - rest[np.roll(faces, 1, axis=1)]
        tolerance = float(np.linalg.norm(edges, axis=-1).mean())
    names = [f"{path.name}:{prim.GetPath()}@{c.GetValue():g}" for c in codes]
    return _animation(path, rest * scale, faces, frames * scale, scale, names,
                      driven=DrivenSurface(mask, tolerance * scale),
                      prim=str(prim.GetPath()))


def _animation(path: Path, rest: np.ndarray, faces: np.ndarray, frames: np.ndarray,
               unit: float, names: list[str], **drive: Any) -> Animation:
    import trimesh

    from ...surface import surface_warnings

    for what, points in (("rest points", rest), ("frames", frames)):
        if not np.isfinite(points).all():
            raise AnimationError(f"{path}: the {what} hold a NaN or infinite coordinate")
    surface = trimesh.Trimesh(rest, faces, process=False)
    return Animation(path, rest, faces, frames, unit, region_labels=None, frame_files=names,
                     warnings=surface_warnings(surface), **drive)


def load_usd(path: str | Path, prim: str = "") -> Animation:
    """Read one mesh prim of a USD stage as an :class:`Animation` (every length in metres)."""
    path = Path(path).expanduser()
    pxr = _pxr(path)
    if not path.is_file():
        raise AnimationError(f"{path}: no such USD file")
    stage = open_stage(path)
    scale = float(pxr.UsdGeom.GetStageMetersPerUnit(stage))
    axis = str(pxr.UsdGeom.GetStageUpAxis(stage)).upper()
    _log.info("%s: up axis %s (coordinates kept as authored), %g metres per unit", path,
              axis, scale)
    skinned, cached = _candidates(pxr, stage)
    chosen = _pick(path, prim, skinned, cached)
    usd_prim = stage.GetPrimAtPath(chosen)
    if chosen in skinned:
        animation = _skinned(pxr, path, usd_prim, *skinned[chosen], scale)
    else:
        animation = _point_cache(pxr, path, usd_prim, scale)
    return dataclasses.replace(animation, up=np.eye(3)[1 if axis == "Y" else 2])
