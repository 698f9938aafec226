"""Meshes: structured triangle/tetrahedral meshes, boundary sets, adjacency, the IPAM font,
user surfaces (loading, checks), tetrahedralisation (fTetWild, cached), barycentric embedding."""
from .embedding import Embedding, boundary_faces, embed_points
from .font import GLYPHS, IPAM_BOX, bitmap_mask, ipam_mask, word_bitmap
from .simplicial import (MeshError, SimplexMesh, box_tetrahedra, check_rest_cells,
                         element_adjacency, normalized_points, rectangle_triangles,
                         signed_volumes)
from .surface import SurfaceError, load_surface, surface_volume, surface_warnings
from .tetrahedralize import (TetMesh, TetOptions, TetrahedralizationError, default_cache_dir,
                             tetrahedralize)

__all__ = ["Embedding", "GLYPHS", "IPAM_BOX", "MeshError", "SimplexMesh", "SurfaceError",
           "TetMesh", "TetOptions", "TetrahedralizationError", "bitmap_mask", "boundary_faces",
           "box_tetrahedra", "check_rest_cells", "default_cache_dir", "element_adjacency",
           "embed_points", "ipam_mask", "load_surface", "normalized_points",
           "rectangle_triangles", "signed_volumes", "surface_volume", "surface_warnings",
           "tetrahedralize", "word_bitmap"]
