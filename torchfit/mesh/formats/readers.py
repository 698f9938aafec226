"""Which reader a ``problem.path`` takes: the folder format, a USD stage or a glTF file.

A file is first sniffed (:mod:`.sniff`): FBX, Alembic, a bare OBJ/PLY/STL mesh and a file
whose suffix names another reader than its content are refused with one line saying what
the file is and what to export instead. Otherwise :func:`read_animation` dispatches by the
path's suffix: ``.usd``, ``.usda``, ``.usdc``,
``.usdz`` to :mod:`.usd.reader` (the extra ``usd``), ``.gltf``, ``.glb`` to
:mod:`.gltf.reader` (the extra ``gltf``), anything else (a folder, a manifest) to
:func:`.folder.load_animation`. Every reader returns the same
:class:`~.folder.Animation`, its seams welded (:mod:`.seams`: a glTF's split
vertices are one surface again, the file's own vertices kept for outputs); errors are one
line (:class:`~.folder.AnimationError`).
"""
from __future__ import annotations

from pathlib import Path

from .folder import Animation, AnimationError, load_animation
from .seams import weld_seams
from .sniff import GLTF_SUFFIXES, USD_SUFFIXES, refusal


def read_animation(path: str | Path, prim: str = "", fps: float = 0.0,
                   weld: bool = True) -> Animation:
    """The animation at ``path``, seams welded (``weld=False``: on the file's own vertices,
    as scripts/convert.sh writes them); ``prim`` picks the mesh of a USD stage (a prim path)
    or of a glTF file (a node name), ``fps`` the sampling rate of a glTF animation (0: its
    keyframes). Both are refused for the folder format, which has neither."""
    animation = _read(path, prim, fps)
    return weld_seams(animation) if weld else animation


def _read(path: str | Path, prim: str, fps: float) -> Animation:
    refused = refusal(path)
    if refused:
        raise AnimationError(refused)
    suffix = Path(path).suffix.lower()
    if suffix in USD_SUFFIXES:
        from .usd.reader import load_usd

        if fps:
            raise AnimationError(f"{path}: problem.fps applies to glTF files only (a USD stage "
                                 "has its time samples); leave it at 0")
        return load_usd(path, prim)
    if suffix in GLTF_SUFFIXES:
        from .gltf.reader import load_gltf

        return load_gltf(path, prim, fps)
    if prim or fps:
        raise AnimationError(f"{path}: problem.{'prim' if prim else 'fps'} applies to USD or "
                             "glTF files only; leave it unset for an animation folder")
    return load_animation(path)
