#!/usr/bin/env python
"""Write the procedural arm of ``problem=arm3d`` as an animation folder (the worked example
of docs/guide/formats.md).

    .venv/bin/python scripts/write_arm.py my_arm            # 48 frames, skeleton-driven
    .venv/bin/python scripts/write_arm.py my_arm --frames-as-meshes
    .venv/bin/python scripts/write_arm.py my_shot --n-frames 6 --max-flexion 90   # another shot
    .venv/bin/python scripts/write_arm.py my_jiggle --jiggle 1.0   # keyframed secondary motion
    scripts/fit.sh problem=animation problem.path=my_arm
    .venv/bin/python scripts/write_arm.py --usd arm.usda --gltf arm.glb   # the same arm as a
    scripts/fit.sh problem=animation problem.path=arm.usda    # UsdSkel rig and as a glTF skin

The folder holds ``animation.yaml`` (the manifest), ``rest.obj``, the frames (``frames.npz``
or ``frames/frame_000.obj`` ...), ``skeleton.npz`` (bone heads, tails and per-frame
``[A | t]`` transforms) and ``weights.npy`` (skinning weights per rest vertex).

``--jiggle A`` adds hand-style secondary motion to the folder's frames (not to the rig): after
every change of speed the flesh lags and overshoots in a damped oscillation
(``--jiggle-frequency`` Hz, ``--jiggle-damping`` ratio; the bellies of bicep and tricep move
most; :func:`torchfit.problems.body.procedural_arm.keyframed_jiggle`), the target that
``problem.dynamic=true`` explains and the quasistatic body cannot. ``--fps`` goes in the
manifest (default 24).

``--usd`` (extra ``usd``) and ``--gltf`` (extra ``gltf``) write the arm as a skinned mesh:
joints shoulder, elbow and wrist tip, the weights, the elbow's animation and the bicep and
tricep correctives as blend shapes (morph targets in glTF), so that UsdSkel (or the glTF
skinning) poses it to the folder's frames (float32 storage: within 1e-7 m). Both formats
store the rest surface in float32, and pytetwild meshes a surface moved by that rounding
(3e-8 m) differently; ``--float32-rest`` rounds the rest surface of every output (the folder
too) to float32, so that all three tetrahedralise alike and fit to the same figures.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torchfit.mesh import AnimationError, check_replaceable, write_animation  # noqa: E402
from torchfit.problems.body.procedural_arm import ArmShape, arm_animation  # noqa: E402
from torchfit.problems.body.procedural_arm import MAX_FLEXION  # noqa: E402
from torchfit.problems.body.procedural_arm import corrective_shapes  # noqa: E402
from torchfit.problems.body.procedural_arm import flesh_weights, keyframed_jiggle  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Write the procedural arm of problem=arm3d as an animation folder (the "
                    "worked example of the format), and as a UsdSkel stage or a glTF skin.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n"
               "  .venv/bin/python scripts/write_arm.py my_arm     # 48 frames, skeleton-driven\n"
               "  .venv/bin/python scripts/write_arm.py --usd arm.usda --gltf arm.glb\n"
               "  scripts/fit.sh problem=animation problem.path=my_arm\n"
               "Documented in docs/guide/formats.md and docs/guide/your-character.md.")
    parser.add_argument("folder", type=Path, nargs="?",
                        help="where to write the animation folder (replaced)")
    parser.add_argument("--frames-as-meshes", action="store_true",
                        help="write the frames as OBJ files frames/frame_NNN.obj (a glob in the "
                             "manifest) instead of one frames.npz")
    parser.add_argument("--usd", type=Path, help="also write the arm as a UsdSkel stage (.usda, "
                        ".usdc or .usd)")
    parser.add_argument("--gltf", type=Path, help="also write the arm as a glTF skin (.glb or "
                        ".gltf)")
    parser.add_argument("--n-frames", type=int, default=ArmShape.n_frames,
                        help="frames of the animation (default %(default)s); with "
                             "--max-flexion, another shot of the same arm")
    parser.add_argument("--max-flexion", type=float, default=ArmShape.max_flexion,
                        help="the elbow's largest bend in degrees (default %(default)s)")
    parser.add_argument("--float32-rest", action="store_true",
                        help="round the rest surface to float32 in every output (as USD and "
                             "glTF store it), so that the folder meshes like the files")
    parser.add_argument("--jiggle", type=float, default=0.0,
                        help="amplitude of keyframed secondary motion added to the folder's "
                             "frames (1: the lag of a 6 Hz oscillator; 0: none)")
    parser.add_argument("--jiggle-frequency", type=float, default=6.0, help="Hz (default 6)")
    parser.add_argument("--jiggle-damping", type=float, default=0.2,
                        help="damping ratio of the jiggle (default 0.2)")
    parser.add_argument("--fps", type=float, default=24.0,
                        help="frames per second written in the manifest (default 24)")
    args = parser.parse_args(argv)
    if args.folder is None and args.usd is None and args.gltf is None:
        parser.error("name a folder, --usd FILE or --gltf FILE")
    if args.n_frames < 2 or not 0.0 < args.max_flexion <= MAX_FLEXION:
        parser.error(f"--n-frames must be at least 2 and --max-flexion in (0, {MAX_FLEXION:g}] "
                     "degrees")
    if args.folder is not None:
        try:                         # before any file is written: a user's folder is never replaced
            check_replaceable(args.folder)
        except AnimationError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
    shape = ArmShape(n_frames=args.n_frames, max_flexion=args.max_flexion)
    data = arm_animation(shape)
    if args.float32_rest:
        data["rest_vertices"] = data["rest_vertices"].astype(np.float32).astype(np.float64)
    shapes, shape_weights = corrective_shapes(shape, data["rest_vertices"], data["angles"])
    for option, module, function in ((args.usd, "formats.usd.writer", "write_skinned_usd"),
                                     (args.gltf, "formats.gltf.writer", "write_skinned_gltf")):
        if option is not None:
            import importlib

            write = getattr(importlib.import_module(f"torchfit.mesh.{module}"), function)
            write(option, data["rest_vertices"], data["faces"], data["skeleton"], shapes,
                  shape_weights)
            print(f"wrote {option}")
    if args.folder is None:
        return 0
    if args.jiggle < 0 or args.jiggle_frequency <= 0 or not 0 <= args.jiggle_damping < 1 \
            or args.fps <= 0:
        parser.error("--jiggle must be >= 0, --jiggle-frequency and --fps > 0, "
                     "--jiggle-damping in [0, 1)")
    frames = data["frames"]
    if args.jiggle > 0:
        frames = keyframed_jiggle(frames, flesh_weights(shape, data["rest_vertices"]), args.fps,
                                  args.jiggle, args.jiggle_frequency, args.jiggle_damping)
    manifest = write_animation(args.folder, data["rest_vertices"], data["faces"],
                               frames, skeleton=data["skeleton"], fps=args.fps,
                               description="the procedural arm of torchfit's arm3d problem" + (
                                   f" with keyframed jiggle {args.jiggle:g}" if args.jiggle
                                   else ""))
    if args.frames_as_meshes:
        import trimesh
        import yaml

        folder = args.folder / "frames"
        folder.mkdir()
        for f, positions in enumerate(frames):
            trimesh.Trimesh(positions, data["faces"], process=False).export(
                str(folder / f"frame_{f:03d}.obj"))
        (args.folder / "frames.npz").unlink()
        spec = yaml.safe_load(manifest.read_text())
        spec["frames"] = "frames/frame_*.obj"
        manifest.write_text(yaml.safe_dump(spec, sort_keys=False))
    n_frames, n_vertices = data["frames"].shape[:2]
    print(f"wrote {manifest}: {n_vertices} surface vertices, {n_frames} frames, "
          f"{len(data['skeleton'].names)} bones; elbow angles "
          f"{np.round(data['angles']).astype(int).tolist()} (frame by frame)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
