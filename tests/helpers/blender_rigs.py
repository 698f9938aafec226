"""Rigs built in Blender (``bpy``, the extra ``blender``), exported by Blender's own USD and
glTF exporters, and torchfit's USD outputs imported back into Blender.

Blender runs in a subprocess (:func:`run_blender`): its module bundles its own USD library
(which must not meet usd-core's ``pxr`` in one process), its scene is process-global state,
and ``bpy`` 4.5 is built against NumPy 1.x (a NumPy-2 warning on import, harmless to the
operators used here). The same file is the subprocess's script: ``python blender_rigs.py
job.json`` runs one job and writes ``result.json`` beside the job.

Rigs (Blender's Z-up world, metres; bones along +x):

``limb``
    a closed capped tube of radius ``RADIUS`` and length ``LENGTH`` along x, three equal
    bones ``upper -> lower -> end`` (the end bone carries a third of the limb), heat weights
    (``parent_set(type='ARMATURE_AUTO')``); frames 1..F: the end bone alone bends about z
    by ``0 .. bend`` degrees (``twist``: the lower bone also twists about its axis).
``hand``
    a palm box with two finger tubes (one closed surface, a boolean union), a palm bone and
    two fingers of two bones each branching from the palm's tail; frames: both fingers curl.

``seams``: a cylindrical UV map (a seam along the tube) and sharp cap rims: the glTF exporter
splits those vertices (the file has more vertices than the surface), and ``split=True``
splits them in the mesh itself (an Edge Split), so the USD has them split too.

Exports: ``usd`` (``bpy.ops.wm.usd_export``; ``meters_per_unit`` converts the scene's units,
Z up as Blender writes it), ``glb`` (``bpy.ops.export_scene.gltf``, Y up as glTF says).

``reimport`` jobs import a USD layer into an empty scene (``bpy.ops.wm.usd_import``) and
write, for every mesh, its evaluated world-space points at each frame and every mesh
attribute (name, domain, values) to an ``.npz``; Blender 4.5 imports no
``UsdGeom.TetMesh``, so a TetMesh's material is read with the USD library Blender ships
(its ``pxr``, put first on the subprocess's path).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

LENGTH = 0.5
RADIUS = 0.05
N_AROUND = 16
N_RINGS = 31
BONES = ("upper", "lower", "end")


# -- the test side: run a job in a subprocess -----------------------------------------------
def blender_available() -> bool:
    """Whether this interpreter has ``bpy`` (looked up without importing it)."""
    import importlib.util

    return importlib.util.find_spec("bpy") is not None


def run_blender(job: dict, folder: Path, timeout: float = 600) -> dict:
    """Run ``job`` (a dict with ``kind``) in a Blender subprocess, files in ``folder``;
    returns its ``result.json`` (with ``seconds``: the subprocess's wall time)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    job_file = folder / f"job_{job['kind']}_{len(list(folder.glob('job_*.json')))}.json"
    job_file.write_text(json.dumps(job))
    result_file = job_file.with_suffix(".result.json")
    start = time.perf_counter()
    import importlib.util

    # Blender's own Python modules (its pxr) before the environment's usd-core
    bundled = Path(importlib.util.find_spec("bpy").origin).parent / "4.5" / "python" / "lib" / \
        "python3.11" / "site-packages"
    env = {**os.environ, "PYTHONWARNINGS": "ignore",
           "PYTHONPATH": os.pathsep.join([str(bundled), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, __file__, str(job_file)], capture_output=True,
                          text=True, timeout=timeout, env=env)
    seconds = time.perf_counter() - start
    if proc.returncode != 0 or not result_file.is_file():
        raise RuntimeError(f"Blender job {job['kind']} failed ({proc.returncode}):\n"
                           f"{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    result = json.loads(result_file.read_text())
    result["seconds"] = seconds
    return result


# -- the Blender side -------------------------------------------------------------------------
def _tube(x0: float, x1: float, radius: float, n_around: int, n_rings: int,
          centre=(0.0, 0.0)) -> tuple[list, list]:
    """A capped tube along x: vertices and faces (quads on the side, triangle fans on the caps,
    outward winding)."""
    import math

    verts, faces = [], []
    for r in range(n_rings):
        x = x0 + (x1 - x0) * r / (n_rings - 1)
        for k in range(n_around):
            phi = 2 * math.pi * k / n_around
            verts.append((x, centre[0] + radius * math.cos(phi),
                          centre[1] + radius * math.sin(phi)))
    for r in range(n_rings - 1):
        for k in range(n_around):
            a, b = r * n_around + k, r * n_around + (k + 1) % n_around
            faces.append((a, b, b + n_around, a + n_around))
    start = len(verts)
    verts.append((x0, centre[0], centre[1]))
    verts.append((x1, centre[0], centre[1]))
    last = (n_rings - 1) * n_around
    for k in range(n_around):
        k1 = (k + 1) % n_around
        faces.append((start, k1, k))
        faces.append((start + 1, last + k, last + k1))
    return verts, faces


def _clear(bpy) -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)


def _mesh_object(bpy, name: str, verts: list, faces: list):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(verts, [], faces)
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _add_seams(bpy, obj, split: bool) -> None:
    """A cylindrical UV map (seam at phi = 0) and sharp cap rims; ``split``: split the mesh
    there (an Edge Split applied), so every exporter writes the seam's vertices twice."""
    import bmesh
    import math

    mesh = obj.data
    bm = bmesh.new()
    bm.from_mesh(mesh)
    uv = bm.loops.layers.uv.new("UVMap")
    xs = [v.co.x for v in bm.verts]
    x0, x1 = min(xs), max(xs)
    for face in bm.faces:
        side = len(face.verts) == 4
        us = [(math.atan2(v.co.z, v.co.y) / (2 * math.pi)) % 1.0 for v in face.verts]
        if side and max(us) - min(us) > 0.5:          # the face across the seam
            us = [u if u > 0.5 else u + 1.0 for u in us]
        for loop, u in zip(face.loops, us):
            co = loop.vert.co
            loop[uv].uv = (u, (co.x - x0) / (x1 - x0)) if side else \
                (0.5 + co.y * 5, 0.5 + co.z * 5)
    sharp = []
    for edge in bm.edges:
        kinds = {len(f.verts) == 4 for f in edge.link_faces}
        if len(kinds) == 2:                            # a cap rim: side quad meets cap fan
            edge.smooth = False
            sharp.append(edge)
        else:
            edge.smooth = True
    for face in bm.faces:
        face.smooth = True
    if split:
        seam = [e for e in bm.edges if all(
            abs((math.atan2(v.co.z, v.co.y)) % (2 * math.pi)) < 1e-6 for v in e.verts)
            and len(e.link_faces) == 2]
        bmesh.ops.split_edges(bm, edges=sharp + seam)
    bm.to_mesh(mesh)
    bm.free()
    mesh.update()


def _armature(bpy, name: str, bones: list[tuple[str, tuple, tuple, str | None]]):
    """An armature object with ``bones`` (name, head, tail, parent) in edit mode."""
    data = bpy.data.armatures.new(name)
    arm = bpy.data.objects.new(name, data)
    bpy.context.scene.collection.objects.link(arm)
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")
    edit = {}
    for bone_name, head, tail, parent in bones:
        bone = data.edit_bones.new(bone_name)
        bone.head, bone.tail = head, tail
        bone.roll = 0.0
        if parent is not None:
            bone.parent = edit[parent]
            bone.use_connect = tuple(edit[parent].tail) == tuple(head)
        edit[bone_name] = bone
    bpy.ops.object.mode_set(mode="OBJECT")
    return arm


def _heat_weights(bpy, mesh_obj, arm) -> None:
    bpy.ops.object.select_all(action="DESELECT")
    mesh_obj.select_set(True)
    arm.select_set(True)
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.parent_set(type="ARMATURE_AUTO")


def _keyframes(bpy, arm, poses: list[dict[str, tuple]]) -> None:
    """Frame ``1 + i`` of pose ``i``: bone name -> (axis, degrees) in the bone's own frame
    (``y`` along the bone)."""
    import math

    from mathutils import Quaternion

    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, len(poses)
    for frame, pose in enumerate(poses, start=1):
        for bone in arm.pose.bones:
            bone.rotation_mode = "QUATERNION"
            q = Quaternion((1.0, 0.0, 0.0, 0.0))
            for axis, degrees in pose.get(bone.name, []):
                q = q @ Quaternion({"x": (1, 0, 0), "y": (0, 1, 0), "z": (0, 0, 1)}[axis],
                                   math.radians(degrees))
            bone.rotation_quaternion = q
            bone.keyframe_insert("rotation_quaternion", frame=frame)


def _limb(bpy, job: dict):
    verts, faces = _tube(0.0, LENGTH, RADIUS, N_AROUND, N_RINGS)
    body = _mesh_object(bpy, "Limb", verts, faces)
    if job.get("seams"):
        _add_seams(bpy, body, split=bool(job.get("split")))
    third = LENGTH / 3
    arm = _armature(bpy, "Rig", [("upper", (0, 0, 0), (third, 0, 0), None),
                                 ("lower", (third, 0, 0), (2 * third, 0, 0), "upper"),
                                 ("end", (2 * third, 0, 0), (LENGTH, 0, 0), "lower")])
    _heat_weights(bpy, body, arm)
    n = int(job.get("frames", 5))
    bend = float(job.get("bend", 60.0))
    twist = float(job.get("twist", 0.0))
    poses = [{"end": [("z", bend * i / (n - 1))],
              "lower": [("y", twist * i / (n - 1))] if twist else []} for i in range(n)]
    _keyframes(bpy, arm, poses)
    return body, arm


def _hand(bpy, job: dict):
    palm_len, finger_len, width = 0.12, 0.12, 0.05
    gap = 0.028
    verts, faces = [], []
    bpy.ops.mesh.primitive_cube_add(size=1.0)
    palm = bpy.context.active_object
    palm.scale = (palm_len, 2 * width + 0.02, 0.04)
    palm.location = (palm_len / 2, 0, 0)
    bpy.ops.object.transform_apply(location=True, scale=True)
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.mesh.subdivide(number_cuts=5)
    bpy.ops.object.mode_set(mode="OBJECT")
    fingers = []
    for side, y in (("a", -gap), ("b", gap)):
        v, f = _tube(palm_len - 0.02, palm_len + finger_len, 0.016, 12, 17, centre=(y, 0.0))
        fingers.append(_mesh_object(bpy, f"finger_{side}", v, f))
    for finger in fingers:
        mod = palm.modifiers.new("union", "BOOLEAN")
        mod.operation, mod.solver, mod.object = "UNION", "EXACT", finger
        bpy.context.view_layer.objects.active = palm
        bpy.ops.object.modifier_apply(modifier=mod.name)
        bpy.data.objects.remove(finger)
    palm.name = "Hand"
    half = finger_len / 2
    bones = [("palm", (0, 0, 0), (palm_len, 0, 0), None)]
    for side, y in (("a", -gap), ("b", gap)):
        bones += [(f"{side}1", (palm_len, y, 0), (palm_len + half, y, 0), "palm"),
                  (f"{side}2", (palm_len + half, y, 0), (palm_len + finger_len, y, 0),
                   f"{side}1")]
    arm = _armature(bpy, "Rig", bones)
    _heat_weights(bpy, palm, arm)
    n = int(job.get("frames", 5))
    curl = float(job.get("bend", 50.0))
    poses = [{"a1": [("z", 0.5 * curl * i / (n - 1))], "a2": [("z", curl * i / (n - 1))],
              "b1": [("x", 0.6 * curl * i / (n - 1))], "b2": [("x", curl * i / (n - 1))]}
             for i in range(n)]
    _keyframes(bpy, arm, poses)
    return palm, arm


def _export(bpy, job: dict, folder: Path) -> dict:
    out = {}
    if job.get("usd"):
        path = folder / job["usd"]
        mpu = float(job.get("meters_per_unit", 1.0))
        units = {1.0: "METERS", 0.01: "CENTIMETERS", 0.001: "MILLIMETERS"}.get(mpu, "CUSTOM")
        bpy.ops.wm.usd_export(filepath=str(path), export_animation=True, export_armatures=True,
                              only_deform_bones=True, export_materials=False,
                              export_shapekeys=False, convert_scene_units=units,
                              meters_per_unit=mpu, selected_objects_only=False)
        out["usd"] = str(path)
    if job.get("glb"):
        path = folder / job["glb"]
        bpy.ops.export_scene.gltf(filepath=str(path), export_format="GLB", export_yup=True,
                                  export_skins=True, export_animations=True,
                                  export_materials="NONE", export_force_sampling=True)
        out["glb"] = str(path)
    return out


def _skinned_points(bpy, body, n_frames: int):
    """World-space evaluated points of ``body`` at frames 1..n (Blender's own skinning)."""
    scene = bpy.context.scene
    frames = []
    for frame in range(1, n_frames + 1):
        scene.frame_set(frame)
        evaluated = body.evaluated_get(bpy.context.evaluated_depsgraph_get())
        mesh = evaluated.to_mesh()
        frames.append([list(evaluated.matrix_world @ v.co) for v in mesh.vertices])
        evaluated.to_mesh_clear()
    return frames


def _reimport(bpy, job: dict, folder: Path) -> dict:
    import numpy as np

    _clear(bpy)
    bpy.ops.wm.usd_import(filepath=job["path"], import_skeletons=True, read_mesh_attributes=True,
                          attr_import_mode="ALL", apply_unit_conversion_scale=True)
    scene = bpy.context.scene
    frames = job.get("frames") or [scene.frame_start]
    arrays, meshes = {}, []
    for obj in [o for o in scene.objects if o.type == "MESH"]:
        meshes.append({"name": obj.name, "vertices": len(obj.data.vertices),
                       "attributes": [(a.name, a.domain, a.data_type)
                                      for a in obj.data.attributes],
                       "modifiers": [m.type for m in obj.modifiers],
                       "prim": obj.data.get("prim_path", "")})
        for attribute in obj.data.attributes:
            if attribute.data_type in ("FLOAT", "INT") and not attribute.name.startswith("."):
                values = np.zeros(len(attribute.data))
                attribute.data.foreach_get("value", values)
                arrays[f"{obj.name}|attr|{attribute.name}"] = values
        points = []
        for frame in frames:
            scene.frame_set(int(frame))
            evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
            mesh = evaluated.to_mesh()
            co = np.zeros(3 * len(mesh.vertices))
            mesh.vertices.foreach_get("co", co)
            m = np.array(evaluated.matrix_world)
            points.append(co.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3])
            evaluated.to_mesh_clear()
        arrays[f"{obj.name}|points"] = np.stack(points)
    npz = folder / (Path(job["path"]).stem + "_blender.npz")
    np.savez(npz, **arrays)
    return {"meshes": meshes, "npz": str(npz), "tet_meshes": _tet_materials(job["path"])}


def _tet_materials(path: str) -> list[dict]:
    """Blender 4.5's importer skips ``UsdGeom.TetMesh``: its material is read with Blender's
    own USD library (the ``pxr`` Blender ships) instead: per-tetrahedron primvars and the
    physics material bound to each TetMesh."""
    from pxr import Usd, UsdGeom, UsdShade

    out = []
    stage = Usd.Stage.Open(path)
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.TetMesh):
            continue
        primvars = UsdGeom.PrimvarsAPI(prim)
        entry = {"prim": str(prim.GetPath()), "usd": Usd.__file__,
                 "tets": len(UsdGeom.TetMesh(prim).GetTetVertexIndicesAttr().Get())}
        for name in ("youngsModulus", "poissonsRatio", "density"):
            primvar = primvars.GetPrimvar(name)
            entry[name] = [float(v) for v in primvar.Get()] if primvar else None
        material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial("physics")
        if material:
            entry["material"] = {
                "path": str(material.GetPath()),
                # the draft's schemas are codeless (not registered here): the authored list
                "schemas": [str(t) for t in material.GetPrim().GetMetadata(
                    "apiSchemas").GetAddedOrExplicitItems()],
                **{a.GetName(): a.Get() for a in material.GetPrim().GetAttributes()
                   if a.GetName().startswith("omniphysics:")},
                "customData": _flat(material.GetPrim().GetCustomData())}
        out.append(entry)
    return out


def _flat(data: dict, prefix: str = "") -> dict:
    """``customData`` with nested keys joined by ``:`` (as USD nests ``a:b``)."""
    out = {}
    for key, value in data.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}:"))
        elif isinstance(value, (str, float, int)):
            out[f"{prefix}{key}"] = value
    return out


def _main(job_file: str) -> None:
    import bpy

    job_path = Path(job_file)
    job = json.loads(job_path.read_text())
    folder = job_path.parent
    if job["kind"] == "reimport":
        result = _reimport(bpy, job, folder)
    else:
        _clear(bpy)
        body, arm = {"limb": _limb, "hand": _hand}[job["kind"]](bpy, job)
        result = _export(bpy, job, folder)
        result["vertices"] = len(body.data.vertices)
        result["faces"] = len(body.data.polygons)
        if job.get("skinned_points"):
            import numpy as np

            npz = folder / f"{job['kind']}_blender_frames.npz"
            np.savez(npz, frames=np.asarray(_skinned_points(bpy, body, int(
                job.get("frames", 5)))))
            result["skinned"] = str(npz)
        result["groups"] = [g.name for g in body.vertex_groups]
    job_path.with_suffix(".result.json").write_text(json.dumps(result))


if __name__ == "__main__":
    _main(sys.argv[1])
