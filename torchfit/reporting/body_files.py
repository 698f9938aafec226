"""The files of a simulated body, shared by a fit's outputs and ``simulate``.

``frames/frame_NNN.obj`` (the user's surface per frame), ``body.vtu`` (the tet mesh for
ParaView with the field and a displacement per frame), and where ``usd-core`` is installed
``usd/frames.usda`` (the surface as a time-sampled USD point cache at ``/Simulated``,
layered over the user's stage when the animation came from USD, in its units) and
``usd/body.usda`` (the tet mesh as a ``UsdGeom.TetMesh`` with the field per tetrahedron as
a primvar). Folders are filled beside their name and renamed when whole, single files
written to a temporary name and renamed: a kill or a full disk leaves no part.
"""
from __future__ import annotations

import importlib.util
import logging
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..mesh import write_obj
from .progress import PROGRESS_LOGGER
from .results import write_folder

VTU_FILE = "body.vtu"
FRAMES_DIR = "frames"
USD_DIR = "usd"
USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")

progress = logging.getLogger(PROGRESS_LOGGER)


def write_obj_sequence(folder: Path, surface: np.ndarray, faces: np.ndarray) -> list[Path]:
    """``folder/frame_NNN.obj`` for every frame of ``surface`` ``(F, V, 3)`` on ``faces``."""
    names = [f"frame_{f:03d}.obj" for f in range(surface.shape[0])]

    def fill(partial: Path) -> None:
        for f, name in enumerate(names):
            write_obj(partial / name, surface[f], faces)

    write_folder(folder, fill)
    return [folder / name for name in names]


def write_body_vtu(path: Path, points: np.ndarray, cells: np.ndarray, positions: np.ndarray,
                   cell_data: dict[str, np.ndarray]) -> Path:
    """The tet mesh at rest (``points`` ``(n, 3)``, ``cells`` ``(m, 4)``) with each cell
    field ``(m,)`` and ``displacement_NNN`` per frame of ``positions`` ``(F, n, 3)``."""
    import meshio

    point_data = {f"displacement_{f:03d}": positions[f] - points
                  for f in range(positions.shape[0])}
    mesh = meshio.Mesh(points, [("tetra", np.asarray(cells))], point_data=point_data,
                       cell_data={k: [np.asarray(v)] for k, v in cell_data.items()})
    tmp = path.with_name(path.name + ".tmp.vtu")
    try:
        meshio.write(str(tmp), mesh)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def _frame_times(names: Sequence[str]) -> list[float] | None:
    """The USD time codes of frames read from a stage (``<file>:<prim>@<time>``)."""
    try:
        return [float(str(n).rsplit("@", 1)[1]) for n in names]
    except (IndexError, ValueError):
        return None


def write_usd(run_dir: Path, problem: Any, surface: np.ndarray, field: np.ndarray) -> list[Path]:
    """``usd/frames.usda`` and ``usd/body.usda`` (module docstring); nothing, with a log
    line, where ``usd-core`` is not installed."""
    if importlib.util.find_spec("pxr") is None:
        progress.info("no USD output: install the extra torchfit[usd] (usd-core) for it")
        return []
    from ..mesh.formats.usd.writer import write_point_cache_usd, write_tet_mesh_usd

    source = Path(str(problem.animation.path))
    over = source if source.suffix.lower() in USD_SUFFIXES and source.is_file() else None
    times = _frame_times(problem.frame_names()) if over is not None else None
    faces = np.asarray(problem.animation.faces)
    cells = np.asarray(problem.mesh.cells)
    fields = {"youngs_modulus": field}
    if problem.tet_regions is not None:
        fields["region"] = np.asarray(problem.tet_regions, dtype=np.int32)

    def fill(partial: Path) -> None:
        write_point_cache_usd(partial / "frames.usda", faces, surface, times=times, over=over)
        write_tet_mesh_usd(partial / "body.usda", np.asarray(problem.mesh.points), cells, fields)

    folder = run_dir / USD_DIR
    write_folder(folder, fill)
    return [folder / "frames.usda", folder / "body.usda"]
