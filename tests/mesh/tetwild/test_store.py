"""torchfit.mesh.tetwild.store: a run's own mesh.npz, read back exactly, preferred over the cache,
and required (any other surface or option refused, nothing tetrahedralised)."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from torchfit.mesh import MeshError, box_tetrahedra
from torchfit.mesh.tetwild.store import (KeptMesh, read_kept_mesh, read_run_mesh,
                                     tetrahedralize_kept, write_run_mesh)
from torchfit.mesh.tetwild.tetrahedralize import TetMesh, TetOptions, cache_key, pytetwild_version

OPTIONS = TetOptions(edge_length_fac=0.3)


def stored_box(path):
    """A box's tetrahedra written as the mesh of a tube-like surface (a 3 x 1 x 1 box along
    x), as if fTetWild had made them."""
    surface = trimesh.creation.box(extents=(3.0, 1.0, 1.0))
    vertices, faces = np.asarray(surface.vertices), np.asarray(surface.faces)
    box = box_tetrahedra(3, 1, 1, (3.0, 1.0, 1.0))
    key = cache_key(vertices, faces, OPTIONS, pytetwild_version())
    tet = TetMesh(box.points, box.cells, key, False, 0.0, 1.5, None)
    regions = np.arange(len(box.cells)) % 2
    write_run_mesh(path, tet, OPTIONS, vertices, faces, regions)
    return vertices, faces, box, regions


def test_the_run_mesh_reads_back_bit_for_bit_and_writes_the_same_bytes(tmp_path):
    vertices, faces, box, regions = stored_box(tmp_path / "mesh.npz")
    stored = read_run_mesh(tmp_path / "mesh.npz")
    np.testing.assert_array_equal(stored.points, box.points)
    np.testing.assert_array_equal(stored.cells, box.cells)
    np.testing.assert_array_equal(stored.regions, regions)
    assert stored.build_seconds == 1.5 and stored.options == OPTIONS.as_dict()
    stored_box(tmp_path / "again.npz")
    assert (tmp_path / "again.npz").read_bytes() == (tmp_path / "mesh.npz").read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.npz", "mesh.npz"]


def test_a_kept_mesh_comes_before_the_cache(tmp_path):
    vertices, faces, box, _ = stored_box(tmp_path / "mesh.npz")
    assert read_kept_mesh(tmp_path / "nowhere") is None
    kept = read_kept_mesh(tmp_path)
    tet = tetrahedralize_kept(vertices, faces, OPTIONS, kept, cache_dir=tmp_path / "cache")
    np.testing.assert_array_equal(tet.cells, box.cells)
    assert tet.from_cache and not (tmp_path / "cache").exists()
    # not required: another surface is tetrahedralised as usual (here: no kept mesh used)
    assert kept.mesh_for(1.05 * vertices, faces, OPTIONS) is None
    assert kept.frame_for(vertices, faces, OPTIONS) is None      # stored without a frame


def test_a_required_mesh_refuses_another_surface_or_option(tmp_path):
    vertices, faces, box, _ = stored_box(tmp_path / "mesh.npz")
    stored = read_run_mesh(tmp_path / "mesh.npz")
    kept = KeptMesh(stored, required=True)
    assert tetrahedralize_kept(vertices, faces, OPTIONS, kept).points is stored.points
    with pytest.raises(MeshError, match=r"not the fitted body: its rest surface's vertices "
                                        r"differ from the fitted body's \(by up to 0\.075\)"):
        tetrahedralize_kept(1.05 * vertices, faces, OPTIONS, kept, cache_dir=tmp_path / "c")
    with pytest.raises(MeshError, match="rest surface has 7 vertices and 1 faces"):
        tetrahedralize_kept(vertices[:7], faces[:1], OPTIONS, kept, cache_dir=tmp_path / "c")
    with pytest.raises(MeshError, match="edge_length_fac: 0.3 fitted, 0.2 now"):
        tetrahedralize_kept(vertices, faces, TetOptions(edge_length_fac=0.2), kept,
                            cache_dir=tmp_path / "c")
    assert not (tmp_path / "c").exists()


def test_a_file_that_is_not_a_run_mesh_is_one_line(tmp_path):
    (tmp_path / "mesh.npz").write_bytes(b"not a zip")
    with pytest.raises(MeshError, match=r"mesh.npz is not a torchfit run mesh") as info:
        read_run_mesh(tmp_path / "mesh.npz")
    assert "\n" not in str(info.value)


def test_the_same_body_from_another_file_gets_the_kept_mesh_mapped(tmp_path):
    """A run's mesh made in canonical form serves the same surface from another file (turned,
    re-ordered, seam-split, float32), mapped into its coordinates, with the grid's frame;
    a copy scaled by 100 in the same unit and another shape are refused in one line."""
    from tests.helpers.canonical_surfaces import permuted, seam_split, tapered_capsule, turned
    from torchfit.problems.body.frame import body_surface, tetrahedralize_in_frame

    vertices, faces = tapered_capsule()
    options = TetOptions(edge_length_fac=0.2)
    tet = tetrahedralize_in_frame(vertices, faces, None, options, tmp_path / "cache")
    frame = (np.array([0.1, 0.2, 0.3]), np.eye(3)[[1, 2, 0]])
    write_run_mesh(tmp_path / "mesh.npz", tet, options, vertices, faces, None, frame)
    kept = KeptMesh(read_run_mesh(tmp_path / "mesh.npz"), required=True)
    moved, (_, R, t) = turned(vertices, scale=1.0)
    v, f = seam_split(*permuted(moved, faces))
    v = v.astype(np.float32)
    surface = body_surface(v, f, None)
    mesh = kept.mesh_for(v, f, options, surface)
    np.testing.assert_array_equal(mesh.cells, tet.cells)
    assert mesh.key == tet.key and mesh.canonical is surface
    assert np.abs(mesh.points - (tet.points @ R.T + t)).max() < 1e-6 * np.ptp(tet.points)
    origin, axes = kept.frame_for(v, f, options, surface)
    assert np.abs(origin - (frame[0] @ R.T + t)).max() < 1e-6
    assert np.abs(axes - frame[1] @ R.T).max() < 1e-6
    same = kept.mesh_for(vertices, faces, options, body_surface(vertices, faces, None))
    assert same.points is kept.stored.points                   # the file itself: as kept
    big = 100.0 * v
    with pytest.raises(MeshError, match=r"^not the fitted body: its rest surface is the "
                                        r"fitted body's scaled by 100 \(in metres"):
        kept.mesh_for(big, f, options, body_surface(big, f, None))
    other = v.copy()
    other[:, 0] *= 1.1
    with pytest.raises(MeshError, match=r"^not the fitted body: not the fitted body's surface "
                                        r"in any axes, order or seams: its surface differs in "
                                        r"shape \(a vertex 0\.0\d+ of the body's radius"):
        kept.mesh_for(other, f, options, body_surface(other, f, None))
    assert kept.frame_for(other, f, options, body_surface(other, f, None)) is None


def test_a_round_body_turned_by_another_shot_s_motion_still_gets_the_kept_mesh(tmp_path):
    """A round body's canonical frame is settled by its motion: another shot from another
    file can turn it about the body's axis, so the canonical surfaces differ; the kept
    welded vertices moved rigidly onto the file's (in their order) still match, and the
    mesh is mapped by that motion. Another shape still does not."""
    from scipy.spatial.transform import Rotation

    from tests.helpers.canonical_surfaces import seam_split, tapered_capsule, turned
    from torchfit.mesh import canonical_surface
    from torchfit.problems.body.frame import body_surface, tetrahedralize_in_frame

    vertices, faces = tapered_capsule()
    options = TetOptions(edge_length_fac=0.2)
    tet = tetrahedralize_in_frame(vertices, faces, None, options, tmp_path / "cache")
    frame = (np.array([0.1, 0.2, 0.3]), np.eye(3))
    write_run_mesh(tmp_path / "mesh.npz", tet, options, vertices, faces, None, frame)
    kept = KeptMesh(read_run_mesh(tmp_path / "mesh.npz"), required=True)
    moved, (_, R, t) = turned(vertices, scale=1.0)
    v, f = seam_split(moved.astype(np.float32), faces)
    own = body_surface(v, f, None).placement
    spin = Rotation.from_rotvec([0.0, 0.0, 0.7]).as_matrix()    # about a2: the motion's choice
    surface = canonical_surface(v, f, own.origin, spin @ own.axes)
    assert kept.stored.canonical_surface().difference(surface) != ""
    mesh = kept.mesh_for(v, f, options, surface)
    assert np.abs(mesh.points - (tet.points @ R.T + t)).max() < 1e-6 * np.ptp(tet.points)
    origin, axes = kept.frame_for(v, f, options, surface)
    assert np.abs(origin - (frame[0] @ R.T + t)).max() < 1e-6
    assert np.abs(axes - frame[1] @ R.T).max() < 1e-6
    other = v.copy()
    other[:, 2] *= 1.05
    with pytest.raises(MeshError, match="^not the fitted body: not the fitted body's surface"):
        kept.mesh_for(other, f, options, canonical_surface(other, f, own.origin,
                                                           spin @ own.axes))
