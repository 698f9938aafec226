"""Files torchfit does not read, told apart by their first bytes (torchfit.mesh.formats.sniff):
FBX, Alembic, a bare OBJ/PLY/STL and a file whose suffix lies are refused with one line
naming the absolute path, what the file is and what to export instead."""
from __future__ import annotations

import os
import struct
import subprocess
import sys
from pathlib import Path

import pytest
import trimesh

from helpers.capsule_animation import write_capsule
from torchfit.mesh.formats.folder import AnimationError, load_animation
from torchfit.mesh.formats.readers import read_animation
from torchfit.mesh.formats.sniff import refusal, sniff
from torchfit.problems import build_problem
from torchfit.problems.config import ProblemConfigError

REPO = Path(__file__).resolve().parents[3]
FBX_BINARY = b"Kaydara FBX Binary  \x00\x1a\x00" + struct.pack("<I", 7400) + b"\x00" * 64
EXPORT_WORDS = ("USD", "UsdSkel", "glTF 2.0", "Blender: File > Export > Universal Scene "
                "Description", "Maya", "docs/guide/formats.md")


def fake_files(folder: Path) -> dict[str, tuple[Path, str]]:
    """name -> (file, the words saying what it is): fake magic bytes and real meshes."""
    folder.mkdir(parents=True, exist_ok=True)
    files = {
        "fbx": ("shot.fbx", FBX_BINARY, "a binary FBX file (FBX 7.4)"),
        "fbx_ascii": ("shot_ascii.fbx", b"; FBX 7.5.0 project file\n; ---\nFBXHeaderExtension: {\n",
                      "an ASCII FBX file (FBX 7.5.0 project file)"),
        "alembic": ("shot.abc", b"Ogawa\xff\x00\x01" + b"\x00" * 32,
                    "an Alembic archive (Ogawa)"),
        "alembic_hdf5": ("old.abc", b"\x89HDF\r\n\x1a\n" + b"\x00" * 32,
                         "an Alembic archive (HDF5)"),
        "lying_usda": ("shot.usda", FBX_BINARY, "a binary FBX file"),
        "lying_glb": ("crate.glb", b"PXR-USDC" + b"\x00" * 64,
                      "a binary USD file (crate, PXR-USDC) but its suffix '.glb'"),
        "lying_usdc": ("skin.usdc", b"glTF" + struct.pack("<II", 2, 80) + b"\x00" * 64,
                       "a binary glTF file (glTF 2) but its suffix '.usdc'"),
    }
    out = {}
    for name, (file, data, what) in files.items():
        (folder / file).write_bytes(data)
        out[name] = (folder / file, what)
    box = trimesh.creation.box()
    for suffix, what in (("obj", "an OBJ mesh"), ("ply", "a PLY mesh"),
                         ("stl", "a binary STL mesh")):
        box.export(str(folder / f"body.{suffix}"))
        out[suffix] = (folder / f"body.{suffix}", what)
    return out


def test_each_kind_is_named_with_what_to_export(tmp_path):
    for name, (path, what) in fake_files(tmp_path).items():
        with pytest.raises(AnimationError) as info:
            read_animation(path)
        message = str(info.value)
        assert "\n" not in message and message.startswith(f"{path.absolute()} is {what}"), \
            (name, message)
        if not name.startswith("lying_") or name == "lying_usda":
            assert all(w in message for w in EXPORT_WORDS), (name, message)
    # the suffix lies: the rename that makes it readable
    assert "rename it to end in .usd" in str(pytest.raises(
        AnimationError, read_animation, tmp_path / "crate.glb").value)
    # the folder reader, given the file itself as its manifest, says the same
    with pytest.raises(AnimationError, match="is a binary FBX file"):
        load_animation(tmp_path / "shot.fbx")


def test_readable_files_still_read(tmp_path):
    folder = write_capsule(tmp_path / "c")
    assert sniff(folder / "animation.yaml").reader == "folder"
    assert read_animation(folder / "animation.yaml").n_frames == 3
    assert read_animation(folder).n_frames == 3


def test_build_problem_names_problem_path_absolute(tmp_path, monkeypatch):
    files = fake_files(tmp_path / "in")
    monkeypatch.chdir(tmp_path / "in")
    for name in ("fbx", "alembic", "obj"):
        with pytest.raises(ProblemConfigError) as info:
            build_problem("animation", {"path": files[name][0].name,
                                        "cache_dir": str(tmp_path / "cache")})
        message = str(info.value)
        assert message.startswith(f"problem.path={files[name][0].absolute()}: is "
                                  f"{files[name][1]}"), message
        assert "USD" in message and "glTF" in message
    assert not (tmp_path / "cache").exists()


def test_fbx_is_refused_by_the_fit_app(tmp_path):
    files = fake_files(tmp_path / "in")
    run = tmp_path / "run"
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    proc = subprocess.run([sys.executable, "experiments/fit.py", f"hydra.run.dir={run}",
                           "problem=animation", f"problem.path={files['fbx'][0]}",
                           f"problem.cache_dir={tmp_path / 'cache'}"], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120)
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and len(errors) == 1, proc.stderr[-3000:]
    assert errors[0].startswith(f"error: problem.path={files['fbx'][0]}: is a binary FBX file")
    assert all(w in errors[0] for w in EXPORT_WORDS)
    assert not run.exists() and not (tmp_path / "cache").exists()


@pytest.mark.parametrize("name, content, words", [
    ("shot.fbx", b"", "is an empty file"),
    ("shot.usda", b"", "is an empty file"),
    ("shot.fbx", b"unit: 1.0\nrest: rest.obj\n", "ends in '.fbx' but is a text file, not an FBX"),
    ("shot.abc", b"\x01\x02\x00\x03", "ends in '.abc' but is a binary file, not an Alembic"),
])
def test_an_empty_or_misnamed_file_is_not_read_as_a_manifest(tmp_path, name, content, words):
    """Issue 50: an empty .fbx was read as a manifest ("missing entry 'rest'")."""
    path = tmp_path / name
    path.write_bytes(content)
    line = refusal(path)
    assert line is not None and words in line and "\n" not in line
    assert line.startswith(str(path.absolute()))
