"""The files of ``simulate`` (a fitted material on an animation of the same body).

Into the simulation's directory:

``frames/frame_NNN.obj``
    the simulated surface of every frame on the user's own vertices and faces (the
    file's vertex count and order, its seams split as it has them; 17 significant digits);
``body.vtu``
    the tetrahedral mesh at rest for ParaView (meshio): cell data ``E`` (the fitted field),
    ``region``; point data ``displacement_NNN`` per frame (``Warp By Vector`` shows one);
``frames.npz``
    ``rest_points``, ``cells``, ``positions`` ``(F, n, 3)`` of the tetrahedron vertices,
    ``surface`` ``(F, V, 3)`` of the user's vertices, ``field``;
``simulation.png``
    the frame of largest mean surface error: the animation | the simulation coloured by
    its distance to the animation (a colour bar in mm), through the body's camera
    (``view_axes``: the file's up axis up);
``result.json``
    written by the caller (:mod:`torchfit.run.simulating`).

:func:`write_frames` is the one function that writes the simulated frames (every format a
frame sequence goes out in; a new format is a line there). Nothing here simulates.
"""
from __future__ import annotations

import io
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from torch import Tensor

from .body import surface_figure
from .body_files import (FRAMES_DIR, VTU_FILE, file_surface, vtu_cell_data, write_body_vtu,
                         write_obj_sequence, write_usd)
from .figures import save_png
from .results import atomic_write

SIMULATION_PNG = "simulation.png"
FRAMES_NPZ = "frames.npz"


def _numpy(x: Tensor) -> np.ndarray:
    return x.detach().cpu().numpy()


def write_frames(run_dir: Path, problem: Any, x: Tensor, field: Tensor,
                 density: tuple[float, str] | None = None,
                 damping: dict[str, Any] | None = None) -> list[Path]:
    """Every output of the simulated frames ``x`` ``(F, n, 3)`` (tet vertex positions) of a
    body problem with ``field`` per tetrahedron: the OBJ sequence, ``body.vtu``,
    ``frames.npz`` and the USD files (:mod:`.body_files`; ``density``: as for
    :func:`~.body_files.write_usd`; ``damping``: a body in time's fitted damping, for the
    USD layers); returns the files written."""
    surface = _numpy(problem.observation.surface(x))
    positions = _numpy(x)
    cell_data = vtu_cell_data(problem, _numpy(field))
    return [*write_obj_sequence(run_dir / FRAMES_DIR, *file_surface(problem, surface)),
            write_body_vtu(run_dir / VTU_FILE, np.asarray(problem.mesh.points),
                           problem.mesh.cells, positions, cell_data),
            _write_npz(run_dir / FRAMES_NPZ, problem, positions,
                       file_surface(problem, surface)[0], _numpy(field)),
            *write_usd(run_dir, problem, surface, _numpy(field), density, damping)]


def _write_npz(path: Path, problem: Any, positions: np.ndarray, surface: np.ndarray,
               field: np.ndarray) -> Path:
    buffer = io.BytesIO()
    np.savez_compressed(buffer, rest_points=problem.mesh.points, cells=problem.mesh.cells,
                        positions=positions, surface=surface, field=field)
    atomic_write(path, lambda f: f.write(buffer.getvalue()))
    return path


def comparison_picture(run_dir: Path, problem: Any, x: Tensor, frame: int,
                       frame_names: Sequence[str]) -> Path:
    """``simulation.png``: the animation at ``frame`` beside the simulation, coloured by the
    distance of every surface vertex to the animation's."""
    error = _numpy(problem.observation.surface_error_field(x, problem.x_true))[frame]
    vmax = float(error.max()) or 1.0
    target = _numpy(problem.observation.clean_surface(problem.x_true))[frame]
    panels = [("animation (target)", target, None),
              (f"simulated, fitted E\nmean error {1e3 * float(error.mean()):.2f} mm",
               _numpy(problem.observation.surface(x))[frame], error)]
    fig = surface_figure(panels, np.asarray(problem.animation.faces), vmax,
                         title=f"{frame_names[frame]} (colour: surface error, 0 to "
                               f"{1e3 * vmax:.2f} mm)",
                         view=getattr(problem, "view_axes", None))
    path = run_dir / SIMULATION_PNG
    save_png(fig, path)
    return path
