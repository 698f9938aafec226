"""problem.path dispatch by suffix (torchfit.mesh.formats.readers)."""
from __future__ import annotations

import pytest

from helpers.capsule_animation import write_capsule
from torchfit.mesh.formats.folder import AnimationError
from torchfit.mesh.formats.readers import read_animation


def test_a_folder_reads_as_before_and_refuses_usd_and_gltf_settings(tmp_path):
    folder = write_capsule(tmp_path / "c")
    assert read_animation(folder).n_frames == 3
    with pytest.raises(AnimationError, match="problem.prim applies to USD or glTF"):
        read_animation(folder, prim="/Root/Mesh")
    with pytest.raises(AnimationError, match="problem.fps applies to USD or glTF"):
        read_animation(folder, fps=24.0)


def test_suffixes_pick_the_reader(tmp_path):
    pytest.importorskip("pxr")
    pytest.importorskip("pygltflib")
    with pytest.raises(AnimationError, match="no such USD file"):
        read_animation(tmp_path / "a.USDA")
    with pytest.raises(AnimationError, match="no such glTF file"):
        read_animation(tmp_path / "a.glb")
    with pytest.raises(AnimationError, match="problem.fps applies to glTF files only"):
        read_animation(tmp_path / "a.usdc", fps=30.0)
