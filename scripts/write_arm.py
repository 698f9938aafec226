#!/usr/bin/env python
"""Write the procedural arm of ``problem=arm3d`` as an animation folder (the worked example
of README's "Bring your own animation").

    .venv/bin/python scripts/write_arm.py my_arm            # 48 frames, skeleton-driven
    .venv/bin/python scripts/write_arm.py my_arm --frames-as-meshes
    scripts/fit.sh problem=animation problem.path=my_arm

The folder holds ``animation.yaml`` (the manifest), ``rest.obj``, the frames (``frames.npz``
or ``frames/frame_000.obj`` ...), ``skeleton.npz`` (bone heads, tails and per-frame
``[A | t]`` transforms) and ``weights.npy`` (skinning weights per rest vertex).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torchfit.mesh import ArmShape, arm_animation, write_animation  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, help="where to write the animation (replaced)")
    parser.add_argument("--frames-as-meshes", action="store_true",
                        help="write the frames as OBJ files frames/frame_NNN.obj (a glob in the "
                             "manifest) instead of one frames.npz")
    args = parser.parse_args(argv)
    shape = ArmShape()
    data = arm_animation(shape)
    manifest = write_animation(args.folder, data["rest_vertices"], data["faces"],
                               data["frames"], skeleton=data["skeleton"],
                               description="the procedural arm of torchfit's arm3d problem")
    if args.frames_as_meshes:
        import trimesh
        import yaml

        folder = args.folder / "frames"
        folder.mkdir()
        for f, positions in enumerate(data["frames"]):
            trimesh.Trimesh(positions, data["faces"], process=False).export(
                str(folder / f"frame_{f:03d}.obj"))
        (args.folder / "frames.npz").unlink()
        spec = yaml.safe_load(manifest.read_text())
        spec["frames"] = "frames/frame_*.obj"
        manifest.write_text(yaml.safe_dump(spec, sort_keys=False))
    n_frames, n_vertices = data["frames"].shape[:2]
    print(f"wrote {manifest}: {n_vertices} surface vertices, {n_frames} frames, "
          f"{len(data['skeleton'].names)} bones; elbow angles "
          f"{np.round(data['angles'][[0, 11, 23, 35, 47]]).astype(int).tolist()} (frames 0, 11, "
          "23, 35, 47)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
