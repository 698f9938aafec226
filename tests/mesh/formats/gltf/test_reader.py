"""glTF files built in code, read by torchfit.mesh.formats.gltf.reader, against a hand-written skinning."""
from __future__ import annotations

import sys

import numpy as np
import pytest

from torchfit.mesh.formats.folder import AnimationError
from torchfit.mesh.rig import blend

pytest.importorskip("pygltflib")

from helpers.skinned_files import expected_gltf_frames, gltf_tube  # noqa: E402
from torchfit.mesh.formats.gltf.reader import load_gltf  # noqa: E402


def save(gltf, path):
    if path.suffix == ".glb":
        gltf.save_binary(str(path))
    else:
        from pygltflib import BufferFormat

        gltf.convert_buffers(BufferFormat.DATAURI)         # the buffer inside the JSON
        gltf.save_json(str(path))
    return path


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_skinned_tube_at_its_keyframes(tmp_path, suffix):
    gltf, data = gltf_tube()
    animation = load_gltf(save(gltf, tmp_path / f"tube{suffix}"))
    times = np.array([0.0, 0.5, 1.0])                       # every key of every sampler
    assert [f.rsplit("@", 1)[1] for f in animation.frame_files] == ["0s", "0.5s", "1s"]
    want = expected_gltf_frames(data, times)
    assert np.abs(animation.frames - want).max() < 1e-7
    # the skinned node's translation (100 m) is ignored; the rest is the mesh as stored
    assert np.abs(animation.rest_vertices - data["points"]).max() < 1e-7
    assert animation.faces.tolist() == data["triangles"].tolist()
    skeleton = animation.skeleton
    assert skeleton.names == ["A", "B"]
    joint = {j: np.linalg.inv(np.linalg.inv(data["bind"][j]).astype(np.float32))[:3, 3]
             for j in "ABC"}
    assert np.allclose(skeleton.heads, [joint["A"], joint["B"]], atol=1e-6)
    assert np.allclose(skeleton.tails, [joint["B"], joint["C"]], atol=1e-6)
    assert np.abs(blend(animation.rest_vertices, skeleton.weights, skeleton.transforms)
                  - want).max() < 1e-7


@pytest.mark.parametrize("byte_weights", [False, True])
def test_sampled_at_a_frame_rate_with_slerp(tmp_path, byte_weights):
    gltf, data = gltf_tube(byte_weights=byte_weights)
    animation = load_gltf(save(gltf, tmp_path / "tube.glb"), fps=4.0)
    times = np.arange(5) / 4.0
    assert animation.n_frames == 5
    assert np.abs(animation.frames - expected_gltf_frames(data, times)).max() < 1e-7


@pytest.mark.parametrize("case, message", [
    ({"cubic": True}, "CUBICSPLINE"),
    ({"sparse": True}, "sparse"),
    ({"draco": True}, "KHR_draco_mesh_compression"),
    ({"skinned_nodes": 0}, "no skinned mesh"),
    ({"skinned_nodes": 2}, r"2 skinned nodes .*problem\.prim"),
    ({"short_weights": True}, "the weights must match the points"),
])
def test_unsupported_or_ambiguous_files_are_one_line(tmp_path, case, message):
    gltf, _ = gltf_tube(**case)
    path = save(gltf, tmp_path / "bad.glb")
    with pytest.raises(AnimationError, match=message) as info:
        load_gltf(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_prim_picks_a_skinned_node_by_name(tmp_path):
    gltf, data = gltf_tube(skinned_nodes=2)
    path = save(gltf, tmp_path / "two.glb")
    assert load_gltf(path, "tube1").n_frames == 3
    with pytest.raises(AnimationError, match="problem.prim=nope is not a skinned node"):
        load_gltf(path, "nope")


def test_a_missing_extra_names_it(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pygltflib", None)
    with pytest.raises(AnimationError, match=r"optional extra 'gltf'.*torchfit\[gltf\]"):
        load_gltf(tmp_path / "any.glb")


def save_with_bin(gltf, path, bin_name: str = "tube.bin"):
    """A ``.gltf`` whose buffer 0 is the file ``bin_name`` beside it (its uri
    percent-encoded, as exporters write it)."""
    from urllib.parse import quote

    (path.parent / bin_name).write_bytes(gltf.binary_blob())
    gltf.buffers[0].uri = quote(bin_name)
    gltf.destroy_binary_blob()
    gltf.save_json(str(path))
    return path


def test_an_external_bin_is_read_and_a_missing_one_is_one_line(tmp_path, monkeypatch):
    from torchfit.mesh import read_animation

    gltf, data = gltf_tube()
    path = save_with_bin(gltf, tmp_path / "tube.gltf", "my tube.bin")
    assert np.abs(read_animation(path).frames - expected_gltf_frames(
        data, np.array([0.0, 0.5, 1.0]))).max() < 1e-7
    (tmp_path / "my tube.bin").unlink()
    monkeypatch.chdir(tmp_path)             # a relative problem.path: the line is absolute
    with pytest.raises(AnimationError) as info:
        read_animation("tube.gltf")
    assert str(info.value) == (
        f"{path}: its buffer 0 names my%20tube.bin, which is not there "
        f"({tmp_path / 'my tube.bin'}); keep the .bin beside the .gltf or export a .glb "
        "(one file)")


def test_the_fit_app_names_the_setting_and_the_missing_bin(tmp_path):
    from helpers.fit_app import run_fit_app

    gltf, _ = gltf_tube()
    path = save_with_bin(gltf, tmp_path / "tube.gltf")
    (tmp_path / "tube.bin").unlink()
    run = tmp_path / "run"
    proc = run_fit_app(run, "problem=animation", f"problem.path={path}",
                       f"problem.cache_dir={tmp_path / 'cache'}")
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert errors == [f"error: problem.path={path}: its buffer 0 names tube.bin, which is not "
                      f"there ({tmp_path / 'tube.bin'}); keep the .bin beside the .gltf or "
                      "export a .glb (one file)"]
    assert not run.exists()
