"""Simplicial meshes (torchfit.mesh.simplicial): structured triangles and tetrahedra, boundary
sets, adjacency, rest-cell checks."""
from __future__ import annotations

import numpy as np
import pytest

from torchfit.mesh import (MeshError, box_tetrahedra, check_rest_cells, element_adjacency,
                           rectangle_triangles)


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
