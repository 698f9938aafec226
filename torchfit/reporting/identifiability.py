"""The files of a run's identifiability report: ``identifiability.json``, ``.vtu`` and ``.png``.

The report itself is computed by the run (:mod:`torchfit.run.identifiability`); this module
only writes what it is handed:

``identifiability.json``
    the report (:meth:`~torchfit.run.identifiability.Identifiability.as_json`): whether the
    data determine the material, per parameter its sensitivity, relative sensitivity and
    flag, the singular values and effective rank, per region the fraction determined.
``identifiability.vtu``
    a mesh problem's cells (rest positions, ParaView) with cell data ``sensitivity`` (the
    relative sensitivity of the parameters each cell depends on) and ``determined`` (the
    weight of determined parameters, 0 to 1), and ``region`` where the body has labels.
``identifiability.png``
    the parameters' relative sensitivities, largest first, against the threshold, and the
    singular values relative to the largest (where the Jacobian was dense).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .figures import save_png
from .guard import PlotGuard
from .results import write_json

JSON_FILE = "identifiability.json"
VTU_FILE = "identifiability.vtu"
PNG_FILE = "identifiability.png"
_CELL_TYPES = {4: "tetra", 3: "triangle", 2: "line"}


def write_identifiability(run_dir: Path, mesh: Any, regions: np.ndarray | None,
                          report: Mapping[str, Any],
                          cell_fields: Mapping[str, np.ndarray | None],
                          guard: PlotGuard) -> list[Path]:
    """Write the three files (module docstring); returns those written. ``mesh``: the
    problem's simplicial mesh (``points``, ``cells``) or ``None``; ``regions``: a region label
    per cell or ``None``; ``cell_fields``: ``sensitivity`` and ``determined`` per field
    element (``None``: no VTU)."""
    files = [write_json(run_dir / JSON_FILE, dict(report))]
    fields = {k: v for k, v in cell_fields.items() if v is not None}
    if mesh is not None and fields and all(len(v) == len(mesh.cells) for v in fields.values()):
        written = guard.run("the identifiability VTU", _write_vtu, run_dir / VTU_FILE, mesh,
                            regions, fields)
        files.extend(written or [])
    picture = guard.run("the identifiability picture", _write_png, run_dir / PNG_FILE, report)
    files.extend(picture or [])
    return files


def _write_vtu(path: Path, mesh: Any, regions: np.ndarray | None,
               fields: Mapping[str, np.ndarray]) -> list[Path]:
    import meshio

    cells = np.asarray(mesh.cells)
    points = np.asarray(mesh.points, dtype=np.float64)
    if points.shape[1] < 3:
        points = np.pad(points, ((0, 0), (0, 3 - points.shape[1])))
    cell_data = {name: [np.asarray(values, dtype=np.float64)] for name, values in fields.items()}
    if regions is not None and len(regions) == len(cells):
        cell_data["region"] = [np.asarray(regions, dtype=np.int32)]
    written = meshio.Mesh(points, [(_CELL_TYPES[cells.shape[1]], cells)], cell_data=cell_data)
    tmp = path.with_name(path.name + ".tmp.vtu")
    meshio.write(str(tmp), written)
    tmp.replace(path)
    return [path]


def _write_png(path: Path, report: Mapping[str, Any]) -> list[Path]:
    from matplotlib.figure import Figure

    relative = np.asarray(report["parameters"]["relative"], dtype=np.float64)
    flags = np.asarray(report["parameters"]["determined"], dtype=bool)
    threshold = float(report["thresholds"]["relative"])
    values = report.get("singular_values")
    fig = Figure(figsize=(9 if values else 5.5, 3.6), dpi=100)
    axes = fig.subplots(1, 2 if values else 1, squeeze=False)[0]
    order = np.argsort(-relative, kind="stable")
    floor = 1e-12
    shown = np.maximum(relative[order], floor)
    ranks = np.arange(1, len(order) + 1)
    axes[0].bar(ranks[flags[order]], shown[flags[order]], width=1.0, color="tab:blue",
                label=f"determined ({int(flags.sum())})")
    axes[0].bar(ranks[~flags[order]], shown[~flags[order]], width=1.0, color="tab:gray",
                label=f"not determined ({int((~flags).sum())})")
    axes[0].axhline(threshold, color="tab:red", lw=1, ls="--", label=f"threshold {threshold:g}")
    axes[0].set_yscale("log")
    axes[0].set_ylim(floor, 2.0)
    axes[0].set_xlabel("parameter, by sensitivity")
    axes[0].set_ylabel("sensitivity / largest")
    axes[0].legend(fontsize=7, loc="lower left")
    if values:
        sv = np.asarray(values, dtype=np.float64)
        sv = np.maximum(sv / sv.max(), floor) if sv.max() > 0 else np.full_like(sv, floor)
        axes[1].semilogy(np.arange(1, len(sv) + 1), sv, ".-", color="tab:blue")
        axes[1].axhline(threshold, color="tab:red", lw=1, ls="--")
        axes[1].set_ylim(floor, 2.0)
        axes[1].set_xlabel("index")
        axes[1].set_ylabel("singular value / largest")
        axes[1].set_title(f"effective rank {report.get('effective_rank')}", fontsize=9)
    verdict = "determined by the data" if report["determined"] else "NOT determined by the data"
    fig.suptitle(f"identifiability: {verdict}, {report['n_determined']} of "
                 f"{report['n_params']} parameters", fontsize=10)
    fig.tight_layout()
    save_png(fig, path)
    return [path]
