"""USD stages built in code, read by torchfit.mesh.formats.usd.reader, against a hand-written skinning."""
from __future__ import annotations

import sys

import numpy as np
import pytest

from torchfit.mesh.formats.folder import AnimationError
from torchfit.mesh.rig import blend

pytest.importorskip("pxr")

from helpers.skinned_files import (METRES_PER_UNIT, expected_tube, rotate,  # noqa: E402
                           write_point_cache_usd, write_tube_usd)
from torchfit.mesh.formats.usd.reader import load_usd  # noqa: E402


def test_skinned_tube_poses_as_a_hand_written_linear_blend_skinning(tmp_path):
    written = write_tube_usd(tmp_path / "tube.usda")
    rest, frames = expected_tube(written["points"], written["rig"])
    animation = load_usd(tmp_path / "tube.usda")
    assert animation.unit == METRES_PER_UNIT
    assert animation.frames.shape == (3, 48, 3)
    assert np.abs(animation.rest_vertices - rest).max() < 1e-8
    assert np.abs(animation.frames - frames).max() < 1e-7     # float32 points, quaternions
    assert np.abs(frames[2] - frames[0]).max() > 0.05          # the bend moves the far end
    # quads as fans from their first vertex, winding kept
    quads = written["quads"]
    assert animation.faces.tolist()[:2] == [quads[0, [0, 1, 2]].tolist(),
                                            quads[0, [0, 2, 3]].tolist()]
    assert [f.rsplit("@", 1)[1] for f in animation.frame_files] == ["1", "2", "4"]
    skeleton = animation.skeleton
    assert skeleton.names == ["A", "B"]                          # the tip has no weight
    bind = written["rig"]["bind"]
    joint = lambda j: (np.array([0, 5, 0]) + bind[j][:3, 3]) * METRES_PER_UNIT  # noqa: E731
    assert np.allclose(skeleton.heads, [joint(0), joint(1)]) and np.allclose(
        skeleton.tails, [joint(1), joint(2)])
    # the bones' transforms and weights skin the rest to the frames
    assert np.abs(blend(animation.rest_vertices, skeleton.weights, skeleton.transforms)
                  - frames).max() < 1e-7
    assert np.allclose(skeleton.weights[:, ::-1], written["rig"]["weights"], atol=1e-7)
    # no torchfit:attachRadius: 0.4 x the median distance of the surface to a bone
    assert skeleton.attach_radius == pytest.approx(0.4 * 0.02, rel=0.05)


def test_constant_interpolation_binds_every_point_to_one_joint(tmp_path):
    written = write_tube_usd(tmp_path / "rigid.usda", interpolation="constant")
    animation = load_usd(tmp_path / "rigid.usda")
    rig = written["rig"]
    skin_b = [rig["local"][k][0] @ rig["local"][k][1] @ np.linalg.inv(rig["bind"][1])
              for k in range(3)]
    hom = np.concatenate([written["points"], np.ones((48, 1))], 1) @ rig["geom_bind"].T
    want = np.stack([(hom @ m.T @ rig["skeleton_xform"].T)[:, :3] for m in skin_b]) * 0.01
    assert np.abs(animation.frames - want).max() < 1e-7
    assert np.allclose(animation.skeleton.weights.sum(1), 1.0)
    assert animation.skeleton.weights[:, 0].max() == 0.0        # bone A carries nothing


def test_point_cache_reads_frames_driven_points_and_units(tmp_path):
    written = write_point_cache_usd(tmp_path / "cache.usda")
    animation = load_usd(tmp_path / "cache.usda")
    assert animation.skeleton is None
    offset = np.array([0, 0, 10.0])
    assert np.abs(animation.frames - (written["frames"] + offset) * 1e-3).max() < 1e-9
    assert np.abs(animation.rest_vertices - (written["points"] + offset) * 1e-3).max() < 1e-9
    assert animation.driven.indices.tolist() == list(range(8))
    assert animation.driven.tolerance == pytest.approx(0.5e-3)
    write_point_cache_usd(tmp_path / "default.usda", tolerance=None)
    tube = load_usd(tmp_path / "default.usda")
    edges = tube.rest_vertices[tube.faces] - tube.rest_vertices[np.roll(tube.faces, 1, 1)]
    assert tube.driven.tolerance == pytest.approx(np.linalg.norm(edges, axis=-1).mean())


def test_prim_setting_chooses_between_two_skinned_meshes(tmp_path):
    write_tube_usd(tmp_path / "two.usda", extra_mesh=True)
    with pytest.raises(AnimationError, match=r"2 skinned meshes .*problem\.prim") as info:
        load_usd(tmp_path / "two.usda")
    assert "\n" not in str(info.value)
    assert load_usd(tmp_path / "two.usda", "/Root/Other").frame_files[0].endswith(
        "/Root/Other@1")
    with pytest.raises(AnimationError, match="/Root/Nope is neither"):
        load_usd(tmp_path / "two.usda", "/Root/Nope")


@pytest.mark.parametrize("case, message", [
    ("static", "no skinned mesh"),
    ("weights", "the weights must match the points"),
    ("undriven", "primvars:torchfit:driven"),
])
def test_bad_stages_are_one_line(tmp_path, case, message):
    path = tmp_path / f"{case}.usda"
    if case == "static":
        from pxr import Usd, UsdGeom

        stage = Usd.Stage.CreateNew(str(path))
        UsdGeom.Mesh.Define(stage, "/Still").CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
        stage.GetRootLayer().Save()
    elif case == "weights":
        write_tube_usd(path, weights_per_point=40)
    else:
        write_point_cache_usd(path, driven=False)
    with pytest.raises(AnimationError, match=message) as info:
        load_usd(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_a_missing_extra_names_it(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pxr", None)
    with pytest.raises(AnimationError, match=r"optional extra 'usd'.*torchfit\[usd\]"):
        load_usd(tmp_path / "any.usda")


def test_rotate_helper_is_a_rotation():
    assert np.allclose(rotate("z", 90)[:3, :3] @ [1, 0, 0], [0, 1, 0])


@pytest.mark.parametrize("name, content", [("junk.usda", bytes(range(256)) * 2),
                                           ("field.npy", b"\x93NUMPY\x01\x00v\x00{'descr'")])
def test_a_file_that_is_not_a_stage_is_one_line_for_the_animation_and_the_layer(
        tmp_path, name, content):
    """Issue 50: random bytes or a .npy as problem.init_field gave a 25-line pxr traceback;
    the animation reader and the material layer's reader both say it in one line."""
    from torchfit.mesh.formats.usd import read_modulus_layer

    path = tmp_path / name
    path.write_bytes(content)
    for read in (load_usd, read_modulus_layer):
        with pytest.raises(AnimationError, match="cannot open it as a USD stage") as info:
            read(path)
        text = str(info.value)
        assert "\n" not in text and text.startswith(str(path)) and "Error in" not in text
        assert text.endswith("give a USD file (.usd, .usda, .usdc)")


def test_a_third_party_tube_stage_derives_the_folders_rig_and_says_so(tmp_path):
    """The rigged tube as a UsdSkel stage with joints only (no end joint, no length, no
    radius): the reader's bones, lengths and attach radius are the folder's authored ones."""
    from helpers.rigged_tube import tube_animation, write_tube_stage

    authored = tube_animation("x", bulge=0.0)
    animation = load_usd(write_tube_stage(tmp_path / "tube.usda"))
    skeleton, folder = animation.skeleton, authored["skeleton"]
    assert skeleton.names == ["base", "tip"]
    assert np.abs(animation.frames - authored["frames"]).max() < 1e-6
    assert np.abs(skeleton.heads - folder.heads).max() < 1e-6
    assert np.abs(skeleton.tails - folder.tails).max() < 2e-3 * 0.25   # within 0.2 %
    assert skeleton.attach_radius == pytest.approx(folder.attach_radius, rel=0.01)
    assert skeleton.origin["lengths"][0] == "authored: the joint to its child joint"
    assert skeleton.origin["lengths"][1].startswith("derived: the extent of the vertices its "
                                                    "weights dominate along its axis less the "
                                                    "rounded end's radius 0.05 m")
    assert skeleton.origin["attach_radius"].startswith("derived: 0.4 x the median distance")


def test_a_stage_with_every_joint_at_the_origin_is_refused_though_it_skins(tmp_path, monkeypatch):
    from helpers.rigged_tube import tube_animation, write_tube_stage
    from torchfit.mesh.formats import joints

    path = write_tube_stage(tmp_path / "origin.usda", at_origin=True)
    with pytest.raises(AnimationError) as err:
        load_usd(path)
    assert str(err.value) == (
        f"{path}:/Root/Tube: joints base, tip coincide (all at (0, 0, 0) m in the rest pose), "
        "so their bones have no length and hold no flesh; the skinning may still reproduce "
        "the frames, but the bind transforms must place each joint where it bends (in the "
        "DCC: apply the armature's rest pose and re-export)")
    # a valid stage: with the placement checks off its skinning gives the tube's frames
    monkeypatch.setattr(joints, "check_joint_placement", lambda *args: None)
    monkeypatch.setattr(joints, "check_bone_placement", lambda *args: None)
    animation = load_usd(path)
    assert np.abs(animation.frames - tube_animation("x", bulge=0.0)["frames"]).max() < 1e-6
