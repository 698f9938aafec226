"""Meshes, surfaces, rigs and animations: everything geometric, nothing that solves.

Structured triangle and tetrahedral meshes, user surfaces, tetrahedralisation (fTetWild,
cached), barycentric embedding, rigs and the rig check, the :class:`Animation` every reader
builds (:mod:`.animation`), and the file formats of a rigged animation (:mod:`.formats`).
"""
from .animation import DEFAULT_FPS, UNITS, Animation, AnimationError
from .formats import (check_replaceable, load_animation, read_animation, write_animation,
                      write_obj)
from .embedding import Embedding, boundary_faces, dof_matrix, embed_points
from .rig import (DrivenSurface, Skeleton, axial_coordinates, blend, distance_weights,
                  joint_cells, rig_description, rig_lines, segment_distances, skeleton_drive,
                  surface_drive)
from .rig_check import RigReport, check_animation
from .simplicial import (MeshError, SimplexMesh, box_tetrahedra, check_rest_cells,
                         element_adjacency, normalized_points, rectangle_triangles,
                         signed_volumes)
from .surface import SurfaceError, load_surface
from .tetwild import (RUN_MESH_FILE, CanonicalSurface, KeptMesh, Placement, StoredMesh,
                      TetMesh, TetOptions, TetrahedralizationError, body_volume,
                      canonical_surface, default_cache_dir, read_kept_mesh, read_run_mesh,
                      tetrahedralize, tetrahedralize_canonical, welded_surface,
                      write_run_mesh)

__all__ = ["Animation", "AnimationError", "CanonicalSurface", "DEFAULT_FPS", "DrivenSurface",
           "Embedding", "KeptMesh", "MeshError", "Placement", "RUN_MESH_FILE", "RigReport",
           "SimplexMesh", "Skeleton", "StoredMesh", "SurfaceError", "TetMesh", "TetOptions",
           "TetrahedralizationError", "UNITS", "axial_coordinates", "blend", "body_volume",
           "boundary_faces", "box_tetrahedra", "canonical_surface", "check_animation",
           "check_replaceable", "check_rest_cells", "default_cache_dir", "distance_weights",
           "dof_matrix", "element_adjacency", "embed_points", "joint_cells", "load_animation",
           "load_surface", "normalized_points", "read_animation", "read_kept_mesh",
           "read_run_mesh", "rectangle_triangles", "rig_description", "rig_lines",
           "segment_distances", "signed_volumes", "skeleton_drive", "surface_drive",
           "tetrahedralize", "tetrahedralize_canonical", "welded_surface", "write_animation",
           "write_obj", "write_run_mesh"]
