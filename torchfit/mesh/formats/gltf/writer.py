"""Writing glTF 2.0 (the extra ``gltf``): a rigged animation as a skin with an animation.

:func:`write_skinned_gltf` writes the animation format's rig as a ``.glb`` (or a ``.gltf``
with its buffer embedded) that :func:`.reader.load_gltf` poses back to the same frames:
one joint node per joint of :func:`..joints.bone_joints` (rest pose = bind pose, inverse
bind matrices the inverse translations, stored column-major), the mesh with ``JOINTS_0`` /
``WEIGHTS_0`` (the four largest weights per vertex: more are refused) and one morph target
per corrective shape, one animation: each joint's translation and rotation (``LINEAR``) at
times ``f / fps``, and the morph weights. ``attach_radius`` goes in the skin's
``extras`` (``torchfit:attachRadius``). Bone transforms must be rigid. Metres; the axes as
given (glTF says Y up, and the reader takes +Y as the pictures' up: a body written along z
is drawn lying, as a DCC tool shows it; turn it first to have it stand).
"""
from __future__ import annotations

import base64
from pathlib import Path

import numpy as np

from ..joints import bone_joints
from ...rig import Skeleton


def write_skinned_gltf(path: str | Path, rest_vertices: np.ndarray, faces: np.ndarray,
                       skeleton: Skeleton, shapes: dict[str, np.ndarray] | None = None,
                       shape_weights: np.ndarray | None = None, fps: float = 24.0) -> Path:
    """Write a skinned mesh and its animation to ``path`` (``.glb`` or ``.gltf``).

    Arguments as :func:`..usd.writer.write_skinned_usd`.
    """
    import pygltflib as g
    from scipy.spatial.transform import Rotation

    if skeleton.weights is None:
        raise ValueError("write_skinned_gltf needs the skeleton's per-vertex weights")
    shapes = shapes or {}
    paths, parents, positions, mover = bone_joints(skeleton)
    F, J, V = skeleton.transforms.shape[0], len(paths), len(rest_vertices)
    weights = np.zeros((V, J))
    weights[:, :skeleton.n_bones] = skeleton.weights
    if ((weights > 0).sum(axis=1) > 4).any():
        raise ValueError("write_skinned_gltf writes at most four influences per vertex")
    order = np.argsort(-weights, axis=1, kind="stable")[:, :4]
    slots = np.pad(order, ((0, 0), (0, 4 - order.shape[1])))
    slot_weights = np.pad(np.take_along_axis(weights, order, 1), ((0, 0), (0, 4 - order.shape[1])))
    # joint world transforms (column vectors): bind (translation), then the bone's motion
    motion = np.tile(np.eye(4), (F, J, 1, 1))
    motion[..., :3, :] = skeleton.transforms[:, mover]
    bind = np.tile(np.eye(4), (J, 1, 1))
    bind[:, :3, 3] = positions
    world = motion @ bind[None]
    local = world.copy()
    child = parents >= 0
    local[:, child] = np.linalg.inv(world[:, parents[child]]) @ world[:, child]
    rest_local = bind.copy()
    rest_local[child, :3, 3] -= positions[parents[child]]
    blob = bytearray()
    views: list[g.BufferView] = []
    accessors: list[g.Accessor] = []

    def add(array: np.ndarray, kind: str, component: int, target: int | None = None,
            bounds: bool = False) -> int:
        data = np.ascontiguousarray(array)
        while len(blob) % 4:
            blob.append(0)
        views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=data.nbytes,
                                  target=target))
        blob.extend(data.tobytes())
        flat = data.reshape(len(data), -1)
        accessors.append(g.Accessor(
            bufferView=len(views) - 1, componentType=component, count=len(data), type=kind,
            min=flat.min(0).tolist() if bounds else None,
            max=flat.max(0).tolist() if bounds else None))
        return len(accessors) - 1

    attributes = g.Attributes(
        POSITION=add(np.asarray(rest_vertices, np.float32), "VEC3", g.FLOAT, g.ARRAY_BUFFER,
                     True),
        JOINTS_0=add(slots.astype(np.uint16), "VEC4", g.UNSIGNED_SHORT, g.ARRAY_BUFFER),
        WEIGHTS_0=add(slot_weights.astype(np.float32), "VEC4", g.FLOAT, g.ARRAY_BUFFER))
    targets = [g.Attributes(POSITION=add(np.asarray(offsets, np.float32), "VEC3", g.FLOAT,
                                         g.ARRAY_BUFFER, True)) for offsets in shapes.values()]
    indices = add(np.asarray(faces, np.uint32).reshape(-1), "SCALAR", g.UNSIGNED_INT,
                  g.ELEMENT_ARRAY_BUFFER)
    primitive = g.Primitive(attributes=attributes, indices=indices, mode=g.TRIANGLES,
                            targets=targets or None)
    mesh = g.Mesh(name="body", primitives=[primitive],
                  weights=[0.0] * len(shapes) if shapes else None)
    inverse_bind = np.linalg.inv(bind).transpose(0, 2, 1).astype(np.float32)   # column-major
    nodes = [g.Node(name=p.rsplit("/", 1)[-1], translation=rest_local[j, :3, 3].tolist(),
                    children=[int(c) for c in np.flatnonzero(parents == j)] or None)
             for j, p in enumerate(paths)]
    nodes.append(g.Node(name="body", mesh=0, skin=0))
    skin = g.Skin(name="rig", joints=list(range(J)),
                  inverseBindMatrices=add(inverse_bind, "MAT4", g.FLOAT),
                  extras={"torchfit:attachRadius": float(skeleton.attach_radius)})
    times = add((np.arange(F) / fps).astype(np.float32), "SCALAR", g.FLOAT, None, True)
    samplers, channels = [], []
    quaternions = Rotation.from_matrix(local[..., :3, :3].reshape(-1, 3, 3)).as_quat()
    quaternions = quaternions.reshape(F, J, 4)
    for j in range(J):
        for kind, values, width in (("translation", local[:, j, :3, 3], "VEC3"),
                                    ("rotation", quaternions[:, j], "VEC4")):
            samplers.append(g.AnimationSampler(
                input=times, output=add(values.astype(np.float32), width, g.FLOAT),
                interpolation="LINEAR"))
            channels.append(g.AnimationChannel(
                sampler=len(samplers) - 1, target=g.AnimationChannelTarget(node=j, path=kind)))
    if shapes:
        samplers.append(g.AnimationSampler(
            input=times, output=add(np.asarray(shape_weights, np.float32).reshape(-1), "SCALAR",
                                    g.FLOAT), interpolation="LINEAR"))
        channels.append(g.AnimationChannel(
            sampler=len(samplers) - 1, target=g.AnimationChannelTarget(node=J, path="weights")))
    roots = [int(j) for j in np.flatnonzero(parents < 0)] + [J]
    gltf = g.GLTF2(scene=0, scenes=[g.Scene(nodes=roots)], nodes=nodes, meshes=[mesh],
                   skins=[skin], accessors=accessors, bufferViews=views,
                   buffers=[g.Buffer(byteLength=len(blob))],
                   animations=[g.Animation(name="animation", samplers=samplers,
                                           channels=channels)])
    path = Path(path)
    if path.suffix.lower() == ".glb":
        gltf.set_binary_blob(bytes(blob))
        gltf.save_binary(str(path))
    else:
        gltf.buffers[0].uri = ("data:application/octet-stream;base64,"
                               + base64.b64encode(bytes(blob)).decode("ascii"))
        gltf.save_json(str(path))
    return path
