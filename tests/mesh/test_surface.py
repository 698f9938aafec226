"""User surfaces: loading in the file's vertex order, load errors, surface checks, volume."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from torchfit.mesh import MeshError, SurfaceError, load_surface
from torchfit.mesh.surface import surface_volume, surface_warnings


def capsule() -> trimesh.Trimesh:
    return trimesh.creation.capsule(height=0.58, radius=0.045, count=[8, 8])


def shuffled(mesh: trimesh.Trimesh, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Vertices in a random order (not one trimesh would make up), faces renumbered."""
    perm = np.random.default_rng(seed).permutation(len(mesh.vertices))
    inverse = np.argsort(perm)
    return mesh.vertices[perm], inverse[mesh.faces]


@pytest.mark.parametrize("ext", ["obj", "ply", "off"])
def test_loading_keeps_the_files_vertex_order(tmp_path, ext):
    vertices, faces = shuffled(capsule())
    path = tmp_path / f"surface.{ext}"
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    mesh = load_surface(path)
    assert mesh.vertices.shape == vertices.shape
    np.testing.assert_allclose(mesh.vertices, vertices, rtol=0, atol=1e-7)   # row by row
    assert np.array_equal(mesh.faces, faces)
    scaled = load_surface(path, scale=100.0)                # e.g. m -> cm
    np.testing.assert_allclose(scaled.vertices, 100.0 * mesh.vertices, rtol=1e-15)
    assert np.array_equal(scaled.faces, faces)


def test_stl_triangle_soup_is_merged_into_a_closed_surface(tmp_path):
    mesh = capsule()
    path = tmp_path / "surface.stl"
    mesh.export(path)
    loaded = load_surface(path)
    assert len(loaded.vertices) == len(mesh.vertices) and len(loaded.faces) == len(mesh.faces)
    assert surface_warnings(loaded) == []
    assert surface_volume(loaded) == pytest.approx(mesh.volume, rel=1e-6)


def write(path, text: str):
    path.write_text(text)
    return path


def test_load_errors_name_the_file_and_the_problem(tmp_path):
    with pytest.raises(SurfaceError, match=r"nothere\.obj does not exist"):
        load_surface(tmp_path / "nothere.obj")
    nan = write(tmp_path / "nan.obj", "v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n")
    with pytest.raises(SurfaceError, match=r"nan\.obj: vertex 2 is not finite"):
        load_surface(nan)
    inf = write(tmp_path / "inf.off", "OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n0 0 inf\n"
                                      "3 0 1 2\n3 0 1 3\n")
    with pytest.raises(SurfaceError, match="vertex 3 is not finite"):
        load_surface(inf)
    with pytest.raises(SurfaceError, match=r"empty\.obj has no"):
        load_surface(write(tmp_path / "empty.obj", ""))
    with pytest.raises(SurfaceError, match=r"points\.obj has no"):
        load_surface(write(tmp_path / "points.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n"))
    with pytest.raises(SurfaceError, match=r"range\.obj: a face refers to a vertex"):
        load_surface(write(tmp_path / "range.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n"))
    ply = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
           "property float z\nelement face 2\nproperty list uchar int vertex_indices\n"
           "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 1 9\n")
    with pytest.raises(SurfaceError, match=r"range\.ply: face 1 \[0, 1, 9\] refers to a vertex "
                                           r"out of range \[0, 3\)"):
        load_surface(write(tmp_path / "range.ply", ply))
    with pytest.raises(SurfaceError, match=r"range\.off .*face index outside the range"):
        load_surface(write(tmp_path / "range.off", "OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n"
                                                   "3 0 1 2\n3 0 1 9\n"))
    with pytest.raises(SurfaceError, match=r"cannot read surface file .*garbage\.ply"):
        load_surface(write(tmp_path / "garbage.ply", "garbage\nmore"))
    with pytest.raises(SurfaceError, match=r"cannot read surface file .*surface\.xyz1"):
        load_surface(write(tmp_path / "surface.xyz1", "v 0 0 0"))
    good = tmp_path / "good.obj"
    capsule().export(good)
    with pytest.raises(SurfaceError, match="scale"):
        load_surface(good, scale=0.0)
    assert issubclass(SurfaceError, MeshError)
    # one line each: what a user reads
    with pytest.raises(SurfaceError) as info:
        load_surface(tmp_path / "garbage.ply")
    assert "\n" not in str(info.value)


def test_a_clean_closed_surface_has_no_warnings_and_its_volume():
    box = trimesh.creation.box((0.1, 0.2, 0.3))
    assert surface_warnings(box) == []
    assert surface_volume(box) == pytest.approx(0.006, rel=1e-13)
    mesh = capsule()
    assert surface_warnings(mesh) == []
    # a polygonal capsule: a little less than pi r^2 h + 4/3 pi r^3
    exact = np.pi * 0.045 ** 2 * 0.58 + 4 / 3 * np.pi * 0.045 ** 3
    assert 0.85 * exact < surface_volume(mesh) < exact
    assert surface_volume(mesh) == pytest.approx(mesh.volume, rel=1e-12)


def test_each_surface_problem_is_named_with_its_count():
    mesh = capsule()
    v, f = mesh.vertices, mesh.faces
    # a missing face opens three edges
    open_ = trimesh.Trimesh(v, f[1:], process=False)
    (text,) = surface_warnings(open_)
    assert "not watertight" in text and "3 boundary edge" in text
    assert surface_volume(open_) is None
    # a fin on edge (a, b): that edge now has three faces, the fin's two others one
    a, b = f[0, 0], f[0, 1]
    fin = trimesh.Trimesh(np.vstack([v, [[1.0, 1.0, 1.0]]]),
                          np.vstack([f, [[a, b, len(v)]]]), process=False)
    texts = surface_warnings(fin)
    assert any("1 non-manifold edge" in t for t in texts)
    assert any("2 boundary edge" in t for t in texts)
    # one face flipped: its three edges are traversed the same way twice
    flipped = f.copy()
    flipped[5] = flipped[5, ::-1]
    (text,) = surface_warnings(trimesh.Trimesh(v, flipped, process=False))
    assert "winding is inconsistent: 3 edge" in text
    assert surface_volume(trimesh.Trimesh(v, flipped, process=False)) is None
    # all faces flipped: inside out, still encloses the same volume
    inverted = trimesh.Trimesh(v, f[:, ::-1], process=False)
    (text,) = surface_warnings(inverted)
    assert "inside out" in text and f"{-mesh.volume:.4g}" in text
    assert surface_volume(inverted) == pytest.approx(mesh.volume, rel=1e-12)
    # two copies of a vertex position (unreferenced here)
    dup = trimesh.Trimesh(np.vstack([v, v[:2]]), f, process=False)
    (text,) = surface_warnings(dup)
    assert text.startswith("2 vertex(es) duplicate")
    assert surface_warnings(trimesh.Trimesh(np.zeros((3, 3)), np.zeros((0, 3), int),
                                            process=False)) == [
        "the surface has no faces, so it encloses no volume"]
