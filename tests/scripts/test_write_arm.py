"""scripts/write_arm.py --usd / --gltf: the arm as a UsdSkel stage and a glTF skin reads back as
the folder format's arm (the worked example of issue 29)."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from torchfit.mesh import load_animation
from torchfit.problems.body.procedural_arm import ArmShape, arm_animation
from torchfit.mesh.formats.readers import read_animation

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "write_arm.py"


def write_arm():
    spec = importlib.util.spec_from_file_location("write_arm", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main


@pytest.mark.parametrize("option, name, extra", [("--usd", "arm.usda", "pxr"),
                                                 ("--usd", "arm.usdc", "pxr"),
                                                 ("--gltf", "arm.glb", "pygltflib")])
def test_the_arm_reads_back_as_the_folder_format(tmp_path, option, name, extra):
    pytest.importorskip(extra)
    assert write_arm()([str(tmp_path / "folder"), option, str(tmp_path / name)]) == 0
    folder = load_animation(tmp_path / "folder")
    other = read_animation(tmp_path / name)
    # float32 storage (points, offsets, quaternions): within 1e-7 m of the float64 frames
    assert np.abs(other.frames - folder.frames).max() < 1e-6
    assert np.abs(other.frames - arm_animation(ArmShape())["frames"]).max() < 1e-6
    assert np.abs(other.rest_vertices - folder.rest_vertices).max() < 1e-7
    assert other.faces.tolist() == folder.faces.tolist()
    a, b = other.skeleton, folder.skeleton
    assert a.names == b.names == ["upper_arm", "forearm"]
    assert a.attach_radius == pytest.approx(b.attach_radius, rel=1e-12)
    for key in ("heads", "tails", "transforms", "weights"):
        assert np.abs(getattr(a, key) - getattr(b, key)).max() < 1e-6, key
    # the correctives came through the blend shapes / morph targets: the bulge is there
    assert np.abs(other.frames[11] - folder.frames[11]).max() < 1e-6


def test_nothing_to_write_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as info:
        write_arm()([])
    assert info.value.code == 2 and "--usd" in capsys.readouterr().err


def test_a_users_folder_is_refused_before_anything_is_written(tmp_path, capsys):
    """Issue 50: write_arm replaced an existing folder whole; a folder holding the user's
    files is refused in one line, and neither it nor the --usd output is written."""
    user = tmp_path / "mine"
    user.mkdir()
    (user / "notes.txt").write_text("precious")
    assert write_arm()([str(user), "--usd", str(tmp_path / "arm.usda")]) == 2
    assert capsys.readouterr().err.startswith(f"error: {user} holds files torchfit did not "
                                              "write (notes.txt)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine"]
    assert [p.name for p in user.iterdir()] == ["notes.txt"]
    assert write_arm()([str(tmp_path / "arm"), "--n-frames", "3"]) == 0
    assert write_arm()([str(tmp_path / "arm"), "--n-frames", "4"]) == 0     # its own: replaced
    assert load_animation(tmp_path / "arm").n_frames == 4
