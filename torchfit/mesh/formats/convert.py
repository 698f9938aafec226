"""Convert a rigged animation between the three formats: the folder format, a USD UsdSkel
stage and a glTF skin (``scripts/convert.sh IN OUT``).

The output's suffix chooses the writer: ``.usd``/``.usda``/``.usdc`` a UsdSkel stage
(:func:`.usd.writer.write_skinned_usd`), ``.glb``/``.gltf`` a glTF skin
(:func:`.gltf.writer.write_skinned_gltf`), anything else an animation folder
(:func:`.folder.write_animation`). What is carried (every length in metres, USD
``metersPerUnit`` 1):

- the surface on the file's own vertices (:func:`.readers.read_animation` with
  ``weld=False``): seams a DCC split (a glTF's UV seams) are written split, as the input had
  them, and every reader welds them again alike;
- the frames, the skeleton (bones, per-frame rigid transforms, per-vertex weights, the
  attach radius), the driven vertices and their tolerance of a point cache, the region
  labels (folder to folder only);
- blend shapes: whatever the frames hold beyond the skinning (correctives, the input's blend
  shapes) as rest-pose shapes with per-frame weights (the residual pulled back through each
  vertex's blended bone transform, compressed to as few shapes as reproduce it within
  ``SHAPE_TOLERANCE``); the input's shape names are not kept;
- the frame rate (``--fps``; else a USD stage's time codes per second, a glTF animation's key
  spacing, 24 for a folder, which has none) and, for USD, the up axis (a USD input's, Y for
  a glTF input, ``--up-axis`` else; positions are never rotated).

A point cache (driven vertices, no rig) converts to USD or a folder, not to glTF (torchfit
reads glTF skins only). The output is written under a temporary name beside it, read back
and compared with the input (frames within :func:`check_tolerance`), then renamed into place.
An existing output is replaced only where it is of the kind written: a USD stage by a
stage, a glTF file by a glTF file, an animation folder torchfit wrote by a folder
(:func:`.folder.check_replaceable`); anything else there (a user's folder, a plain file) is
refused before the input is read. Any fault (a refusal, a full disk, a file-size limit, a
read-only place) is one ``error:`` line, exit 2, nothing written.
"""
from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from ...errors import write_failure, write_failure_line
from ..animation import Animation, AnimationError
from .folder import check_replaceable, replace_folder, write_animation
from .sniff import GLTF_SUFFIXES, suffix_reader
from ..rig import Skeleton

_log = logging.getLogger(__name__)

#: the blend shapes reproduce the frames' residual over the skinning within this (metres;
#: float32, as USD and glTF store points, resolves 6e-8 m at 1 m)
SHAPE_TOLERANCE = 1e-7
#: the written file, read back, reproduces the input's frames within this (metres) or
#: ``CHECK_RELATIVE`` of the animation's extent, whichever is larger: USD and glTF store
#: float32 (6e-8 of a coordinate's size per rounding, a few roundings through the joints), so
#: a fixed tolerance refused large bodies (a stage 1.07e-6 m off against 1e-6 m)
CHECK_TOLERANCE = 1e-6
CHECK_RELATIVE = 1e-6
USD_OUT = (".usd", ".usda", ".usdc")


def output_kind(path: Path) -> str:
    """``usd``, ``gltf`` or ``folder`` (by the suffix; ``.usdz`` is not written)."""
    suffix = path.suffix.lower()
    if suffix == ".usdz":
        raise AnimationError(f"{path}: convert writes .usd, .usda or .usdc stages, not a .usdz "
                             "package; write a .usdc and package it with usdzip")
    return "usd" if suffix in USD_OUT else "gltf" if suffix in GLTF_SUFFIXES else "folder"


#: the first bytes of a file of each kind convert writes (an existing output it replaces)
_MAGIC = {"usd": (b"#usda", b"PXR-USDC"), "gltf": (b"glTF", b"{")}


def check_output(out: Path, target: str) -> None:
    """Refuse (one line) an existing ``out`` that is not of the kind ``target`` writes: a
    folder or another file where a USD stage or glTF file goes, a plain file or a user's
    folder where an animation folder goes. An empty file may be replaced."""
    if target == "folder":
        check_replaceable(out)
        return
    if not (out.exists() or out.is_symlink()):
        return
    name = "a USD stage" if target == "usd" else "a glTF file"
    if out.is_dir():
        raise AnimationError(f"{out} is a folder; {name} would replace it: name a file")
    try:
        with open(out, "rb") as existing:
            head = existing.read(8).lstrip()
    except OSError as err:
        raise AnimationError(f"{out} cannot be read ({err.strerror}); name another output")
    if head and not head.startswith(_MAGIC[target]):
        raise AnimationError(f"{out} exists and is not {name}; convert replaces only a file "
                             "of the kind it writes: name another path, or remove it")


def check_tolerance(animation: Animation) -> float:
    """How far the read-back may lie from the input (metres): :data:`CHECK_TOLERANCE`, or
    :data:`CHECK_RELATIVE` of the extent of every position the animation takes."""
    every = np.concatenate([animation.rest_vertices[None], animation.frames]).reshape(-1, 3)
    extent = float(np.linalg.norm(every.max(axis=0) - every.min(axis=0)))
    return max(CHECK_TOLERANCE, CHECK_RELATIVE * extent)


def up_axis(path: Path, kind: str, given: str) -> str:
    """The up axis to write in a USD output: ``given``, else a USD input's, else Y for a glTF
    input (as glTF says), else Z (torchfit's arm)."""
    if given:
        return given
    if kind == "usd":
        from pxr import Usd, UsdGeom

        stage = Usd.Stage.Open(str(path))
        return str(UsdGeom.GetStageUpAxis(stage)) if stage else "Z"
    return "Y" if kind == "gltf" else "Z"


def blend_shapes(rest: np.ndarray, frames: np.ndarray, skeleton: Skeleton, where: str
                 ) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Rest-pose shapes ``name -> (V, 3)`` and weights ``(F, K)`` such that skinning
    ``rest + weights @ shapes`` with ``skeleton`` gives ``frames`` (``{}`` where the skinning
    alone does, within ``SHAPE_TOLERANCE``)."""
    weights = skeleton.weights
    A = np.einsum("vb,fbij->fvij", weights, skeleton.transforms[..., :3])      # (F, V, 3, 3)
    t = np.einsum("vb,fbi->fvi", weights, skeleton.transforms[..., 3])
    if (np.abs(np.linalg.det(A)) < 1e-9).any():
        f, v = np.argwhere(np.abs(np.linalg.det(A)) < 1e-9)[0]
        raise AnimationError(f"{where}: frame {f}, vertex {v}: its blended bone transform is "
                             "singular, so no rest-pose shape reproduces the frame")
    offsets = np.linalg.solve(A, (frames - t)[..., None])[..., 0] - rest[None]  # (F, V, 3)
    D = offsets.reshape(len(frames), -1)
    if np.abs(D).max() <= SHAPE_TOLERANCE:
        return {}, np.zeros((len(frames), 0))
    U, S, Vt = np.linalg.svd(D, full_matrices=False)
    for k in range(1, len(S) + 1):
        if np.abs((U[:, :k] * S[:k]) @ Vt[:k] - D).max() <= SHAPE_TOLERANCE:
            break
    # scale each shape to its largest weight so the weights lie in [-1, 1], largest +1
    coefficients = U[:, :k] * S[:k]
    peak = coefficients[np.abs(coefficients).argmax(axis=0), np.arange(k)]
    shapes = {f"shape{i}": (Vt[i] * peak[i]).reshape(-1, 3) for i in range(k)}
    return shapes, coefficients / peak


def _check_rig(animation: Animation, target: str, where: str) -> Skeleton:
    skeleton = animation.skeleton
    if skeleton is None:
        if target == "gltf":
            raise AnimationError(f"{where} is a point cache (driven vertices, no rig); torchfit "
                                 "reads glTF skins only: convert it to a .usd stage or a folder")
        return None
    if skeleton.weights is None:
        raise AnimationError(f"{where}: the skeleton has no per-vertex skinning weights "
                             "(weights: distance); a USD or glTF skin needs them: give "
                             "skeleton.weights a .npy of (vertices, bones) weights")
    A = skeleton.transforms[..., :3]
    gap = np.abs(np.einsum("fbji,fbjk->fbik", A, A) - np.eye(3)).max()
    if gap > 1e-5 or (np.linalg.det(A) <= 0).any():
        raise AnimationError(f"{where}: the bone transforms are not rigid (A^T A differs from "
                             f"the identity by {gap:.2g}); a USD or glTF joint holds rotation "
                             "and translation only")
    if target == "gltf" and ((skeleton.weights > 0).sum(axis=1) > 4).any():
        v = int(np.flatnonzero((skeleton.weights > 0).sum(axis=1) > 4)[0])
        raise AnimationError(f"{where}: vertex {v} has {(skeleton.weights[v] > 0).sum()} "
                             "bone influences; a glTF skin holds four: convert to .usd or a "
                             "folder, or limit the influences to four in your DCC")
    return skeleton


def _write(animation: Animation, out: Path, target: str, fps: float, up: str,
           description: str) -> int:
    """Write ``animation`` to ``out`` as ``target``; returns the number of blend shapes."""
    rest, faces, frames = animation.rest_vertices, animation.faces, animation.frames
    skeleton = _check_rig(animation, target, str(animation.path))
    if target == "folder":
        labels = animation.region_labels
        write_animation(out, rest, faces, frames, skeleton=skeleton, driven=animation.driven,
                        region_labels=labels, region_names=animation.region_names or None,
                        description=description, fps=fps)
        return 0
    if skeleton is None:                              # a point cache as a USD stage
        from pxr import Sdf, Usd, UsdGeom, Vt

        from .usd import write_point_cache_usd

        write_point_cache_usd(out, faces, frames, prim="/Body", fps=fps)
        stage = Usd.Stage.Open(str(out))
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Body"))
        mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(rest.astype(np.float32)))
        UsdGeom.PrimvarsAPI(mesh.GetPrim()).CreatePrimvar(
            "torchfit:driven", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex).Set(
            Vt.IntArray([int(m) for m in animation.driven.mask]))
        mesh.GetPrim().CreateAttribute("torchfit:drivenTolerance", Sdf.ValueTypeNames.Double
                                       ).Set(float(animation.driven.tolerance))
        UsdGeom.SetStageUpAxis(stage, up)
        stage.SetDefaultPrim(mesh.GetPrim())
        stage.GetRootLayer().Save()
        return 0
    shapes, shape_weights = blend_shapes(rest, frames, skeleton, str(animation.path))
    if target == "usd":
        from pxr import Usd, UsdGeom

        from .usd import write_skinned_usd

        write_skinned_usd(out, rest, faces, skeleton, shapes, shape_weights, fps)
        stage = Usd.Stage.Open(str(out))
        UsdGeom.SetStageUpAxis(stage, up)
        stage.GetRootLayer().Save()
    else:
        from .gltf import write_skinned_gltf

        write_skinned_gltf(out, rest, faces, skeleton, shapes, shape_weights, fps)
    return len(shapes)


def convert(source: Path, out: Path, prim: str = "", fps: float = 0.0, up: str = "") -> str:
    """Write the animation at ``source`` to ``out`` (module docstring); returns a summary
    line. Raises :class:`AnimationError` (one line) and writes nothing on a fault."""
    from .readers import read_animation

    source, out = Path(source).expanduser(), Path(out).expanduser()
    if not source.exists():
        raise AnimationError(f"{source.absolute()}: no such file or folder")
    if source.resolve() == out.resolve() or (source.is_dir() and out.resolve().is_relative_to(
            source.resolve())):
        raise AnimationError(f"{out}: the output would overwrite the input; name another path")
    kind = suffix_reader(source)
    target = output_kind(out)
    check_output(out, target)
    if fps < 0 or not np.isfinite(fps):
        raise AnimationError(f"--fps={fps}: give a positive frame rate (or leave it unset)")
    animation = read_animation(source, prim, fps if kind == "gltf" else 0.0, weld=False)
    rate = fps if fps > 0 else animation.fps
    axis = up_axis(source, kind, up)
    description = f"converted from {source.name}" + (f" ({animation.prim})" if animation.prim
                                                      else "") + f" at {rate:g} fps"
    if animation.region_labels is not None and target != "folder":
        _log.warning("%s: its region labels are not carried into a %s file (a folder keeps "
                     "them)", source, "USD" if target == "usd" else "glTF")
    tmp_dir = None
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp_dir = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
        tmp = tmp_dir / (out.name if target != "folder" else "animation")
        try:
            n_shapes = _write(animation, tmp, target, rate, axis, description)
        except ImportError as err:
            extra = "usd" if target == "usd" else "gltf"
            raise AnimationError(f"{out}: writing {extra.upper()} needs the optional extra "
                                 f"'{extra}': pip install 'torchfit[{extra}]' ({err})") from err
        back = read_animation(tmp, weld=False)
        gap = float(np.abs(back.frames - animation.frames).max())
        rest_gap = float(np.abs(back.rest_vertices - animation.rest_vertices).max())
        tolerance = check_tolerance(animation)
        if max(gap, rest_gap) > tolerance or back.frames.shape != animation.frames.shape:
            raise AnimationError(f"{out}: the converted file reads back {gap:.3g} m from the "
                                 f"input's frames (rest {rest_gap:.3g} m), over "
                                 f"{tolerance:.3g} m; nothing written")
        if target == "folder":
            replace_folder(tmp, out)
        else:
            os.replace(tmp, out)         # checked above: nothing or a file of this kind
    except Exception as err:            # noqa: BLE001 - a write fault of any library
        failure = write_failure(err)
        if failure is None:
            raise
        raise AnimationError(write_failure_line(failure, out) + " (nothing was written)"
                             ) from None
    finally:
        if tmp_dir is not None:
            shutil.rmtree(tmp_dir, ignore_errors=True)
    rig = f"{animation.skeleton.n_bones} bones" if animation.skeleton is not None else \
        f"{int(animation.driven.mask.sum())} driven vertices"
    shapes = f", {n_shapes} blend shapes" if target != "folder" and animation.skeleton else ""
    return (f"wrote {out}: {animation.n_vertices} vertices, {animation.n_frames} frames at "
            f"{rate:g} fps, {rig}{shapes}; read back within {gap:.2g} m of the input")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="scripts/convert.sh",
        description="Convert a rigged animation between the animation folder format, a USD "
                    "UsdSkel stage and a glTF skin; the output's suffix chooses the format "
                    "(.usd/.usda/.usdc: USD, .glb/.gltf: glTF, anything else: a folder). "
                    "Carries the surface (seams as the input has them), the frames, the "
                    "skeleton with its per-frame transforms and weights (or a point cache's "
                    "driven vertices), what the frames hold beyond the skinning as blend "
                    "shapes, the frame rate; metres. The output is read back and compared "
                    "with the input (within 1e-6 m, or 1e-6 of the body's extent if larger) "
                    "before it replaces an existing one of its kind.",
        epilog="examples: scripts/convert.sh shot.usdc shot.glb; scripts/convert.sh my_arm "
               "arm.usda; scripts/convert.sh rig.glb rig_folder --fps 30 "
               "(docs/guide/formats.md)")
    parser.add_argument("input", type=Path, help="an animation folder (or its animation.yaml), "
                        "a USD stage or a glTF file")
    parser.add_argument("output", type=Path, help="the file or folder to write (replaced)")
    parser.add_argument("--prim", default="", help="the mesh to read: a prim path of a USD "
                        "stage or a node name of a glTF file (default: the one skinned mesh)")
    parser.add_argument("--fps", type=float, default=0.0,
                        help="frame rate of the output (and the rate a glTF input's animation "
                             "is sampled at); default: the input's (a folder has none: 24)")
    parser.add_argument("--up-axis", choices=("Y", "Z"), default="",
                        help="the up axis a USD output declares (positions are not rotated); "
                             "default: a USD input's, Y for glTF, Z for a folder")
    args = parser.parse_args(argv)
    logging.basicConfig(format="warning: %(message)s", level=logging.WARNING)
    try:
        print(convert(args.input, args.output, args.prim, args.fps, args.up_axis))
    except AnimationError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
