"""Meshes, surfaces, rigs and animations: everything geometric, nothing that solves.

Structured triangle and tetrahedral meshes, user surfaces, tetrahedralisation (fTetWild,
cached), barycentric embedding, rigs, and the file formats of a rigged animation.
"""
from .formats import (Animation, AnimationError, load_animation, read_animation,
                      write_animation, write_obj)
from .embedding import Embedding, boundary_faces, embed_points
from .rig import DrivenSurface, Skeleton
from .simplicial import (MeshError, SimplexMesh, box_tetrahedra, check_rest_cells,
                         element_adjacency, normalized_points, rectangle_triangles,
                         signed_volumes)
from .surface import SurfaceError, load_surface
from .tetwild import (TetMesh, TetOptions, TetrahedralizationError, default_cache_dir,
                      tetrahedralize)

__all__ = ["Animation", "AnimationError", "DrivenSurface", "Embedding",
           "MeshError", "SimplexMesh", "Skeleton", "SurfaceError", "TetMesh", "TetOptions",
           "TetrahedralizationError", "box_tetrahedra", "boundary_faces",
           "check_rest_cells", "default_cache_dir", "element_adjacency", "embed_points",
           "load_animation", "read_animation", "load_surface", "normalized_points",
           "rectangle_triangles", "signed_volumes", "tetrahedralize", "write_animation",
           "write_obj"]
