"""A body restrained by surface patches only (driven-vertex animations of the capsule).

``write_patch_capsule(folder, patches=1)``: the capsule of :mod:`.capsule_animation` with
one driven patch, its upper cap, and frames that rotate the whole body rigidly about the
joint (0, 15, 30 degrees about y): any material moves it so, so the data determine no
material. ``patches=2``: both caps driven, the lower one held and the upper one turned
with the bend of the skinned capsule (the frames of :func:`.capsule_animation.write_capsule`
in ``driven`` mode): the body bends between them, as a material decides.
``patches=1, bent=True``: the upper cap alone driven, turned with the bend, and the frames
of the bent capsule as targets (a hand driven only at the wrist): the body follows its patch
rigidly whatever the material, the targets do not, so the data are not a rigid motion of the
rest and still determine no material.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from helpers.capsule_animation import HALF, RADIUS, bone_transforms, capsule, write_capsule
from torchfit.mesh import DrivenSurface, write_animation

#: driven.tolerance of the patches (m)
TOLERANCE = 0.006


def write_patch_capsule(folder: Path, patches: int = 1, bent: bool = False) -> Path:
    """Write the capsule driven by ``patches`` (1 or 2) surface patches, with rigid or
    ``bent`` frames for one patch (module docstring)."""
    if patches == 2:
        return write_capsule(folder, "driven")
    mesh = capsule()
    rest = np.asarray(mesh.vertices)
    upper_cap = rest[:, 2] > HALF + 0.5 * RADIUS
    if bent:
        skinned = write_capsule(folder.with_name(folder.name + ".bent"), "driven")
        with np.load(skinned / "frames.npz") as saved:
            frames = saved["frames"]
        shutil.rmtree(skinned)
    else:
        rotations = bone_transforms()[:, 1, :, :3]                   # (F, 3, 3) about y
        frames = np.einsum("fij,vj->fvi", rotations, rest)           # rigid: joint at 0
    write_animation(folder, rest, np.asarray(mesh.faces), frames,
                    driven=DrivenSurface(upper_cap, TOLERANCE))
    return folder
