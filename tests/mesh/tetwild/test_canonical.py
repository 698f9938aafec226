"""torchfit.mesh.tetwild.canonical: the canonical form of a surface in a given frame, the match
between two of them, and the cache that serves every representation one entry."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from tests.helpers.canonical_surfaces import permuted, seam_split, tapered_capsule
from torchfit.mesh import TetOptions, canonical_surface, tetrahedralize_canonical, welded_surface
from torchfit.mesh.tetwild.canonical import MATCH, Placement, canonical_options

FRAME = (np.array([0.01, -0.02, 0.03]), np.eye(3))


def test_the_placement_maps_canonical_points_into_the_file_and_back():
    axes = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0]
    placement = Placement(np.array([1.0, 2.0, 3.0]), axes, 2.5)
    x = np.random.default_rng(1).normal(size=(5, 3))
    np.testing.assert_allclose(placement.to_file(x), 2.5 * x @ axes + [1.0, 2.0, 3.0])
    np.testing.assert_allclose(placement.from_file(placement.to_file(x)), x, atol=1e-14)
    other = Placement(np.zeros(3), np.eye(3), 1.0)
    np.testing.assert_allclose(placement.directions_to(other, axes), np.eye(3), atol=1e-14)


def test_the_canonical_form_ignores_order_seams_and_a_face_s_first_corner():
    vertices, faces = tapered_capsule()
    plain = canonical_surface(vertices, faces, *FRAME)
    for v, f in (permuted(vertices, faces), seam_split(vertices, faces)):
        other = canonical_surface(v, f, *FRAME)
        np.testing.assert_array_equal(other.vertices, plain.vertices)
        np.testing.assert_array_equal(other.faces, plain.faces)
        assert other.digest == plain.digest
    # orientation kept: every face starts at its lowest vertex, the winding as given
    assert (plain.faces[:, 0] < plain.faces[:, 1:].min(axis=1)).all()
    area = trimesh.Trimesh(plain.vertices, plain.faces, process=False)
    assert area.is_watertight and area.volume > 0
    assert plain.placement.scale == pytest.approx(
        np.linalg.norm(vertices - FRAME[0], axis=1).max(), rel=1e-12)


def test_two_surfaces_are_one_within_the_match_and_not_beyond():
    vertices, faces = tapered_capsule()
    plain = canonical_surface(vertices, faces, *FRAME)
    scale = plain.placement.scale
    near = vertices + 0.15 * MATCH * scale * np.random.default_rng(2).uniform(-1, 1, vertices.shape)
    assert plain.difference(canonical_surface(near, faces, *FRAME)) == ""
    far = vertices.copy()
    far[7, 0] += 0.01 * scale
    assert plain.difference(canonical_surface(far, faces, *FRAME)).startswith(
        "its surface differs in shape (a vertex 0.01 of the body's radius")
    flipped = faces.copy()
    flipped[3] = flipped[3, ::-1]                             # one triangle turned over
    assert plain.difference(canonical_surface(vertices, flipped, *FRAME)) == \
        "its surface has the same points but other triangles"
    assert plain.difference(canonical_surface(vertices, faces[1:], *FRAME)).startswith(
        f"its surface has {len(vertices)} vertices and {len(faces) - 1} faces once welded")
    # the key holds only what is invariant: counts, options (an absolute edge size-free)
    assert canonical_options(TetOptions(edge_length_abs=0.3), 2.0).edge_length_abs == 0.15
    assert plain.key(TetOptions(), "0.2.3") == canonical_surface(
        far, faces, *FRAME).key(TetOptions(), "0.2.3")
    assert plain.key(TetOptions(), "0.2.3") != plain.key(TetOptions(epsilon=2e-3), "0.2.3")


def test_welding_merges_a_seam_s_copies_at_their_mean():
    vertices, faces = tapered_capsule()
    v, f = seam_split(vertices, faces)
    groups, merged, welded_faces = welded_surface(v, f)
    assert len(v) > len(vertices) and len(merged) == len(vertices)
    np.testing.assert_array_equal(merged[groups], v)
    np.testing.assert_array_equal(welded_faces, groups[f])


def test_a_near_copy_reads_the_entry_and_another_body_builds_its_own(tmp_path):
    vertices, faces = tapered_capsule()
    options = TetOptions(edge_length_fac=0.2)
    first = tetrahedralize_canonical(canonical_surface(vertices, faces, *FRAME), options,
                                     cache_dir=tmp_path)
    # 4e-7 of the radius off: other canonical bytes (another digest), the same entry
    moved = vertices + 4e-7 * np.random.default_rng(3).uniform(-1, 1, vertices.shape) * 0.5
    near = canonical_surface(moved, faces, *FRAME)
    assert near.digest != first.canonical.digest
    again = tetrahedralize_canonical(near, options, cache_dir=tmp_path)
    assert again.from_cache and again.key == first.key and again.path == first.path
    np.testing.assert_array_equal(again.cells, first.cells)
    longer = canonical_surface(vertices * [1, 1, 1.3], faces, *FRAME)
    other = tetrahedralize_canonical(longer, options, cache_dir=tmp_path)
    assert not other.from_cache and other.key != first.key
    assert len(list(tmp_path.glob("canonical/*/*.npz"))) == 2


def test_the_same_surface_in_a_turned_canonical_frame_reads_the_entry_turned(tmp_path):
    """A round body's frame in its cross-section comes from the motion: another shot turns
    it. The entry stored in one frame serves the other, its tetrahedra turned alike."""
    from scipy.spatial.transform import Rotation

    vertices, faces = tapered_capsule()
    options = TetOptions(edge_length_fac=0.2)
    first = tetrahedralize_canonical(canonical_surface(vertices, faces, *FRAME), options,
                                     cache_dir=tmp_path)
    spin = Rotation.from_rotvec([0.0, 0.0, 0.9]).as_matrix()
    v, f = seam_split(vertices, faces)                  # the welded order is the file's
    turned_frame = canonical_surface(v, f, FRAME[0], spin @ FRAME[1])
    assert canonical_surface(vertices, faces, *FRAME).difference(turned_frame) != ""
    again = tetrahedralize_canonical(turned_frame, options, cache_dir=tmp_path)
    assert again.from_cache and again.key == first.key
    np.testing.assert_array_equal(again.cells, first.cells)
    np.testing.assert_allclose(again.points, first.points, atol=1e-12)
    # another order in the file gives no correspondence: another entry
    pv, pf = permuted(vertices, faces)
    other = tetrahedralize_canonical(canonical_surface(pv, pf, FRAME[0], spin @ FRAME[1]),
                                     options, cache_dir=tmp_path)
    assert not other.from_cache
