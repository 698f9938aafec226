"""A body problem's tetrahedral mesh kept in its run directory (``mesh.npz``), for the run layer.

A fit of a body writes the mesh it uses before its first checkpoint (:func:`keep_run_mesh`);
building the problem again after :func:`use_run_mesh` gives that mesh whatever the mesh cache
holds (a resume on a machine, or after a cache clean, where the entry is gone);
:func:`fitted_mesh` (``simulate``) refuses any rest surface or tetrahedralisation option but
the fitted body's. The file format and the matching: :mod:`torchfit.mesh.tetwild.store`.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import ContextManager

from ...mesh import MeshError
from ...mesh.tetwild.store import (RUN_MESH_FILE, StoredMesh, read_run_mesh, register_run_mesh,
                              requiring, write_run_mesh)
from ...mesh.tetwild.tetrahedralize import TetMesh

log = logging.getLogger(__name__)

__all__ = ["RUN_MESH_FILE", "StoredMesh", "fitted_mesh", "keep_run_mesh", "read_run_mesh",
           "use_run_mesh"]


def keep_run_mesh(run_dir: Path, problem: object) -> Path | None:
    """The problem's tetrahedral mesh into ``run_dir/mesh.npz``; an existing one is left as
    it is (a resume passed the checkpoint's mesh digest, so it is the same mesh). Returns the
    path written, ``None`` for a problem without a tetrahedralised body."""
    tet, path = getattr(problem, "tet", None), Path(run_dir) / RUN_MESH_FILE
    if not isinstance(tet, TetMesh) or path.exists() or path.is_symlink():
        return None
    animation = getattr(problem, "animation")
    grid = getattr(problem, "grid", None)
    return write_run_mesh(path, tet, getattr(problem, "tet_options"), animation.rest_vertices,
                          animation.faces, getattr(problem, "tet_regions", None),
                          None if grid is None else (grid.origin, grid.axes))


def use_run_mesh(run_dir: str | Path) -> StoredMesh | None:
    """Build bodies of this process with the mesh ``run_dir`` keeps, where their surface and
    options are its own (:func:`~torchfit.mesh.tetwild.store.register_run_mesh`). An unreadable
    ``mesh.npz`` is warned about and left out (the mesh cache then serves, and a resume's
    mesh digest check still refuses another mesh)."""
    try:
        return register_run_mesh(run_dir)
    except MeshError as e:
        log.warning(f"{' '.join(str(e).split())}; building the mesh from the cache instead")
        return None


def fitted_mesh(stored: StoredMesh) -> ContextManager[None]:
    """Within: a body is built on ``stored`` or refused (one line naming what differs)."""
    return requiring(stored)
