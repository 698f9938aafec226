"""Rigs built in Blender and exported by its own USD and glTF exporters, read by torchfit.

Blender runs in a subprocess (:mod:`helpers.blender_rigs`; under a second a job). Skipped
where ``bpy`` (the extra ``blender``) is not installed.
"""
from __future__ import annotations

import numpy as np
import pytest

from helpers.blender_rigs import LENGTH, RADIUS, blender_available, run_blender

pytestmark = pytest.mark.skipif(not blender_available(),
                                reason="needs Blender as a module (the extra blender)")

pytest.importorskip("pxr")
pytest.importorskip("pygltflib")


def z_up(points: np.ndarray) -> np.ndarray:
    """glTF's Y-up coordinates in Blender's Z-up world (Blender's exporter: (x, z, -y))."""
    return np.stack([points[..., 0], -points[..., 2], points[..., 1]], axis=-1)


@pytest.fixture(scope="module")
def limb(tmp_path_factory):
    folder = tmp_path_factory.mktemp("limb")
    result = run_blender({"kind": "limb", "seams": True, "split": True, "usd": "limb.usda",
                          "meters_per_unit": 0.01, "glb": "limb.glb", "skinned_points": True},
                         folder)
    return folder, result


def test_a_split_limb_from_blender_reads_as_blender_skins_it(limb):
    from torchfit.mesh.formats import read_animation

    folder, result = limb
    blender = np.load(result["skinned"])["frames"]                  # (F, V_blender, 3), metres
    usd = read_animation(folder / "limb.usda")
    glb = read_animation(folder / "limb.glb")
    # Z-up USD in centimetres: metres, Blender's own vertices (split at the seams), its frames
    assert usd.n_file_vertices == result["vertices"] == blender.shape[1]
    assert np.abs(usd.file_points(usd.frames) - blender).max() < 1e-6
    # both files hold the seams split (563 vertices); welded, both are the closed surface
    assert glb.n_file_vertices == usd.n_file_vertices > usd.n_vertices
    assert glb.n_vertices == usd.n_vertices == 16 * 31 + 2
    assert usd.warnings == [] and glb.warnings == []                # closed: no warning
    order = np.lexsort(usd.rest_vertices.T)
    other = np.lexsort(z_up(glb.rest_vertices).T)
    assert np.abs(usd.frames[:, order] - z_up(glb.frames)[:, other]).max() < 1e-6
    # the end bone carries a third of the limb: the limb's end is flat (a capped tube), so
    # its bone reaches the tip, as Blender's bone does; the same rig from either file
    for animation, tail in ((usd, usd.skeleton.tails[2]), (glb, z_up(glb.skeleton.tails[2]))):
        assert animation.skeleton.names == ["upper", "lower", "end"]
        assert np.allclose(tail, [LENGTH, 0, 0], atol=2e-3)
        assert animation.skeleton.origin["lengths"][2].endswith("(a flat end)")
    assert glb.skeleton.attach_radius == pytest.approx(usd.skeleton.attach_radius, rel=1e-6)


def test_a_hand_with_two_fingers_has_a_bone_per_finger_joint(tmp_path):
    from torchfit.mesh.formats import read_animation

    result = run_blender({"kind": "hand", "usd": "hand.usda", "glb": "hand.glb"}, tmp_path)
    assert result["groups"] == ["palm", "a1", "a2", "b1", "b2"]
    for name in ("hand.usda", "hand.glb"):
        animation = read_animation(tmp_path / name)
        skeleton = animation.skeleton
        assert skeleton.names == ["palm->a1", "palm->b1", "a1", "a2", "b1", "b2"]
        lengths = np.linalg.norm(skeleton.tails - skeleton.heads, axis=1)
        assert (lengths > 0.03).all()                                 # fingertips included
        assert animation.warnings == []
