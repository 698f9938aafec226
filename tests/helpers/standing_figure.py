"""A small standing figure along +Y (a Y-up body), rigged from its pelvis, for the camera tests.

The surface is a body of revolution about the y axis (metres): thin legs (radius 0.06, y 0
to 0.8), a thick torso (radius 0.16, y 0.85 to 1.4), a neck and a head (to y 1.65). Its
volume's long tail is the legs, so its third moment along y is negative: the principal
frame's ``a2`` points down (-y), the sign the old camera stood the picture on. The rig is
SMPL-like, rooted at the pelvis (0, 0.8, 0): two legs (thigh, shin: two bones each) and the
spine (spine, chest, neck, head: four bones) start there. Two frames bend the spine's upper
three bones (about z, towards +x) by 0 and 25 degrees; the surface follows by linear blend
skinning with distance weights.

:func:`figure_animation` returns the parts; :func:`write_figure` writes it as an animation
folder (with an optional manifest ``up``), a USD stage (``upAxis`` Y, or Z after turning the
figure to stand along +z) or a glTF file, through the project's own writers.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from torchfit.mesh import Skeleton, write_animation
from torchfit.mesh.rig import blend, distance_weights, segment_distances

PROFILE = [(0.0, 0.0), (0.06, 0.0), (0.06, 0.8), (0.16, 0.85), (0.16, 1.4), (0.06, 1.44),
           (0.08, 1.52), (0.07, 1.62), (0.0, 1.65)]
PELVIS = (0.0, 0.8, 0.0)
#: heads, tails of the bones: left thigh, left shin, right thigh, right shin, spine, chest,
#: neck, head
BONES = [((0.0, 0.8, 0.0), (-0.03, 0.4, 0.0)), ((-0.03, 0.4, 0.0), (-0.03, 0.02, 0.0)),
         ((0.0, 0.8, 0.0), (0.03, 0.4, 0.0)), ((0.03, 0.4, 0.0), (0.03, 0.02, 0.0)),
         ((0.0, 0.8, 0.0), (0.0, 1.1, 0.0)), ((0.0, 1.1, 0.0), (0.0, 1.4, 0.0)),
         ((0.0, 1.4, 0.0), (0.0, 1.5, 0.0)), ((0.0, 1.5, 0.0), (0.0, 1.62, 0.0))]
NAMES = ["thigh_l", "shin_l", "thigh_r", "shin_r", "spine", "chest", "neck", "head"]
ANGLES = (0.0, 25.0)
#: a rotation taking +y to +z (the figure standing in a Z-up stage)
Y_TO_Z = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def surface() -> tuple[np.ndarray, np.ndarray]:
    """Rest vertices ``(V, 3)`` along +y and faces ``(T, 3)`` (closed, outward)."""
    mesh = trimesh.creation.revolve(np.array(PROFILE), sections=16)   # about z
    vertices = np.asarray(mesh.vertices) @ Y_TO_Z        # z -> y: (x, y, z) -> (x, z, -y)
    return vertices, np.asarray(mesh.faces)


def figure_animation(rotation: np.ndarray | None = None) -> dict:
    """``rest``, ``faces``, ``frames`` ``(2, V, 3)`` and ``skeleton`` (with weights), all
    turned by ``rotation`` ``(3, 3)`` (``None``: standing along +y)."""
    R = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
    rest, faces = surface()
    heads = np.array([h for h, _ in BONES])
    tails = np.array([t for _, t in BONES])
    transforms = np.zeros((len(ANGLES), len(BONES), 3, 4))
    transforms[..., :3] = np.eye(3)
    pivot = np.array([0.0, 1.1, 0.0])                   # the chest joint
    for f, degrees in enumerate(ANGLES):
        a = np.radians(-degrees)                        # about z: +y towards +x
        bend = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        for b in (5, 6, 7):
            transforms[f, b, :, :3] = bend
            transforms[f, b, :, 3] = pivot - bend @ pivot
    weights = distance_weights(segment_distances(rest, heads, tails), 0.1)
    weights[weights < np.sort(weights, axis=1)[:, -4:-3]] = 0.0    # four influences (glTF)
    weights /= weights.sum(axis=1, keepdims=True)
    frames = blend(rest, weights, transforms)
    turned = transforms.copy()
    turned[..., :3] = R @ transforms[..., :3] @ R.T
    turned[..., 3] = transforms[..., 3] @ R.T
    skeleton = Skeleton(heads @ R.T, tails @ R.T, turned, 0.04, weights, list(NAMES))
    return {"rest": rest @ R.T, "faces": faces, "frames": frames @ R.T, "skeleton": skeleton}


def write_figure(path: Path, kind: str = "folder", *, up: str | None = None,
                 rotation: np.ndarray | None = None, rig: bool = True) -> Path:
    """Write the figure: ``kind`` ``folder`` (manifest ``up`` as given; ``rig=False``: the
    pelvis ring driven instead of the skeleton), ``usd-y`` (a stage with upAxis Y),
    ``usd-z`` (turned to stand along +z, upAxis Z) or ``gltf`` (a ``.glb``); ``rotation``
    turns the folder's figure. Returns the path to give ``problem.path``."""
    if kind == "usd-z":
        rotation = Y_TO_Z
    data = figure_animation(rotation)
    if kind == "folder":
        if rig:
            return write_animation(path, data["rest"], data["faces"], data["frames"],
                                   skeleton=data["skeleton"], up=up)
        from torchfit.mesh import DrivenSurface

        feet = data["rest"] @ (np.eye(3) if rotation is None else rotation)
        return write_animation(path, data["rest"], data["faces"], data["frames"],
                               driven=DrivenSurface(feet[:, 1] < 0.05, 0.03), up=up)
    if kind.startswith("usd"):
        from torchfit.mesh.formats.usd.writer import write_skinned_usd

        return write_skinned_usd(path, data["rest"], data["faces"], data["skeleton"],
                                 up_axis=kind[-1].upper())
    from torchfit.mesh.formats.gltf.writer import write_skinned_gltf

    return write_skinned_gltf(path, data["rest"], data["faces"], data["skeleton"])
