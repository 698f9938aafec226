"""Tetrahedral meshes of closed surfaces by fTetWild (pytetwild): options, the on-disk cache,
the size a target count asks for, and a run's own copy of its mesh.

pytetwild runs in a child process (:mod:`.worker`), its output is cached by a hash of the
surface and the options (fTetWild is not deterministic), and a run keeps the mesh it used
(:mod:`.store`), so a resume or ``simulate`` needs no cache.
"""
from .tetrahedralize import (TetMesh, TetOptions, TetrahedralizationError, default_cache_dir,
                             tetrahedralize)

__all__ = ["TetMesh", "TetOptions", "TetrahedralizationError", "default_cache_dir",
           "tetrahedralize"]
