"""The files of a simulated body, shared by a fit's outputs and ``simulate``.

``frames/frame_NNN.obj`` (the user's surface per frame, on the file's own vertices and
faces: :func:`file_surface`), ``body.vtu`` (the tet mesh for
ParaView with the field and a displacement per frame), and where ``usd-core`` is installed
``usd/frames.usda`` (the surface as a time-sampled USD point cache at ``/Simulated``,
layered over the user's stage when the animation came from USD, in its units) and
``usd/body.usda`` (the tet mesh as a ``UsdGeom.TetMesh`` with the field per tetrahedron as
a primvar, and the material as the deformable-physics draft names it: ``youngsModulus``,
``poissonsRatio``, ``density`` per tetrahedron and a physics material bound to the mesh),
``usd/material.usda`` (the field sampled at the rest vertices, ``primvars:youngsModulus``
on an ``over`` of the user's mesh prim, or on a ``/Rest`` mesh for a folder or glTF
animation). Every modulus is written in the units :func:`modulus_units` gives (pascals, or
relative to ``problem.E0``), said on each attribute (``customData``, ``documentation``)
and in the VTU field's name. ``rig.json``: the rig the body was attached with (its bones,
lengths, attach radius, driven vertices per bone, each authored or derived and how:
:func:`torchfit.mesh.rig_description`). Folders are filled beside their name and renamed when whole, single files
written to a temporary name and renamed: a kill or a full disk leaves no part.
"""
from __future__ import annotations

import dataclasses
import importlib.util
import logging
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..mesh import write_obj
from ..problems import EmbeddedSurfaceProblem
from .progress import PROGRESS_LOGGER
from .results import write_folder, write_json

VTU_FILE = "body.vtu"
#: the per-vertex Young's modulus on the user's mesh (an over of its prim)
MATERIAL_FILE = "material.usda"
#: the density written with the material (kg/m^3): a quasistatic fit does not determine it
DENSITY = 1000.0
DENSITY_SOURCE = "assumed 1000 kg/m^3 (water): a quasistatic fit does not determine it"
FRAMES_DIR = "frames"
#: ``customData`` ``torchfit:determined`` of the material a not-determined fit writes
NOT_DETERMINED = ("false: the data determine no material; this is the field the fit started "
                  "from, not a fitted one (identifiability.json)")
RIG_FILE = "rig.json"
#: what the per-tetrahedron uncertainty of the modulus in ``body.usda`` is
BAND_UNITS = ("factor, 1 (dimensionless): the modulus lies within [E / factor, E * factor] "
              "at two standard deviations (Gauss-Newton posterior at the fitted point); inf: "
              "the data do not determine it")
USD_DIR = "usd"
USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")

progress = logging.getLogger(PROGRESS_LOGGER)


def file_surface(problem: Any, surface: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The simulated surface ``(F, V, 3)`` on the user's file's own vertices (seams the
    reader welded split again: :mod:`torchfit.mesh.formats.seams`) and the file's faces."""
    animation = problem.animation
    return animation.file_points(surface), np.asarray(animation.output_faces)


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


def vtu_cell_data(problem: Any, field: np.ndarray,
                  truth: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The cell fields of ``body.vtu``: the modulus ``field`` ``(m,)`` (and a known
    ``truth``) in the units of :func:`modulus_units`, named with them (``E_Pa``,
    ``E_relative_to_E0``; ``E_true_...``), and the region labels."""
    units = modulus_units(problem)
    data = {units.vtu_name: np.asarray(field, dtype=np.float64) * units.factor}
    if truth is not None:
        data[units.vtu_name.replace("E_", "E_true_", 1)] = \
            np.asarray(truth, dtype=np.float64) * units.factor
    if problem.tet_regions is not None:
        data["region"] = np.asarray(problem.tet_regions, dtype=np.int32)
    return data


def _frame_times(names: Sequence[str]) -> list[float] | None:
    """The USD time codes of frames read from a stage (``<file>:<prim>@<time>``)."""
    try:
        return [float(str(n).rsplit("@", 1)[1]) for n in names]
    except (IndexError, ValueError):
        return None


def write_usd(run_dir: Path, problem: Any, surface: np.ndarray, field: np.ndarray,
              density: tuple[float, str] | None = None,
              damping: dict[str, Any] | None = None, band: np.ndarray | None = None,
              kept_start: bool = False) -> list[Path]:
    """``usd/frames.usda`` and ``usd/body.usda`` (module docstring); nothing, with a log
    line, where ``usd-core`` is not installed. ``density``: the material's density (kg/m^3)
    and where it comes from (the problem's :meth:`material_density`); ``None``: the assumed
    :data:`DENSITY`. ``damping``: a body in time's fitted damping (:func:`fitted_damping`),
    written beside the modulus (:func:`write_damping_attributes`). ``band``: ``(m,)`` the
    modulus' two-sigma band per tetrahedron (the fit's uncertainty: :data:`BAND_UNITS`),
    written to ``body.usda`` as ``primvars:torchfit:youngs_modulus_band``. ``kept_start``:
    the data determine no material and ``field`` is the fit's start, said on every material
    attribute (``customData`` ``torchfit:determined``, :data:`NOT_DETERMINED`)."""
    if importlib.util.find_spec("pxr") is None:
        progress.info("no USD output: install the extra torchfit[usd] (usd-core) for it")
        return []
    from ..mesh.formats.usd import (write_point_cache_usd, write_tet_mesh_usd,
                                    write_vertex_field_usd)

    source = Path(str(problem.animation.path))
    over = source if source.suffix.lower() in USD_SUFFIXES and source.is_file() else None
    # the time codes of the frames written: a stage's own, else the animation's frame
    # numbers (a subset of frames plays at its place in the shot, not packed from 0)
    times = _frame_times(problem.frame_names()) if over is not None else None
    if times is None:
        times = [float(n) for n in problem.frame_numbers()]
    surface, faces = file_surface(problem, surface)
    cells = np.asarray(problem.mesh.cells)
    units = modulus_units(problem)
    field = np.asarray(field, dtype=np.float64) * units.factor
    fields = {"youngs_modulus": field}
    if problem.tet_regions is not None:
        fields["region"] = np.asarray(problem.tet_regions, dtype=np.int32)
    labels = {"youngs_modulus": units.unit, "youngsModulus": units.unit,
              "poissonsRatio": "1 (dimensionless)", "density": "kg/m^3",
              "youngs_modulus_band": BAND_UNITS}
    if band is not None:
        fields["youngs_modulus_band"] = np.asarray(band, dtype=np.float64)
    density_value, density_source = (DENSITY, DENSITY_SOURCE) if density is None else density
    material = {"youngsModulus": field, "poissonsRatio": np.full(len(cells), problem.cfg.nu),
                "density": np.full(len(cells), float(density_value))}
    custom = {**units.custom(), "torchfit:densitySource": density_source}
    if kept_start:
        custom["torchfit:determined"] = NOT_DETERMINED
    per_vertex = vertex_field(problem, field)

    def fill(partial: Path) -> None:
        write_point_cache_usd(partial / "frames.usda", faces, surface, times=times, over=over,
                              fps=float(getattr(problem.animation, "fps", 24.0)))
        write_tet_mesh_usd(partial / "body.usda", np.asarray(problem.mesh.points), cells, fields,
                           material=material, custom=custom, units=labels)
        if per_vertex is not None:
            animation = problem.animation
            write_vertex_field_usd(partial / MATERIAL_FILE, "youngsModulus", per_vertex,
                                   over=over, prim=animation.prim if over is not None else "",
                                   rest=animation.file_points(animation.rest_vertices),
                                   faces=faces, custom=custom, units=labels)
        if damping is not None:
            write_damping_attributes([partial / "body.usda"] + (
                [partial / MATERIAL_FILE] if per_vertex is not None else []), damping)

    folder = run_dir / USD_DIR
    write_folder(folder, fill)
    return [folder / "frames.usda", folder / "body.usda"] + (
        [folder / MATERIAL_FILE] if per_vertex is not None else [])


#: the damping attributes written beside the modulus: (attribute, key of the damping report,
#: unit, what it is). The OpenUSD deformable-physics draft names no damping, so they are
#: torchfit's own (docs/guide/dcc.md).
DAMPING_ATTRIBUTES = (
    ("torchfit:rayleighAlpha", "alpha", "1/s",
     "Rayleigh mass damping alpha of C = alpha M + beta K (fitted)"),
    ("torchfit:rayleighBeta", "beta", "s",
     "Rayleigh stiffness damping beta of C = alpha M + beta K (fitted)"),
    ("torchfit:dampingRatioLowestMode", "zeta_w1", "1 (dimensionless)",
     "damping ratio alpha / (2 w1) + beta w1 / 2 at the body's lowest mode w1"),
    ("torchfit:lowestAngularFrequency", "w1", "rad/s",
     "w1: lowest angular frequency of K u = w^2 M u at the start's homogeneous material"),
)


def fitted_damping(problem: Any, theta: Any) -> dict[str, Any] | None:
    """The fitted damping of a problem in time at ``theta`` (its time model's
    ``damping_report``: alpha, beta, the band and ratios), ``None`` for frames independent
    of each other or where no band is known."""
    report = getattr(problem.time, "damping_report", None)
    if report is None:
        return None
    return report(problem.simulation_input(theta))


def write_damping_attributes(paths: Sequence[Path], damping: dict[str, Any]) -> None:
    """Add the fitted Rayleigh damping (:data:`DAMPING_ATTRIBUTES`: ``alpha`` in 1/s,
    ``beta`` in s, the damping ratio at the lowest mode and that mode's angular frequency)
    to every prim carrying ``primvars:youngsModulus`` in the layers ``paths`` (written
    just before: ``body.usda``'s TetMesh, ``material.usda``'s mesh), each attribute a
    ``double`` with its unit in ``customData`` (``torchfit:units``) and its meaning in
    ``documentation``. A value that is not known (no lowest mode) is left out."""
    from pxr import Sdf, Usd, UsdGeom

    for path in paths:
        layer = Sdf.Layer.FindOrOpen(str(path))
        stage = Usd.Stage.Open(layer)
        for prim in stage.Traverse():
            if not UsdGeom.PrimvarsAPI(prim).GetPrimvar("youngsModulus"):
                continue
            for name, key, unit, meaning in DAMPING_ATTRIBUTES:
                value = damping.get(key)
                if value is None:
                    continue
                attribute = prim.CreateAttribute(name, Sdf.ValueTypeNames.Double, custom=True)
                attribute.Set(float(value))
                attribute.SetCustomDataByKey("torchfit:units", unit)
                attribute.SetDocumentation(f"{meaning}, in {unit}")
        layer.Save()


@dataclasses.dataclass(frozen=True)
class ModulusUnits:
    """What a Young's modulus leaving the tool is: the fitted field times ``factor`` is in
    ``unit`` (``Pa``, or ``relative to problem.E0``: 1 is the homogeneous start).

    A scale-free body (every load a prescribed displacement: rig targets) determines the
    field only up to a factor, so its moduli are pascals only where ``problem.E0`` was
    given as one (``problem.E0_unit=Pa``); otherwise they are written divided by E0."""

    factor: float
    unit: str
    E0: float

    @property
    def vtu_name(self) -> str:
        """The VTU cell field's name, the unit in it (``E_Pa``, ``E_relative_to_E0``)."""
        return "E_Pa" if self.unit == "Pa" else "E_relative_to_E0"

    def custom(self) -> dict[str, str | float]:
        """``customData`` for USD prims and attributes."""
        data: dict[str, str | float] = {"torchfit:youngsModulusUnits": self.unit,
                                        "torchfit:E0": self.E0}
        if self.unit != "Pa":
            data["torchfit:toPascals"] = TO_PASCALS
        return data

    def as_dict(self) -> dict[str, str | float]:
        """For ``result.json``: the unit, E0, and how to turn the values into pascals."""
        out: dict[str, str | float] = {"unit": self.unit, "E0": self.E0,
                                       "written_as": "field / E0" if self.unit != "Pa"
                                       else "field"}
        if self.unit != "Pa":
            out["to_pascals"] = TO_PASCALS
        return out


#: how a relative modulus becomes one in pascals
TO_PASCALS = ("multiply by the homogeneous material's Young's modulus in Pa: the animation "
              "does not fix the scale (or fit with problem.E0=<Pa> problem.E0_unit=Pa)")


def modulus_units(problem: Any) -> ModulusUnits:
    """The units of ``problem``'s written moduli (:class:`ModulusUnits`): pascals where the
    problem is not scale-free or ``problem.E0_unit`` is ``Pa``, else relative to E0."""
    E0 = float(problem.cfg.E0)
    if not problem.scale_free or str(problem.cfg.E0_unit) == "Pa":
        return ModulusUnits(1.0, "Pa", E0)
    return ModulusUnits(1.0 / E0, "relative to problem.E0", E0)


def vertex_field(problem: Any, field: np.ndarray) -> np.ndarray | None:
    """The per-tetrahedron ``field`` sampled at the user's rest vertices ``(V_file,)``: the
    volume-weighted mean of the tetrahedra at each tet vertex, interpolated with each surface
    vertex's embedding weights; ``None`` for a problem without an embedded surface."""
    if not isinstance(problem, EmbeddedSurfaceProblem):
        return None
    points, cells = np.asarray(problem.mesh.points), np.asarray(problem.mesh.cells)
    volumes = np.abs(np.linalg.det(points[cells[:, 1:]] - points[cells[:, :1]])) / 6.0
    total = np.zeros(len(points))
    weight = np.zeros(len(points))
    np.add.at(total, cells.reshape(-1), np.repeat(field * volumes, 4))
    np.add.at(weight, cells.reshape(-1), np.repeat(volumes, 4))
    nodes = total / np.maximum(weight, 1e-300)
    values = np.einsum("vk,vk->v", nodes[cells[problem.embedding.cells]],
                       problem.embedding.weights)
    return problem.animation.file_values(values)


def write_rig(run_dir: Path, problem: Any) -> list[Path]:
    """``rig.json``: the problem's attached rig (``problem.rig_description``); nothing for a
    body driven by surface vertices."""
    description = getattr(problem, "rig_description", None)
    if description is None:
        return []
    return [write_json(Path(run_dir) / RIG_FILE, description)]
