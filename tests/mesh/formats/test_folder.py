"""The animation folder format (torchfit.mesh.formats.folder): what the writer writes the
loader reads back, frames selected by number, and one line naming the file, frame or vertex
at fault for every bad input."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from helpers.capsule_animation import ANGLES, write_capsule
from torchfit.mesh import (AnimationError, DrivenSurface, MeshError, load_animation,
                           write_animation)


def edit_manifest(folder, change):
    path = folder / "animation.yaml"
    spec = yaml.safe_load(path.read_text())
    change(spec)
    path.write_text(yaml.safe_dump(spec))


def expect_error(folder, match):
    with pytest.raises(MeshError, match=match) as info:
        load_animation(folder)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("mode,frames_as", [("skeleton", "npz"), ("driven", "obj")])
def test_what_is_written_is_read_back(tmp_path, mode, frames_as):
    folder = write_capsule(tmp_path / "capsule", mode, frames_as)
    animation = load_animation(folder)
    assert animation.n_frames == len(ANGLES) and animation.frames.shape[1:] == \
        (animation.n_vertices, 3)
    assert np.allclose(animation.frames[0], animation.rest_vertices, atol=1e-12)  # 0 degrees
    if mode == "skeleton":
        assert animation.driven is None and animation.skeleton.n_bones == 2
        assert np.allclose(animation.skeleton.joints(), [[0.0, 0.0, 0.0]])
    else:
        assert animation.skeleton is None and 0 < animation.driven.indices.size < \
            animation.n_vertices
    selected = animation.select([2, 0])
    assert np.array_equal(selected.frames, animation.frames[[2, 0]])
    with pytest.raises(AnimationError, match="frame 5 does not exist"):
        animation.select([5])


def test_frame_with_another_vertex_count_names_the_file(tmp_path):
    folder = write_capsule(tmp_path / "c", "skeleton", "obj")
    import trimesh

    trimesh.creation.icosphere(subdivisions=1).export(str(folder / "frames" / "pose2.obj"))
    expect_error(folder, r"pose2\.obj: frame has 42 vertices but the rest surface has")


def test_nan_coordinate_names_frame_and_vertex(tmp_path):
    folder = write_capsule(tmp_path / "c", "skeleton", "npz")
    frames = np.load(folder / "frames.npz")["frames"]
    frames[2, 17, 1] = np.nan
    np.savez(folder / "frames.npz", frames=frames)
    expect_error(folder, r"frame 2 .*vertex 17 has a NaN or infinite coordinate")


def test_missing_files_and_manifest_keys(tmp_path):
    folder = write_capsule(tmp_path / "c", "skeleton", "npz")
    expect_error(tmp_path / "nowhere", "no animation manifest at")
    (folder / "rest.obj").rename(folder / "moved.obj")
    expect_error(folder, r"rest surface file .*rest\.obj does not exist")
    (folder / "moved.obj").rename(folder / "rest.obj")
    edit_manifest(folder, lambda s: s.update(colour="red"))
    expect_error(folder, r"unknown key 'colour' in the manifest")
    edit_manifest(folder, lambda s: (s.pop("colour"), s.pop("frames")))
    expect_error(folder, r"missing entry 'frames' in the manifest")


def test_driven_sets_empty_or_everything(tmp_path):
    folder = write_capsule(tmp_path / "c", "driven", "npz")
    n = len(np.load(folder / "frames.npz")["frames"][0])
    np.save(folder / "driven.npy", np.zeros(0, dtype=np.int64))
    expect_error(folder, "the driven set is empty")
    np.save(folder / "driven.npy", np.ones(n, dtype=bool))
    expect_error(folder, "the driven set covers every vertex")


def test_bone_transform_not_finite(tmp_path):
    folder = write_capsule(tmp_path / "c", "skeleton", "npz")
    with np.load(folder / "skeleton.npz") as data:
        bones = {k: data[k] for k in data.files}
    bones["transforms"][1, 0, 2, 3] = np.inf
    np.savez(folder / "skeleton.npz", **bones)
    expect_error(folder, "the transform of bone 0 in frame 1 is not finite")


def test_the_manifest_up_axis_is_read_as_a_unit_vector_and_checked(tmp_path):
    folder = write_capsule(tmp_path / "c")
    assert load_animation(folder).up is None                  # none written: none read
    manifest = folder / "animation.yaml"
    spec = yaml.safe_load(manifest.read_text())
    for value, expected in (("y", [0, 1, 0]), ("-Z", [0, 0, -1]), ("+x", [1, 0, 0])):
        manifest.write_text(yaml.safe_dump({**spec, "up": value}))
        np.testing.assert_array_equal(load_animation(folder).up, expected)
    manifest.write_text(yaml.safe_dump({**spec, "up": "north"}))
    with pytest.raises(AnimationError, match=r"up must be one of x, y, z, -x, -y, -z") as err:
        load_animation(folder)
    assert "\n" not in str(err.value) and "'north'" in str(err.value)


@pytest.mark.parametrize("values, found", [
    (np.array(["a", "b"]), r"holds text \(dtype <U1\)"),
    ("complex", r"holds complex \(dtype complex128\)"),
    (np.array([object(), 1.0], dtype=object), r"holds Python objects \(dtype object\)"),
    ("bool", r"holds bool \(dtype bool\)")])
def test_frames_that_are_not_real_numbers_are_refused_naming_file_key_and_dtype(
        tmp_path, values, found):
    """Issue 38: string frames were a traceback, complex ones lost their imaginary part."""
    folder = write_capsule(tmp_path / "c", "skeleton", "npz")
    frames = np.load(folder / "frames.npz")["frames"]
    values = frames + 1e-3j if isinstance(values, str) and values == "complex" else \
        frames > 0 if isinstance(values, str) else values
    np.savez(folder / "frames.npz", frames=values)
    expect_error(folder, rf"frames\.npz \((array 'frames'|frames\.npy)\): {found}")


def test_weights_labels_and_bones_that_are_not_numbers_are_refused(tmp_path):
    folder = write_capsule(tmp_path / "c", "skeleton", "npz")
    n = len(np.load(folder / "frames.npz")["frames"][0])
    np.save(folder / "weights.npy", np.ones((n, 2), dtype=np.complex64))
    edit_manifest(folder, lambda s: s["skeleton"].update(weights="weights.npy"))
    expect_error(folder, r"weights\.npy: holds complex \(dtype complex64\), but must hold "
                         r"real numbers")
    np.save(folder / "weights.npy", np.ones((n, 2), dtype=bool))
    expect_error(folder, r"weights\.npy: holds bool \(dtype bool\)")
    edit_manifest(folder, lambda s: s["skeleton"].update(weights="distance"))
    with np.load(folder / "skeleton.npz") as data:
        bones = {k: data[k] for k in data.files}
    np.savez(folder / "skeleton.npz", **{**bones, "heads": bones["heads"].astype(str)})
    expect_error(folder, r"skeleton\.npz \(heads\): holds text")
    np.savez(folder / "skeleton.npz", **{**bones, "transforms": bones["transforms"] + 0j})
    expect_error(folder, r"skeleton\.npz \(transforms\): holds complex")
    np.savez(folder / "skeleton.npz", **bones)
    np.save(folder / "regions.npy", np.array(["bone"] * n))
    edit_manifest(folder, lambda s: s.update(regions={"labels": "regions.npy"}))
    expect_error(folder, r"regions\.npy: holds text \(dtype <U4\), but must hold integers")


def test_an_existing_path_is_replaced_only_when_it_holds_a_written_animation(tmp_path):
    """write_animation removed whatever stood at the path: now a plain file or a folder with
    anything it does not write is refused (one line naming it), the folder untouched."""
    rest, faces = np.eye(4, 3), np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])
    frames = np.stack([rest, rest + 0.1])

    def write(folder):
        return write_animation(folder, rest, faces, frames,
                               driven=DrivenSurface(np.array([True, False, False, False]), 1e-3))

    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "rest.obj").write_text("my own rest surface")
    (mine / "sculpt.blend").write_bytes(b"BLENDER")
    with pytest.raises(AnimationError, match=r"holds files torchfit did not write "
                                             r"\(sculpt\.blend\)"):
        write(mine)
    assert (mine / "rest.obj").read_text() == "my own rest surface"
    (tmp_path / "file").write_text("x")
    with pytest.raises(AnimationError, match="exists and is not a folder"):
        write(tmp_path / "file")
    write(tmp_path / "anim")
    write(tmp_path / "anim")                             # its own: replaced, nothing beside it
    assert load_animation(tmp_path / "anim").n_frames == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["anim", "file", "mine"]
