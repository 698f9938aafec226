"""scripts/convert.sh (torchfit.mesh.formats.convert): any of the three formats to any other,
positions within 1e-6 m after round trips, refusals as one line with nothing written."""
from __future__ import annotations

import errno
import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers.capsule_animation import write_capsule
from helpers.rigged_tube import tube_animation
from torchfit.mesh import write_animation
from torchfit.mesh.formats.convert import main
from torchfit.mesh.formats.readers import read_animation
from torchfit.mesh.rig import blend
from torchfit.problems.body.procedural_arm import ArmShape, arm_animation

pytest.importorskip("pxr")
pytest.importorskip("pygltflib")
REPO = Path(__file__).resolve().parents[3]
TOL = 1e-6


def write_arm(folder: Path) -> Path:
    data = arm_animation(ArmShape())
    write_animation(folder, data["rest_vertices"], data["faces"], data["frames"],
                    skeleton=data["skeleton"])
    return folder


def write_y_tube(folder: Path) -> Path:
    """The two-bone tube along y (Y up), with a bulge the skinning does not explain."""
    data = tube_animation("y", count=12)
    write_animation(folder, data["rest"], data["faces"], data["frames"],
                    skeleton=data["skeleton"])
    return folder


def converted(source: Path, out: Path, *options: str, capsys=None) -> Path:
    assert main([str(source), str(out), *options]) == 0
    return out


def assert_same(a, b, rig: bool = True) -> None:
    assert a.rest_vertices.shape == b.rest_vertices.shape and a.faces.shape == b.faces.shape
    assert np.abs(a.rest_vertices - b.rest_vertices).max() < TOL
    assert np.abs(a.frames - b.frames).max() < TOL
    assert (a.faces == b.faces).all()
    if rig:       # the skinning of either rig moves the rest surface alike
        skinned = [blend(x.rest_vertices, x.skeleton.weights, x.skeleton.transforms)
                   for x in (a, b)]
        assert np.abs(skinned[0] - skinned[1]).max() < TOL
        assert a.skeleton.attach_radius == pytest.approx(b.skeleton.attach_radius, rel=1e-6)


def test_the_arm_folder_usd_gltf_folder(tmp_path, capsys):
    source = write_arm(tmp_path / "arm")
    usd = converted(source, tmp_path / "arm.usda")
    assert "2 blend shapes" in capsys.readouterr().out     # the bicep and tricep correctives
    glb = converted(usd, tmp_path / "arm.glb")
    back = converted(glb, tmp_path / "back")
    original = read_animation(source)
    for path in (usd, glb, back):
        assert_same(original, read_animation(path))
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(usd))
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0 and stage.GetTimeCodesPerSecond() == 24
    assert UsdGeom.GetStageUpAxis(stage) == "Z"


def test_the_y_up_tube_folder_gltf_usd_folder_and_fps(tmp_path):
    source = write_y_tube(tmp_path / "tube")
    glb = converted(source, tmp_path / "tube.glb", "--fps", "30")
    usd = converted(glb, tmp_path / "tube.usdc")            # glTF is Y up: the stage says so
    back = converted(usd, tmp_path / "back")
    original = read_animation(source)
    for path in (glb, usd, back):
        assert_same(original, read_animation(path))
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(usd))
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and stage.GetTimeCodesPerSecond() == 30
    assert "at 30 fps" in (back / "animation.yaml").read_text()
    # USD to glTF directly, and folder to folder
    assert_same(original, read_animation(converted(usd, tmp_path / "direct.gltf")))
    assert_same(original, read_animation(converted(source, tmp_path / "copy")))


def test_seams_are_written_as_the_file_has_them(tmp_path):
    data = tube_animation("y", count=12)
    rest, faces, skeleton = data["rest"], data["faces"].copy(), data["skeleton"]
    # split the vertices of the faces on the +x side (a UV seam): copies at one position
    side = np.flatnonzero(rest[faces].mean(1)[:, 0] > rest[:, 0].mean())
    split = np.unique(faces[side])
    copy = {int(v): len(rest) + k for k, v in enumerate(split)}
    faces[side] = np.vectorize(copy.get)(faces[side])
    import dataclasses

    skeleton = dataclasses.replace(skeleton, weights=np.concatenate(
        [skeleton.weights, skeleton.weights[split]]))
    write_animation(tmp_path / "split", np.concatenate([rest, rest[split]]), faces,
                    np.concatenate([data["frames"], data["frames"][:, split]], axis=1),
                    skeleton=skeleton)
    glb = converted(tmp_path / "split", tmp_path / "split.glb")
    folder = converted(glb, tmp_path / "back")
    for path in (glb, folder):
        file = read_animation(path, weld=False)
        assert file.n_vertices == len(rest) + len(split)          # as the input had them
        welded = read_animation(path)
        assert welded.n_vertices == len(rest)
        assert_same(read_animation(tmp_path / "split"), welded)


def test_a_point_cache_converts_to_usd_and_back(tmp_path, capsys):
    source = write_capsule(tmp_path / "cache", mode="driven")
    usd = converted(source, tmp_path / "cache.usda")
    back = converted(usd, tmp_path / "back")
    original = read_animation(source)
    for path in (usd, back):
        again = read_animation(path)
        assert_same(original, again, rig=False)
        assert (again.driven.mask == original.driven.mask).all()
        assert again.driven.tolerance == pytest.approx(original.driven.tolerance)
    # a glTF skin cannot hold it: one line, nothing written
    assert main([str(source), str(tmp_path / "cache.glb")]) == 2
    assert "a point cache (driven vertices, no rig)" in capsys.readouterr().err


def test_refusals_write_nothing(tmp_path, capsys):
    arm = write_arm(tmp_path / "arm")
    (tmp_path / "shot.fbx").write_bytes(b"Kaydara FBX Binary  \x00\x1a\x00" + b"\x00" * 40)
    data = tube_animation("x", count=8)
    weights = np.full((len(data["rest"]), 5), 0.2)                 # five influences
    skeleton = data["skeleton"]
    import dataclasses

    five = dataclasses.replace(skeleton, heads=np.repeat(skeleton.heads[:1], 5, 0),
                               tails=np.repeat(skeleton.tails[:1], 5, 0),
                               transforms=np.repeat(skeleton.transforms[:, :1], 5, 1),
                               weights=weights, names=[f"b{i}" for i in range(5)])
    write_animation(tmp_path / "five", data["rest"], data["faces"], data["frames"],
                    skeleton=five)
    cases = {
        "missing": ([str(tmp_path / "nothing"), str(tmp_path / "out.usda")],
                    "no such file or folder"),
        "fbx": ([str(tmp_path / "shot.fbx"), str(tmp_path / "out.usda")],
                "is a binary FBX file"),
        "usdz": ([str(arm), str(tmp_path / "out.usdz")], "not a .usdz package"),
        "itself": ([str(arm), str(arm)], "would overwrite the input"),
        "influences": ([str(tmp_path / "five"), str(tmp_path / "out.glb")],
                       "5 bone influences; a glTF skin holds four"),
        "fps": ([str(arm), str(tmp_path / "out.glb"), "--fps", "-3"], "positive frame rate"),
    }
    before = sorted(p.name for p in tmp_path.iterdir())
    for name, (argv, words) in cases.items():
        assert main(argv) == 2, name
        err = capsys.readouterr().err
        errors = [line for line in err.splitlines() if line.startswith("error: ")]
        assert len(errors) == 1 and words in errors[0], (name, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == before      # not even a temporary


def test_what_is_not_an_output_of_its_kind_is_never_replaced(tmp_path, capsys):
    """Issue 50: a user's folder (its notes were deleted), a plain file (it became a folder),
    a text file where a stage goes, a folder where a glTF goes: refused in one line before
    the input is read, every byte left as it was."""
    arm = write_arm(tmp_path / "arm")
    user = tmp_path / "userdir"
    user.mkdir()
    (user / "notes.txt").write_text("precious")
    (tmp_path / "plain").write_text("a plain file")
    (tmp_path / "notes.usda").write_text("not a stage")
    (tmp_path / "folder.glb").mkdir()
    cases = {user: "holds files torchfit did not write (notes.txt)",
             tmp_path / "plain": "exists and is not a folder",
             tmp_path / "notes.usda": "exists and is not a USD stage",
             tmp_path / "folder.glb": "is a folder; a glTF file would replace it"}

    def state():
        return sorted((str(p.relative_to(tmp_path)), p.read_bytes() if p.is_file() else b"")
                      for p in tmp_path.rglob("*"))

    before = state()
    for out, words in cases.items():
        assert main([str(arm), str(out)]) == 2
        errors = [line for line in capsys.readouterr().err.splitlines() if line]
        assert len(errors) == 1 and errors[0].startswith("error: ") and words in errors[0], \
            (out, errors)
    assert state() == before


def test_an_output_of_its_kind_is_replaced_and_the_folder_is_the_users(tmp_path):
    """A stage over a stage, a folder over an animation folder torchfit wrote, an empty
    folder: replaced; the written folder has a plain mkdir's mode (it was 0700)."""
    arm = write_arm(tmp_path / "arm")
    converted(arm, tmp_path / "out.usda")
    converted(arm, tmp_path / "out.usda")
    (tmp_path / "empty").mkdir()
    for folder in (tmp_path / "copy", tmp_path / "copy", tmp_path / "empty"):
        converted(tmp_path / "out.usda", folder)
        assert_same(read_animation(folder, weld=False), read_animation(arm, weld=False))
        mask = os.umask(0)
        os.umask(mask)
        assert (folder.stat().st_mode & 0o777) == 0o777 & ~mask
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize("out", ["full.usda", "full.glb", "full_folder"])
def test_a_write_that_fails_is_one_line_and_leaves_nothing(tmp_path, out):
    """A file-size limit (``ulimit -f``: EFBIG, what a full disk does to a write) while
    writing each kind: one ``error:`` line that says what to do, exit 2, no traceback (USD
    printed 40 lines of C++ errors), no output and no temporary left."""
    import resource

    arm = write_arm(tmp_path / "arm")
    work = tmp_path / "work"
    work.mkdir()
    limit = 64 * 1024                      # the arm's files are several times larger

    def small_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    proc = subprocess.run([sys.executable, "-m", "torchfit.mesh.formats.convert", str(arm),
                           str(work / out)], capture_output=True, text=True, timeout=300,
                          preexec_fn=small_files, cwd=REPO,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"error: cannot write {work / out}: File "
                                                   "too large; raise the file-size limit"), lines
    assert list(work.iterdir()) == []


def test_a_usd_write_failure_becomes_the_oserror_it_reports():
    from torchfit.errors import write_failure, write_failure_line

    class ErrorException(Exception):           # the shape of pxr.Tf.ErrorException
        pass

    usd = ErrorException("\n\tError in 'ArFilesystemWritableAsset::Write' at line 78: 'Error "
                         "occurred writing file: No space left on device'\n" * 40)
    assert write_failure(RuntimeError("saving")) is None
    failure = write_failure(usd)
    assert failure is not None and failure.errno == errno.ENOSPC
    assert write_failure_line(failure, "x.usda") == ("cannot write x.usda: No space left on "
                                                     "device; free space there")
    assert write_failure(ValueError("not a write")) is None
    try:
        try:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), "out.glb")
        except OSError as inner:
            raise RuntimeError("while converting") from inner
    except RuntimeError as outer:
        assert write_failure(outer).filename == "out.glb"


def test_convert_sh_help(tmp_path):
    """The wrapper sources scripts/_venv.sh and runs the module (a stand-in environment
    whose install stamp is current, so that nothing is installed)."""
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    (venv / "bin" / "python").write_text(f"#!/bin/sh\nexec {sys.executable} \"$@\"\n")
    (venv / "bin" / "python").chmod(0o755)
    extras = "none"
    stamp = hashlib.sha256((REPO / "pyproject.toml").read_bytes()
                           + (REPO / "constraints.txt").read_bytes()
                           + f"{extras} 0\n".encode()).hexdigest()
    (venv / ".torchfit-install").write_text(stamp + "\n")
    env = {**os.environ, "TORCHFIT_VENV": str(venv), "TORCHFIT_EXTRAS": extras,
           "TORCHFIT_BLENDER": "0", "PYTHONPATH": str(REPO)}
    proc = subprocess.run(["bash", str(REPO / "scripts" / "convert.sh"), "--help"], env=env,
                          capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "[torchfit] installing" not in proc.stderr
    for words in ("folder format", "UsdSkel", "glTF", "--prim", "--fps", "--up-axis",
                  ".usd/.usda/.usdc"):
        assert words in proc.stdout, words


@pytest.mark.slow
def test_a_conversion_opens_in_blender(tmp_path):
    from helpers.blender_rigs import blender_available, run_blender

    if not blender_available():
        pytest.skip("Blender (bpy, the extra blender) is not installed")
    source = write_y_tube(tmp_path / "tube")
    glb = converted(source, tmp_path / "tube.glb")
    usd = converted(glb, tmp_path / "tube.usda")
    original = read_animation(source)
    frames = [0, 2, 4]
    back = run_blender({"kind": "reimport", "path": str(usd), "frames": frames},
                       tmp_path / "blender")
    (mesh,) = back["meshes"]
    assert mesh["vertices"] == original.n_vertices and "ARMATURE" in mesh["modifiers"]
    points = np.load(back["npz"])[f"{mesh['name']}|points"]
    # Blender stands the Y-up stage up (Z up): compare shapes after undoing its rotation
    rotate = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])            # Y up -> Z up
    expected = original.frames[frames] @ rotate.T
    assert np.abs(points - expected).max() < 1e-5
    assert np.abs(points[2] - points[0]).max() > 0.05                  # it bends


def test_the_read_back_tolerance_scales_with_the_body(tmp_path):
    """Issue 50: a stage 1.07e-6 m off was refused against a fixed 1e-6 m; float32 storage
    is relative. The arm scaled to 40 m (a building-sized creature) converts both ways."""
    from torchfit.mesh.formats.convert import check_tolerance

    data = arm_animation(ArmShape())
    scale = 40.0 / np.ptp(data["frames"][..., 2])
    skeleton = data["skeleton"]
    import dataclasses

    transforms = skeleton.transforms.copy()
    transforms[..., 3] *= scale
    big = dataclasses.replace(skeleton, heads=skeleton.heads * scale, tails=skeleton.tails * scale,
                              transforms=transforms, attach_radius=skeleton.attach_radius * scale)
    write_animation(tmp_path / "giant", data["rest_vertices"] * scale, data["faces"],
                    data["frames"] * scale, skeleton=big)
    giant = read_animation(tmp_path / "giant", weld=False)
    assert check_tolerance(giant) == pytest.approx(1e-6 * np.linalg.norm(np.ptp(
        np.concatenate([giant.rest_vertices[None], giant.frames]).reshape(-1, 3), axis=0)))
    assert check_tolerance(read_animation(write_arm(tmp_path / "arm"), weld=False)) == 1e-6
    for out in ("giant.usda", "giant.glb"):
        converted(tmp_path / "giant", tmp_path / out)
        back = read_animation(tmp_path / out, weld=False)
        assert 1e-6 < np.abs(back.frames - giant.frames).max() <= check_tolerance(giant)
