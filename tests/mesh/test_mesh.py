"""Meshes: structured triangles and tetrahedra, boundary sets, adjacency, the IPAM font."""
from __future__ import annotations

import numpy as np
import pytest

from torchfit.mesh import (MeshError, box_tetrahedra, check_rest_cells, element_adjacency,
                           ipam_mask, normalized_points, rectangle_triangles)
from torchfit.mesh.font import word_bitmap


def test_rectangle_triangulation_numbering_and_orientation():
    mesh = rectangle_triangles(4, 2, 2.0, 0.5)
    assert mesh.points.shape == (15, 2) and mesh.cells.shape == (16, 3)
    assert np.allclose(mesh.points[7], [1.0, 0.25])            # vertex (i=2, j=1) = 1*5 + 2
    vol = mesh.signed_volumes()
    assert np.allclose(vol, 2.0 * 0.5 / 16)                      # all positive, equal
    # cell (i=1, j=1) is c = 5: triangles 10 (below the diagonal) and 11 (above)
    assert mesh.cells[10].tolist() == [6, 7, 12] and mesh.cells[11].tolist() == [6, 12, 11]
    assert mesh.boundary_vertices("left").tolist() == [0, 5, 10]
    assert mesh.boundary_vertices("right").tolist() == [4, 9, 14]
    assert mesh.boundary_vertices("top").tolist() == [10, 11, 12, 13, 14]
    assert mesh.boundary_facet_vertices().size == 12
    with pytest.raises(MeshError, match="side"):
        mesh.boundary_vertices("front")


def test_triangle_adjacency_by_shared_edges():
    mesh = rectangle_triangles(3, 2)
    pairs = mesh.adjacency()
    # interior edges: 6 diagonals, 2 * 2 vertical, 3 * 1 horizontal
    assert len(pairs) == 6 + 4 + 3
    assert (pairs[:, 0] < pairs[:, 1]).all()
    assert [0, 1] in pairs.tolist()                   # the two halves of cell 0
    assert [1, 6] in pairs.tolist()                   # cell 0 upper / cell 3 lower (shared horizontal edge)
    degree = np.bincount(pairs.reshape(-1), minlength=mesh.n_cells)
    assert degree.max() == 3 and degree.min() >= 1


def test_tetrahedral_box_is_conforming_and_positive():
    mesh = box_tetrahedra(2, 3, 2, (1.0, 1.5, 0.5))
    vol = mesh.signed_volumes()
    assert (vol > 0).all() and np.isclose(vol.sum(), 1.0 * 1.5 * 0.5)
    pairs = element_adjacency(mesh.cells)
    # every interior face is shared by exactly two tets: 4 faces per tet = 2 interior + boundary
    n_boundary_faces = 2 * 2 * (2 * 3 + 3 * 2 + 2 * 2)
    assert 4 * mesh.n_cells == 2 * len(pairs) + n_boundary_faces
    assert mesh.boundary_vertices("front").size == 3 * 4


def test_rest_cell_check_names_bad_elements():
    mesh = rectangle_triangles(2, 1)
    cells = mesh.cells.copy()
    cells[1] = cells[1][::-1]
    with pytest.raises(MeshError, match=r"1 inverted .*: 1 \(vertices"):
        check_rest_cells(mesh.points, cells)
    points = mesh.points.copy()
    points[4] = points[3]                              # repeated vertex: zero area
    with pytest.raises(MeshError, match="degenerate"):
        check_rest_cells(points, mesh.cells)


def test_ipam_bitmap_glyphs():
    bitmap = word_bitmap("IPAM")
    assert bitmap.shape == (7, 23)
    assert not bitmap[:, 5].any() and not bitmap[:, 11].any() and not bitmap[:, 17].any()
    rows = ["".join("#" if b else "." for b in row[12:17]) for row in bitmap]
    assert rows == [".###.", "#...#", "#...#", "#####", "#...#", "#...#", "#...#"]   # A
    with pytest.raises(ValueError, match="no glyph"):
        word_bitmap("IPAX")


def test_ipam_mask_reproduces_the_independent_poisson2d_vectors(vectors_dir):
    data = np.load(vectors_dir / "poisson2d_N16_ipam.npz")
    centres = data["cell_centres"] / float(data["s"])
    k = np.where(ipam_mask(centres), 5.0, 1.0)
    np.testing.assert_array_equal(k, data["k"])


def test_ipam_mask_placement_rule():
    # top-left pixel of I is ink, the pixel below it is not; the box is half-open
    x0, x1, y0, y1 = 0.10, 0.90, 0.35, 0.65
    px, py = (x1 - x0) / 23, (y1 - y0) / 7
    top_left = [x0 + 0.5 * px, y1 - 0.5 * py]
    below = [x0 + 0.5 * px, y1 - 1.5 * py]
    mask = ipam_mask(np.array([top_left, below, [x0, y1 - 0.5 * py], [x1, 0.5], [0.5, y1]]))
    assert mask.tolist() == [True, False, True, False, False]
    assert np.allclose(normalized_points(np.array([[2.0, 0.5]]), ((0.0, 2.0), (0.0, 0.5))), [[1.0, 1.0]])
