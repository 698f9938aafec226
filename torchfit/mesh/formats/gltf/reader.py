"""A glTF 2.0 skin as an animation (``.glb``/``.gltf``, the extra ``gltf``: pygltflib).

:func:`load_gltf` reads one skinned node (a node with a ``mesh`` and a ``skin``) into the same
:class:`~torchfit.mesh.Animation` as the folder format:

- rest: the mesh's ``POSITION`` (every triangle primitive, concatenated in order), faces from
  its indices; the skinned node's own transform is ignored, as the specification says (the
  skin's joints place the mesh; trimesh applies it and drops the skin, so it is not used);
- joints: the skin's joint nodes, their parents (the nearest ancestor that is a joint), bind
  positions (the translation of the inverse of each inverse bind matrix: column-major in the
  file); weights ``JOINTS_n``/``WEIGHTS_n`` (every set, float or normalised integers);
- frames: the animation's channels (the first animation) sampled at every keyframe time of
  its samplers (the union, in order), or at ``fps`` over their range; ``LINEAR``
  interpolation (slerp for rotations) or ``STEP``. Morph targets (``POSITION`` offsets,
  weights from the mesh, the node or a ``weights`` channel) are added before skinning; each
  joint's matrix is its global transform times its inverse bind matrix, and a vertex moves
  by ``sum_j w_j M_j [x, 1]``;
- bones: the joints' segments (:func:`..joints.skeleton_from_joints`: an end joint's bone
  reaches over the vertices its weights dominate, or ``extras: {"torchfit:boneLength":
  metres}`` on its joint node); ``attach_radius`` from ``extras: {"torchfit:attachRadius":
  metres}`` on the skin or the node, else the default there; the skeleton says which was
  authored and which derived, and a degenerate joint tree is refused there.

Units: metres (glTF's); the coordinates are kept, and the animation's ``up`` is +Y (the
glTF specification's up axis; the pictures stand the body on it). Refused with one line (:class:`~torchfit.mesh.AnimationError`): ``CUBICSPLINE``
samplers, sparse accessors, Draco or meshopt compression (any required extension), primitives
other than triangles, no skinned node, several without ``problem.prim``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any
from urllib.parse import unquote

import numpy as np

from ...animation import Animation, AnimationError
from ..joints import skeleton_from_joints

_COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32,
               5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
_COMPRESSION = ("KHR_draco_mesh_compression", "EXT_meshopt_compression",
                "KHR_meshopt_compression")


class _File:
    """The parsed file and its accessors as numpy arrays."""

    def __init__(self, path: Path):
        try:
            from pygltflib import GLTF2
        except ImportError as err:
            raise AnimationError(f"{path}: reading glTF needs the optional extra 'gltf': pip "
                                 f"install 'torchfit[gltf]' (pygltflib) ({err})") from err
        if not path.is_file():
            raise AnimationError(f"{path}: no such glTF file")
        try:
            self.gltf = GLTF2().load(str(path))
        except Exception as err:  # noqa: BLE001 - pygltflib raises many kinds
            raise AnimationError(f"{path}: cannot read it as glTF ({err})") from err
        if self.gltf is None:
            raise AnimationError(f"{path}: cannot read it as glTF")
        self.path = path
        self._buffers: dict[int, bytes] = {}
        used = list(self.gltf.extensionsRequired or []) + [
            e for e in (self.gltf.extensionsUsed or []) if e in _COMPRESSION]
        if used:
            what = "compression" if used[0] in _COMPRESSION else "extension"
            raise AnimationError(f"{path}: uses {used[0]} ({what}), which torchfit does not read; "
                                 "export without compression or extensions")

    def buffer(self, index: int) -> bytes:
        if index not in self._buffers:
            uri = self.gltf.buffers[index].uri
            if uri and not uri.startswith("data:"):
                data = self._external(index, uri)
            else:
                data = self.gltf.get_data_from_buffer_uri(uri)
            if data is None:
                raise AnimationError(f"{self.path}: buffer {index} has no data")
            self._buffers[index] = data
        return self._buffers[index]

    def _external(self, index: int, uri: str) -> bytes:
        """The bytes of buffer ``index`` kept in a file beside the ``.gltf`` (``uri``
        relative to it, percent-encoded or not); a missing or unreadable file is one line
        naming the buffer, its uri and the path tried."""
        gltf = self.path.absolute()
        tried = gltf.parent / unquote(uri)
        if not tried.exists() and (gltf.parent / uri).exists():
            tried = gltf.parent / uri           # a file name that holds a literal '%'
        try:
            return tried.read_bytes()
        except FileNotFoundError:
            why = "which is not there"
        except OSError as err:
            why = f"which cannot be read ({err.strerror or err})"
        raise AnimationError(f"{gltf}: its buffer {index} names {uri}, {why} ({tried}); keep "
                             f"the .bin beside the .gltf or export a .glb (one file)")

    def accessor(self, index: int, normalized: bool = False) -> np.ndarray:
        """Accessor ``index`` as ``(count, width)`` (float64 for floats and normalised
        integers; ``normalized`` for weights, which are normalised whatever the flag says)."""
        acc = self.gltf.accessors[index]
        if acc.sparse is not None:
            raise AnimationError(f"{self.path}: accessor {index} is sparse, which torchfit does "
                                 "not read; export dense accessors")
        if acc.type not in _WIDTH or acc.componentType not in _COMPONENTS:
            raise AnimationError(f"{self.path}: accessor {index} has type {acc.type} of "
                                 f"component {acc.componentType}, which torchfit does not read")
        dtype = np.dtype(_COMPONENTS[acc.componentType]).newbyteorder("<")
        width = _WIDTH[acc.type]
        if acc.bufferView is None:
            data = np.zeros((acc.count, width), dtype=dtype)
        else:
            view = self.gltf.bufferViews[acc.bufferView]
            raw = self.buffer(view.buffer)
            start = (view.byteOffset or 0) + (acc.byteOffset or 0)
            stride = view.byteStride or dtype.itemsize * width
            need = start + stride * (acc.count - 1) + dtype.itemsize * width
            if acc.count and need > len(raw):
                raise AnimationError(f"{self.path}: accessor {index} reads past its buffer")
            data = np.ndarray((acc.count, width), dtype=dtype, buffer=raw, offset=start,
                              strides=(stride, dtype.itemsize)).copy()
        if data.dtype.kind in "iu" and (acc.normalized or normalized):
            return data.astype(np.float64) / np.iinfo(data.dtype).max
        return data.astype(np.float64) if data.dtype.kind == "f" else data.astype(np.int64)


def _attribute(attributes: Any, name: str) -> int | None:
    value = attributes.get(name) if isinstance(attributes, dict) else getattr(attributes, name,
                                                                              None)
    return None if value is None else int(value)


def _local_matrices(node: Any) -> np.ndarray:
    if node.matrix is not None and len(node.matrix) == 16:
        return np.array(node.matrix, dtype=np.float64).reshape(4, 4).T   # column-major
    return _trs(np.array(node.translation or [0, 0, 0], dtype=np.float64)[None],
                np.array(node.rotation or [0, 0, 0, 1], dtype=np.float64)[None],
                np.array(node.scale or [1, 1, 1], dtype=np.float64)[None])[0]


def _trs(t: np.ndarray, q: np.ndarray, s: np.ndarray) -> np.ndarray:
    """4x4 column-vector matrices ``T R S`` of ``(n, 3)``, quaternions ``(n, 4)`` (x y z w)."""
    from scipy.spatial.transform import Rotation

    out = np.tile(np.eye(4), (len(t), 1, 1))
    out[:, :3, :3] = Rotation.from_quat(q).as_matrix() * s[:, None, :]
    out[:, :3, 3] = t
    return out


def _sample(times: np.ndarray, keys: np.ndarray, values: np.ndarray, mode: str,
            rotation: bool) -> np.ndarray:
    """Values ``(len(times), w)`` of a sampler (clamped outside its keys)."""
    if len(keys) == 1:
        return np.repeat(values[:1], len(times), axis=0)
    k = np.clip(np.searchsorted(keys, times, side="right") - 1, 0, len(keys) - 2)
    u = np.clip((times - keys[k]) / (keys[k + 1] - keys[k]), 0.0, 1.0)[:, None]
    a, b = values[k], values[k + 1]
    if mode == "STEP":
        return np.where(u >= 1.0, b, a)
    if not rotation:
        return (1 - u) * a + u * b
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    dot = np.sum(a * b, axis=1, keepdims=True)
    b = np.where(dot < 0, -b, b)
    dot = np.abs(dot)
    angle = np.arccos(np.clip(dot, -1.0, 1.0))
    small = angle < 1e-6
    sin = np.where(small, 1.0, np.sin(angle))
    wa = np.where(small, 1 - u, np.sin((1 - u) * angle) / sin)
    wb = np.where(small, u, np.sin(u * angle) / sin)
    out = wa * a + wb * b
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _pick(file: _File, name: str) -> int:
    nodes = file.gltf.nodes or []
    skinned = [i for i, n in enumerate(nodes) if n.skin is not None and n.mesh is not None]
    label = [nodes[i].name or f"node{i}" for i in skinned]
    if name:
        if name not in label:
            raise AnimationError(f"{file.path}: problem.prim={name} is not a skinned node "
                                 f"(skinned: {', '.join(label) or 'none'})")
        return skinned[label.index(name)]
    if not skinned:
        raise AnimationError(f"{file.path}: no skinned mesh (a node with a mesh and a skin)")
    if len(skinned) > 1:
        raise AnimationError(f"{file.path}: {len(skinned)} skinned nodes ({', '.join(label[:4])})"
                             "; choose one with problem.prim=<node name>")
    return skinned[0]


def _mesh(file: _File, mesh: Any) -> tuple[np.ndarray, np.ndarray, list[np.ndarray],
                                           np.ndarray, np.ndarray]:
    """Rest points, faces, morph offsets, joint indices and weights of every primitive."""
    points, faces, targets, joints, weights = [], [], [], [], []
    offset = 0
    for p, primitive in enumerate(mesh.primitives):
        if primitive.mode not in (None, 4):
            raise AnimationError(f"{file.path}: mesh {mesh.name or ''} primitive {p} has mode "
                                 f"{primitive.mode}; torchfit reads triangles (mode 4) only")
        if primitive.extensions:
            raise AnimationError(f"{file.path}: mesh primitive {p} uses "
                                 f"{next(iter(primitive.extensions))} (compression), which "
                                 "torchfit does not read")
        position = _attribute(primitive.attributes, "POSITION")
        if position is None:
            raise AnimationError(f"{file.path}: mesh primitive {p} has no POSITION")
        xyz = file.accessor(position)
        n = len(xyz)
        index = file.accessor(primitive.indices).reshape(-1) if primitive.indices is not None \
            else np.arange(n)
        if index.size % 3 or (index.size and (index.min() < 0 or index.max() >= n)):
            raise AnimationError(f"{file.path}: mesh primitive {p}: indices are not triangles "
                                 f"of its {n} points")
        sets, k = [], 0
        while _attribute(primitive.attributes, f"JOINTS_{k}") is not None:
            weight = _attribute(primitive.attributes, f"WEIGHTS_{k}")
            if weight is None:
                raise AnimationError(f"{file.path}: JOINTS_{k} without WEIGHTS_{k}")
            sets.append((file.accessor(_attribute(primitive.attributes, f"JOINTS_{k}")),
                         file.accessor(weight, normalized=True)))
            k += 1
        if not sets:
            raise AnimationError(f"{file.path}: mesh primitive {p} has no JOINTS_0/WEIGHTS_0")
        j = np.concatenate([s[0] for s in sets], axis=1)
        w = np.concatenate([s[1] for s in sets], axis=1)
        if j.shape[0] != n or w.shape != j.shape:
            raise AnimationError(f"{file.path}: mesh primitive {p}: JOINTS/WEIGHTS have "
                                 f"{j.shape[0]} and {w.shape[0]} entries for {n} points; the "
                                 "weights must match the points")
        points.append(xyz)
        faces.append(index.reshape(-1, 3) + offset)
        joints.append(j)
        weights.append(w)
        targets.append([file.accessor(_attribute(t, "POSITION")) for t in
                        (primitive.targets or [])])
        offset += n
    counts = {len(t) for t in targets}
    if len(counts) > 1:
        raise AnimationError(f"{file.path}: the mesh's primitives have different numbers of "
                             "morph targets")
    shapes = [np.concatenate([t[k] for t in targets]) for k in range(counts.pop())]
    width = max(j.shape[1] for j in joints)

    def padded(arrays: list[np.ndarray]) -> np.ndarray:
        return np.concatenate([np.pad(a, ((0, 0), (0, width - a.shape[1]))) for a in arrays])

    return (np.concatenate(points), np.concatenate(faces), shapes, padded(joints),
            padded(weights))


def load_gltf(path: str | Path, prim: str = "", fps: float = 0.0) -> Animation:
    """Read the skinned node of a glTF file as an :class:`Animation` (metres)."""
    path = Path(path).expanduser()
    file = _File(path)
    gltf = file.gltf
    node_index = _pick(file, prim)
    node = gltf.nodes[node_index]
    skin = gltf.skins[node.skin]
    where = f"{path}:{node.name or f'node{node_index}'}"
    rest, faces, shapes, joint_slots, slot_weights = _mesh(file, gltf.meshes[node.mesh])
    joints = [int(j) for j in skin.joints]
    J = len(joints)
    if joint_slots.size and (joint_slots.min() < 0 or joint_slots.max() >= J):
        raise AnimationError(f"{where}: a JOINTS index lies outside the skin's {J} joints")
    weights = np.zeros((len(rest), J))
    np.add.at(weights, (np.repeat(np.arange(len(rest)), joint_slots.shape[1]),
                        joint_slots.reshape(-1)), slot_weights.reshape(-1))
    inverse_bind = np.tile(np.eye(4), (J, 1, 1)) if skin.inverseBindMatrices is None else \
        file.accessor(skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    if inverse_bind.shape[0] != J:
        raise AnimationError(f"{where}: {inverse_bind.shape[0]} inverse bind matrices for {J} "
                             "joints")
    # the node tree: parents, and the animation's channels
    nodes = gltf.nodes
    parent = np.full(len(nodes), -1)
    for i, n in enumerate(nodes):
        for c in n.children or []:
            parent[c] = i
    animation = gltf.animations[0] if gltf.animations else None
    channels = []
    for channel in (animation.channels if animation else []):
        sampler = animation.samplers[channel.sampler]
        if sampler.interpolation == "CUBICSPLINE":
            raise AnimationError(f"{path}: animation sampler {channel.sampler} is CUBICSPLINE, "
                                 "which torchfit does not read; bake to LINEAR keys")
        keys = file.accessor(sampler.input).reshape(-1)
        channels.append((channel.target.node, channel.target.path, keys,
                         file.accessor(sampler.output), sampler.interpolation or "LINEAR"))
    if channels:
        all_keys = np.concatenate([c[2] for c in channels])
        times = np.arange(all_keys.min(), all_keys.max() + 0.5 / fps, 1.0 / fps) if fps > 0 \
            else np.unique(np.round(all_keys, 9))
    else:
        times = np.zeros(1)
    F = len(times)
    trs = {i: [np.repeat(np.array(v, dtype=np.float64)[None], F, 0) for v in (
        n.translation or [0, 0, 0], n.rotation or [0, 0, 0, 1], n.scale or [1, 1, 1])]
        for i, n in enumerate(nodes)}
    default_weights = getattr(node, "weights", None) or gltf.meshes[node.mesh].weights \
        or [0.0] * len(shapes)
    shape_weights = np.repeat(np.array(default_weights, dtype=np.float64)[None], F, 0)
    animated = set()
    for target, kind, keys, values, mode in channels:
        if kind == "weights":
            if target == node_index:
                shape_weights = _sample(times, keys, values.reshape(len(keys), -1), mode, False)
            continue
        slot = {"translation": 0, "rotation": 1, "scale": 2}[kind]
        trs[target][slot] = _sample(times, keys, values, mode, kind == "rotation")
        animated.add(target)
    local = np.stack([_trs(*trs[i]) if (i in animated or nodes[i].matrix is None)
                      else np.repeat(_local_matrices(nodes[i])[None], F, 0)
                      for i in range(len(nodes))], axis=1)            # (F, N, 4, 4)
    world = local.copy()
    done = np.zeros(len(nodes), dtype=bool)

    def resolve(i: int) -> None:
        if not done[i]:
            if parent[i] >= 0:
                resolve(parent[i])
                world[:, i] = world[:, parent[i]] @ local[:, i]
            done[i] = True

    for i in range(len(nodes)):
        resolve(i)
    matrices = world[:, joints] @ inverse_bind[None]                   # (F, J, 4, 4)
    posed = rest[None] + np.einsum("fk,kvi->fvi", shape_weights, np.stack(shapes)) \
        if shapes else np.repeat(rest[None], F, 0)
    moved = np.einsum("fjab,fvb->fjva", matrices[..., :3, :3], posed) \
        + matrices[:, :, None, :3, 3]
    frames = np.einsum("vj,fjva->fva", weights / weights.sum(1, keepdims=True).clip(1e-300),
                       moved)
    joint_parent = []
    for j in joints:
        k = parent[j]
        while k >= 0 and k not in joints:
            k = parent[k]
        joint_parent.append(joints.index(k) if k >= 0 else -1)
    radius = None
    for holder in (skin, node):
        if isinstance(holder.extras, dict) and "torchfit:attachRadius" in holder.extras:
            radius = float(holder.extras["torchfit:attachRadius"])
            break
    positions = np.linalg.inv(inverse_bind)[:, :3, 3]
    names = [nodes[j].name or f"joint{j}" for j in joints]
    lengths = np.array([float(nodes[j].extras.get("torchfit:boneLength", np.nan))
                        if isinstance(nodes[j].extras, dict) else np.nan for j in joints])
    skeleton = skeleton_from_joints(positions, np.array(joint_parent), matrices[..., :3, :],
                                    weights, names, radius, rest, where, lengths,
                                    authored_as=("the extras' torchfit:attachRadius",
                                                 "the joint's extras torchfit:boneLength"))
    if not np.isfinite(frames).all():
        raise AnimationError(f"{where}: the posed points hold a NaN or infinite coordinate")
    import trimesh

    from ...surface import surface_warnings

    surface = trimesh.Trimesh(rest, faces, process=False)
    return Animation(path, rest, faces, frames, 1.0, skeleton=skeleton,
                     frame_files=[f"{path.name}@{t:.6g}s" for t in times],
                     warnings=surface_warnings(surface), up=np.array([0.0, 1.0, 0.0]))
