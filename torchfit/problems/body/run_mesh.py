"""A body problem's tetrahedral mesh kept in its run directory (``mesh.npz``), for the run layer.

A fit of a body writes the mesh it uses before its first checkpoint (:func:`keep_mesh`). A
resume reads it back (:func:`resumed_mesh`) and hands it to
:func:`torchfit.problems.build_problem` (``kept_mesh=``), which builds the body on that mesh
whatever the mesh cache holds (a resume on another machine, or after a cache clean,
where the entry is gone); ``simulate`` hands it over as required (:func:`fitted_mesh`), so any
other rest surface or tetrahedralisation option is refused. The file format and the
matching: :mod:`torchfit.mesh.tetwild.store`.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from ...mesh import MeshError
from ...mesh import (RUN_MESH_FILE, KeptMesh, StoredMesh, read_kept_mesh, read_run_mesh,
                     write_run_mesh)

__all__ = ["RUN_MESH_FILE", "KeptMesh", "StoredMesh", "fitted_mesh", "keep_mesh",
           "read_run_mesh", "resumed_mesh"]

log = logging.getLogger("torchfit.problems")


def resumed_mesh(run_dir: str | Path) -> KeptMesh | None:
    """The mesh ``run_dir`` keeps, for building its bodies again (a resume, a torchrun
    worker); ``None`` where it keeps none. An unreadable ``mesh.npz`` is warned about and
    left out (the mesh cache then serves, and a resume's mesh digest check still refuses
    another mesh)."""
    try:
        return read_kept_mesh(run_dir)
    except MeshError as e:
        log.warning("%s; building the mesh from the cache instead", " ".join(str(e).split()))
        return None


def fitted_mesh(stored: StoredMesh) -> KeptMesh:
    """``stored`` as the mesh a body must be built on (``simulate``): another surface or
    option is refused in one line naming what differs."""
    return KeptMesh(stored, required=True)


def keep_mesh(body: Any, run_dir: str | Path) -> Path | None:
    """``body``'s tetrahedral mesh into ``run_dir/mesh.npz`` (with the rest surface it was
    made of, the options, the regions and the grid's frame) so that a resume or ``simulate``
    needs no cache; an existing one is left as it is (a resume passed the checkpoint's mesh
    digest, so it is the same mesh). Returns the path written, or ``None``."""
    path = Path(run_dir) / RUN_MESH_FILE
    if path.exists() or path.is_symlink():
        return None
    a = body.animation
    return write_run_mesh(path, body.tet, body.tet_options, a.rest_vertices, a.faces,
                          body.tet_regions, (body.grid.origin, body.grid.axes))
