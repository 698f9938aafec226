"""Tetrahedral meshes of closed surfaces by fTetWild (pytetwild): options, the on-disk cache,
the size a target count asks for, and a run's own copy of its mesh.

pytetwild runs in a child process (:mod:`.worker`), its output is cached by a hash of the
surface and the options (fTetWild is not deterministic), or, for a body, on its canonical
surface (:mod:`.canonical`: the same mesh whatever the file's axes, units, dtype, order or
seams), and a run keeps the mesh it used (:mod:`.store`), so a resume or ``simulate``
needs no cache.
"""
from .canonical import (CanonicalSurface, Placement, canonical_surface,
                        tetrahedralize_canonical, welded_surface)
from .size import body_volume
from .store import (RUN_MESH_FILE, KeptMesh, StoredMesh, read_kept_mesh, read_run_mesh,
                    write_run_mesh)
from .tetrahedralize import (TetMesh, TetOptions, TetrahedralizationError, default_cache_dir,
                             tetrahedralize)

__all__ = ["CanonicalSurface", "KeptMesh", "Placement", "RUN_MESH_FILE", "StoredMesh",
           "TetMesh", "TetOptions", "TetrahedralizationError", "body_volume",
           "canonical_surface", "default_cache_dir", "read_kept_mesh", "read_run_mesh",
           "tetrahedralize", "tetrahedralize_canonical", "welded_surface", "write_run_mesh"]
