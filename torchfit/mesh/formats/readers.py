"""Which reader a ``problem.path`` takes: the folder format, a USD stage or a glTF file.

A file is first sniffed (:mod:`.sniff`): FBX, Alembic, a bare OBJ/PLY/STL mesh and a file
whose suffix names another reader than its content are refused with one line saying what
the file is and what to export instead. Otherwise :func:`read_animation` dispatches by the
path's suffix: ``.usd``, ``.usda``, ``.usdc``,
``.usdz`` to :mod:`.usd.reader` (the extra ``usd``), ``.gltf``, ``.glb`` to
:mod:`.gltf.reader` (the extra ``gltf``), anything else (a folder, a manifest) to
:func:`.folder.load_animation`. Every reader returns the same
:class:`~torchfit.mesh.Animation`, its seams welded (:mod:`.seams`: a glTF's split
vertices are one surface again, the file's own vertices kept for outputs); errors are one
line (:class:`~torchfit.mesh.AnimationError`).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

from ..animation import DEFAULT_FPS, Animation, AnimationError
from .folder import load_animation
from .seams import weld_seams
from .sniff import GLTF_SUFFIXES, USD_SUFFIXES, refusal


def read_animation(path: str | Path, prim: str = "", fps: float = 0.0,
                   weld: bool = True) -> Animation:
    """The animation at ``path``, seams welded (``weld=False``: on the file's own vertices,
    as scripts/convert.sh writes them); ``prim`` picks the mesh of a USD stage (a prim path)
    or of a glTF file (a node name), ``fps`` the sampling rate of a glTF animation (0: its
    keyframes). Both are refused for the folder format, which has neither. The
    animation's ``fps`` is :func:`frame_rate`'s."""
    animation = _read(path, prim, fps)
    kind = suffix_kind(path)
    if kind != "folder":
        animation = dataclasses.replace(animation, fps=frame_rate(path, kind, fps))
    return weld_seams(animation) if weld else animation


def suffix_kind(path: str | Path) -> str:
    """``'usd'``, ``'gltf'`` or ``'folder'`` by the path's suffix."""
    suffix = Path(path).suffix.lower()
    return "usd" if suffix in USD_SUFFIXES else "gltf" if suffix in GLTF_SUFFIXES else "folder"


def frame_rate(path: str | Path, kind: str, fps: float) -> float:
    """Frames per second of the animation at ``path``: ``fps`` where given (a glTF's
    sampling), else a USD stage's time codes per second, a glTF animation's key rate
    (``(keys - 1) / duration``), or ``DEFAULT_FPS``; a folder's is its manifest's."""
    if fps > 0:
        return float(fps)
    if kind == "usd":
        from pxr import Usd

        stage = Usd.Stage.Open(str(path))
        return float(stage.GetTimeCodesPerSecond()) if stage else DEFAULT_FPS
    if kind == "gltf":
        import pygltflib

        gltf = pygltflib.GLTF2().load(str(path))
        for animation in gltf.animations or []:
            for sampler in animation.samplers:
                keys = gltf.accessors[sampler.input]
                if keys.count > 1 and keys.min and keys.max and keys.max[0] > keys.min[0]:
                    # float32 key times: 29.999998 is 30 (23.976 stays)
                    return float(round((keys.count - 1) / (keys.max[0] - keys.min[0]), 3))
    return DEFAULT_FPS


def _read(path: str | Path, prim: str, fps: float) -> Animation:
    refused = refusal(path)
    if refused:
        raise AnimationError(refused)
    suffix = Path(path).suffix.lower()
    if suffix in USD_SUFFIXES:
        from .usd import load_usd

        if fps:
            raise AnimationError(f"{path}: problem.fps applies to glTF files only (a USD stage "
                                 "has its time samples); leave it at 0")
        return load_usd(path, prim)
    if suffix in GLTF_SUFFIXES:
        from .gltf import load_gltf

        return load_gltf(path, prim, fps)
    if prim or fps:
        raise AnimationError(f"{path}: problem.{'prim' if prim else 'fps'} applies to USD or "
                             "glTF files only; leave it unset for an animation folder")
    return load_animation(path)
