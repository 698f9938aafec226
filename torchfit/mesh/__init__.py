"""Meshes: structured triangle/tetrahedral meshes, boundary sets, adjacency, the IPAM font."""
from .font import GLYPHS, IPAM_BOX, bitmap_mask, ipam_mask, word_bitmap
from .simplicial import (MeshError, SimplexMesh, box_tetrahedra, check_rest_cells,
                         element_adjacency, normalized_points, rectangle_triangles,
                         signed_volumes)

__all__ = ["GLYPHS", "IPAM_BOX", "MeshError", "SimplexMesh", "bitmap_mask", "box_tetrahedra",
           "check_rest_cells", "element_adjacency", "ipam_mask", "normalized_points",
           "rectangle_triangles", "signed_volumes", "word_bitmap"]
