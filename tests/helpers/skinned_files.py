"""Small skinned files built in code, with their frames by a hand-written linear blend skinning.

A tube along ``y`` (radius 2, length 20, in centimetres: a Y-up stage with ``metersPerUnit``
0.01), quads (so the reader triangulates), three joints ``A`` (root, y = 0), ``A/B`` (y = 10,
its bind turned 10 degrees about z), ``A/B/C`` (the tip, y = 20, no weight), two influences
per vertex (``A/B`` and ``A`` blended along the tube) listed in the mesh's own joint order
``[A/B, A]`` (not the skeleton's), a geometry bind transform that turns the mesh 30 degrees
about y and moves it, the skeleton prim moved by 5 cm along y. Three authored times (1, 2, 4):
the root slides and turns about z, ``A/B`` bends about x by 0, 20 and 45 degrees.

The expected frames are computed here with column-vector 4x4 matrices and scipy rotations,
independently of UsdSkel and of the readers.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

TIMES = (1.0, 2.0, 4.0)
BENDS = (0.0, 20.0, 45.0)
METRES_PER_UNIT = 0.01
JOINTS = ["A", "A/B", "A/B/C"]
MESH_JOINTS = ["A/B", "A"]


def translate(x: float, y: float, z: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def rotate(axis: str, degrees: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler(axis, degrees, degrees=True).as_matrix()
    return m


def tube(n_around: int = 8, n_rings: int = 6, length: float = 20.0, radius: float = 2.0
         ) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(n_rings * n_around, 3)`` along y and quads ``(Q, 4)`` (an open tube)."""
    phi = 2 * np.pi * np.arange(n_around) / n_around
    y = np.linspace(0.0, length, n_rings)
    points = np.stack([np.broadcast_to(radius * np.cos(phi), (n_rings, n_around)),
                       np.broadcast_to(y[:, None], (n_rings, n_around)),
                       np.broadcast_to(radius * np.sin(phi), (n_rings, n_around))], -1)
    idx = np.arange(n_rings * n_around).reshape(n_rings, n_around)
    nxt = np.roll(idx, -1, axis=1)
    quads = np.stack([idx[:-1], idx[1:], nxt[1:], nxt[:-1]], -1).reshape(-1, 4)
    return points.reshape(-1, 3), quads


def rig_of_tube(points: np.ndarray) -> dict:
    """Bind, per-time local transforms, geometry bind, skeleton placement (column vectors)."""
    bind = [np.eye(4), translate(0, 10, 0) @ rotate("z", 10), translate(0, 20, 0)]
    parents = [-1, 0, 1]
    rest_local = [bind[j] if parents[j] < 0 else np.linalg.inv(bind[parents[j]]) @ bind[j]
                  for j in range(3)]
    local = []
    for k, bend in enumerate(BENDS):
        root = translate(0.5 * k, 0, 0) @ rotate("z", 5.0 * k)
        mid = rest_local[1] @ rotate("x", bend)
        local.append([root, mid, rest_local[2]])
    weight_b = np.clip(points[:, 1] / 20.0, 0.1, 0.9)             # on A/B; the rest on A
    return {"bind": bind, "parents": parents, "rest_local": rest_local, "local": local,
            "weights": np.stack([weight_b, 1 - weight_b], 1),     # mesh order [A/B, A]
            "geom_bind": translate(0.5, 0.0, 0.25) @ rotate("y", 30),
            "skeleton_xform": translate(0, 5, 0)}


def expected_tube(points: np.ndarray, rig: dict) -> tuple[np.ndarray, np.ndarray]:
    """Rest and frames ``(F, V, 3)`` in metres by linear blend skinning."""
    hom = np.concatenate([points, np.ones((len(points), 1))], 1)
    bound = hom @ rig["geom_bind"].T
    world = rig["skeleton_xform"]
    frames = []
    for local in rig["local"]:
        posed = [local[0]]
        for j in (1, 2):
            posed.append(posed[rig["parents"][j]] @ local[j])
        skin = [posed[j] @ np.linalg.inv(rig["bind"][j]) for j in range(3)]
        by_mesh_joint = [skin[1], skin[0]]                        # [A/B, A]
        moved = sum(rig["weights"][:, [k]] * (bound @ by_mesh_joint[k].T) for k in range(2))
        frames.append((moved @ world.T)[:, :3])
    rest = (bound @ world.T)[:, :3]
    return rest * METRES_PER_UNIT, np.stack(frames) * METRES_PER_UNIT


def _matrix(m: np.ndarray):
    from pxr import Gf

    return Gf.Matrix4d(*np.asarray(m.T, dtype=np.float64).ravel().tolist())   # row vectors


def _quat(m: np.ndarray):
    from pxr import Gf

    x, y, z, w = Rotation.from_matrix(m[:3, :3]).as_quat()
    return Gf.Quatf(float(w), float(x), float(y), float(z))


def write_tube_usd(path: Path, *, interpolation: str = "vertex", extra_mesh: bool = False,
                   weights_per_point: int | None = None) -> dict:
    """Write the skinned tube (see the module); returns ``points``, ``quads`` and ``rig``.

    ``interpolation="constant"``: every point bound to ``A/B`` alone (elementSize 1);
    ``extra_mesh``: a second skinned mesh ``/Root/Other``; ``weights_per_point``: write the
    weights of only that many points (a file whose weights do not match its points).
    """
    from pxr import Gf, Usd, UsdGeom, UsdSkel, Vt

    points, quads = tube()
    rig = rig_of_tube(points)
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, METRES_PER_UNIT)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    root = UsdSkel.Root.Define(stage, "/Root")
    skeleton = UsdSkel.Skeleton.Define(stage, "/Root/Skeleton")
    UsdGeom.Xformable(skeleton.GetPrim()).AddTranslateOp().Set(Gf.Vec3d(0, 5, 0))
    skeleton.CreateJointsAttr(JOINTS)
    skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray([_matrix(b) for b in rig["bind"]]))
    skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray([_matrix(b) for b in rig["rest_local"]]))
    animation = UsdSkel.Animation.Define(stage, "/Root/Skeleton/Animation")
    animation.CreateJointsAttr(JOINTS)
    for time, local in zip(TIMES, rig["local"]):
        animation.CreateTranslationsAttr().Set(
            Vt.Vec3fArray([Gf.Vec3f(*map(float, m[:3, 3])) for m in local]), time)
        animation.CreateRotationsAttr().Set(Vt.QuatfArray([_quat(m) for m in local]), time)
        animation.CreateScalesAttr().Set(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)] * 3), time)
    UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [animation.GetPath()])
    for name in ["Tube"] + (["Other"] if extra_mesh else []):
        mesh = UsdGeom.Mesh.Define(stage, f"/Root/{name}")
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4] * len(quads)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(quads.ravel().tolist()))
        binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
        binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
        binding.CreateJointsAttr(MESH_JOINTS)
        binding.CreateGeomBindTransformAttr(_matrix(rig["geom_bind"]))
        if interpolation == "constant":
            binding.CreateJointIndicesPrimvar(True, 1).Set(Vt.IntArray([0]))
            binding.CreateJointWeightsPrimvar(True, 1).Set(Vt.FloatArray([1.0]))
            continue
        n = len(points) if weights_per_point is None else weights_per_point
        binding.CreateJointIndicesPrimvar(False, 2).Set(Vt.IntArray([0, 1] * n))
        binding.CreateJointWeightsPrimvar(False, 2).Set(
            Vt.FloatArray(rig["weights"][:n].ravel().tolist()))
    stage.SetDefaultPrim(root.GetPrim())
    stage.GetRootLayer().Save()
    return {"points": points, "quads": quads, "rig": rig}


def write_point_cache_usd(path: Path, *, driven: bool = True, tolerance: float | None = 0.5
                          ) -> dict:
    """A Z-up stage in millimetres: a tube whose points are sampled at times 0, 1, 2 (the
    far end sways along x), the near ring driven (``primvars:torchfit:driven``, int), the
    mesh prim moved 10 mm along z; returns ``points`` and ``frames`` (stage units, before the
    move)."""
    from pxr import Gf, Sdf, Usd, UsdGeom, Vt

    points, quads = tube()
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    mesh = UsdGeom.Mesh.Define(stage, "/Cache")
    UsdGeom.Xformable(mesh.GetPrim()).AddTranslateOp().Set(Gf.Vec3d(0, 0, 10))
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
    frames = []
    for t in range(3):
        moved = points.copy()
        moved[:, 0] += 0.1 * t * (points[:, 1] / 20.0) ** 2
        frames.append(moved.astype(np.float32).astype(np.float64))
        mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(moved.astype(np.float32)), float(t))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4] * len(quads)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(quads.ravel().tolist()))
    if driven:
        UsdGeom.PrimvarsAPI(mesh.GetPrim()).CreatePrimvar(
            "torchfit:driven", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex).Set(
            Vt.IntArray((points[:, 1] == 0).astype(int).tolist()))
    if tolerance is not None:
        mesh.GetPrim().CreateAttribute("torchfit:drivenTolerance",
                                       Sdf.ValueTypeNames.Double).Set(tolerance)
    stage.GetRootLayer().Save()
    return {"points": points, "frames": np.stack(frames)}


# -- glTF ---------------------------------------------------------------------------------
GLTF_KEYS = {"A": (0.0, 0.5, 1.0), "B": (0.0, 1.0)}


def _trs(t=(0, 0, 0), q=(0, 0, 0, 1), s=(1, 1, 1)) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat(q).as_matrix() * np.asarray(s)
    m[:3, 3] = t
    return m


def gltf_tube(*, cubic: bool = False, sparse: bool = False, draco: bool = False,
              skinned_nodes: int = 1, short_weights: bool = False, byte_weights: bool = False):
    """A glTF (pygltflib object) of a metre-scale tube along y and the data to check it.

    Nodes (in this order): ``world`` (a root moved by (0, 1, 0) and scaled by 2, parent of
    the joints and the mesh), the joints ``C``, ``B``, ``A`` (so the skin's joint list
    ``[A, B, C]`` is not the node order), the skinned node ``tube`` moved by (100, 0, 0)
    (which the specification says to ignore); ``byte_weights``: the weights as normalised
    unsigned bytes (``data["weight_b"]`` then the quantised share of ``B``). ``B``'s bind is
    turned 10 degrees about z (inverse bind matrices column-major). Two influences (``B`` and ``A``) per vertex.
    Animation: ``A`` translates (keys 0, 0.5, 1 s), ``B`` turns about x from 0 to 60 degrees
    (keys 0, 1 s: slerp).
    """
    import pygltflib as g

    along, quads = tube(length=0.2, radius=0.02)
    triangles = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    world = _trs(t=(0, 1, 0), s=(2, 2, 2))
    # the mesh stored where the joints bind (the world's placement of the tube): the
    # joints inside the flesh they move, as a DCC exports them
    points = along * 2.0 + np.array([0.0, 1.0, 0.0])
    rest_local = {"A": _trs(), "B": _trs(t=(0, 0.1, 0), q=Rotation.from_euler(
        "z", 10, degrees=True).as_quat()), "C": _trs(t=(0, 0.1, 0))}
    bind = {"A": world @ rest_local["A"]}
    bind["B"] = bind["A"] @ rest_local["B"]
    bind["C"] = bind["B"] @ rest_local["C"]
    order = ["A", "B", "C"]
    weight_b = np.clip(along[:, 1] / 0.2, 0.1, 0.9)
    blob = bytearray()
    views, accessors = [], []

    def add(array, kind, component, count=None):
        data = np.ascontiguousarray(array)
        while len(blob) % 4:
            blob.append(0)
        views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=data.nbytes))
        blob.extend(data.tobytes())
        accessors.append(g.Accessor(bufferView=len(views) - 1, componentType=component,
                                    count=count or len(data), type=kind))
        return len(accessors) - 1

    n_weights = len(points) - 5 if short_weights else len(points)
    joints0 = np.zeros((len(points), 4), np.uint8)
    joints0[:, 0], joints0[:, 1] = 1, 0                            # skin slots: B, A
    weights0 = np.zeros((len(points), 4), np.float32)
    weights0[:, 0], weights0[:, 1] = weight_b, 1 - weight_b
    if byte_weights:
        weights0 = np.round(weights0 * 255).astype(np.uint8)
        weight_b = weights0[:, 0] / weights0[:, :2].sum(1, dtype=np.float64)
    attributes = g.Attributes(POSITION=add(points.astype(np.float32), "VEC3", g.FLOAT),
                              JOINTS_0=add(joints0, "VEC4", g.UNSIGNED_BYTE),
                              WEIGHTS_0=add(weights0[:n_weights], "VEC4",
                                            g.UNSIGNED_BYTE if byte_weights else g.FLOAT))
    if byte_weights:
        accessors[attributes.WEIGHTS_0].normalized = True
    indices = add(triangles.astype(np.uint16).ravel(), "SCALAR", g.UNSIGNED_SHORT)
    inverse = np.stack([np.linalg.inv(bind[j]) for j in order]).astype(np.float32)
    ibm = add(inverse.transpose(0, 2, 1).reshape(3, 16), "MAT4", g.FLOAT)   # column-major
    a_keys, b_keys = (np.array(GLTF_KEYS[k], np.float32) for k in "AB")
    a_values = np.array([[0, 0, 0], [0.05, 0, 0], [0.05, 0.02, 0]], np.float32)
    b_values = np.stack([Rotation.from_euler("z", 10, degrees=True).as_quat(),
                         (Rotation.from_euler("z", 10, degrees=True)
                          * Rotation.from_euler("x", 60, degrees=True)).as_quat()]
                        ).astype(np.float32)
    samplers = [g.AnimationSampler(input=add(a_keys, "SCALAR", g.FLOAT),
                                   output=add(a_values, "VEC3", g.FLOAT),
                                   interpolation="CUBICSPLINE" if cubic else "LINEAR"),
                g.AnimationSampler(input=add(b_keys, "SCALAR", g.FLOAT),
                                   output=add(b_values, "VEC4", g.FLOAT))]
    # node indices: 0 world, 1 C, 2 B, 3 A, 4.. tube(s)
    node_of = {"C": 1, "B": 2, "A": 3}
    nodes = [g.Node(name="world", translation=[0, 1, 0], scale=[2, 2, 2],
                    children=[3] + list(range(4, 4 + skinned_nodes))),
             g.Node(name="C", translation=[0, 0.1, 0]),
             g.Node(name="B", translation=[0, 0.1, 0], rotation=b_values[0].tolist(),
                    children=[1]),
             g.Node(name="A", children=[2])]
    nodes += [g.Node(name=f"tube{k}" if k else "tube", mesh=0, skin=0,
                     translation=[100, 0, 0]) for k in range(skinned_nodes)]
    channels = [g.AnimationChannel(sampler=s, target=g.AnimationChannelTarget(node=n, path=p))
                for s, n, p in ((0, 3, "translation"), (1, 2, "rotation"))]
    gltf = g.GLTF2(scene=0, scenes=[g.Scene(nodes=[0])], nodes=nodes,
                   meshes=[g.Mesh(primitives=[g.Primitive(attributes=attributes,
                                                          indices=indices)])],
                   skins=[g.Skin(joints=[node_of[j] for j in order], inverseBindMatrices=ibm)],
                   accessors=accessors, bufferViews=views, buffers=[g.Buffer(byteLength=0)],
                   animations=[g.Animation(samplers=samplers, channels=channels)])
    if sparse:
        accessors[attributes.POSITION].sparse = g.Sparse(
            count=1, indices=g.AccessorSparseIndices(bufferView=0, componentType=g.UNSIGNED_SHORT),
            values=g.AccessorSparseValues(bufferView=0))
    if draco:
        gltf.extensionsUsed = gltf.extensionsRequired = ["KHR_draco_mesh_compression"]
    gltf.buffers[0].byteLength = len(blob)
    gltf.set_binary_blob(bytes(blob))
    data = {"points": points, "triangles": triangles, "world": world, "bind": bind,
            "rest_local": rest_local, "order": order, "weight_b": weight_b,
            "a": (a_keys, a_values), "b": (b_keys, b_values)}
    return gltf, data


def expected_gltf_frames(data: dict, times: np.ndarray) -> np.ndarray:
    """Frames ``(F, V, 3)`` of :func:`gltf_tube` at ``times`` (linear keys, slerp), by hand."""
    from scipy.spatial.transform import Slerp

    a_keys, a_values = data["a"]
    b_keys, b_values = data["b"]
    hom = np.concatenate([data["points"], np.ones((len(data["points"]), 1))], 1)
    out = []
    for t in times:
        a = _trs(t=[np.interp(t, a_keys, a_values[:, i]) for i in range(3)])
        b_rotation = Slerp(b_keys, Rotation.from_quat(b_values))(np.clip(t, 0, 1)).as_quat()
        b = _trs(t=(0, 0.1, 0), q=b_rotation)
        posed = {"A": data["world"] @ a}
        posed["B"] = posed["A"] @ b
        skin = {j: posed[j] @ np.linalg.inv(data["bind"][j]) for j in ("A", "B")}
        w = data["weight_b"][:, None]
        out.append((w * (hom @ skin["B"].T) + (1 - w) * (hom @ skin["A"].T))[:, :3])
    return np.stack(out)
