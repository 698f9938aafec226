"""A run's own copy of its tetrahedral mesh (``mesh.npz``), and tetrahedralisation that uses it.

fTetWild is not deterministic: the on-disk cache (:mod:`.cache`) is what gives the same
surface the same tetrahedra. A fit keeps the mesh it used in its run directory
(:func:`write_run_mesh`), so that a resume, or ``simulate`` of the fitted material on
another machine, needs no cache: the run reads it back (:func:`read_kept_mesh`) and hands
it to the body's build as a :class:`KeptMesh`, whose :func:`tetrahedralize_kept` returns
it for its own surface and options before the cache is looked at; a ``required`` one
(``simulate``) refuses any other surface or options instead of tetrahedralising them.

**The same body from another file** (other axes, units, format, dtype, vertex or face
order, seams) is the same surface: where the mesh was made in canonical form
(:mod:`.canonical`) the file keeps that form's placement, and a surface handed over with
its own canonical form (``surface=``) matches when the two canonical surfaces are one
(:meth:`~.canonical.CanonicalSurface.difference`), or its welded vertices in their order
are the kept ones moved rigidly (a round body turned by another shot's motion), and their
sizes agree within
:data:`SCALE_MATCH` (the kept mesh is a physical body: a rescaled copy in the same unit is
another body, refused); the kept tetrahedra and the grid's frame are then mapped into the
new file's coordinates. Any other surface is refused in one line naming what differs.

``mesh.npz`` holds ``points`` ``(n, 3)`` float64, ``cells`` ``(m, 4)`` int64, ``regions``
``(m,)`` int64 (``-1`` everywhere without region labels), ``surface_vertices`` and
``surface_faces`` (the rest surface that was tetrahedralised), ``frame_origin`` and
``frame_axes`` (the grid's frame, where given), ``canonical_origin``, ``canonical_axes``,
``canonical_scale`` (the canonical form's placement, where the mesh was made in one), and ``meta`` (JSON: the cache
``key``, the pytetwild ``version`` it was built with, the ``options``
(:meth:`~.tetrahedralize.TetOptions.as_dict`), ``build_seconds``). It is written atomically
(a temporary file, then a rename). Nothing here solves anything.
"""
from __future__ import annotations

import dataclasses
import io
import json
import os
import time
import zipfile
from pathlib import Path

import numpy as np

from ..simplicial import MeshError
from .canonical import MATCH, CanonicalSurface, Placement, canonical_surface, welded_surface
from .tetrahedralize import TetMesh, TetOptions, pytetwild_version, tetrahedralize

#: The file a run keeps its mesh in.
RUN_MESH_FILE = "mesh.npz"
_FORMAT = "torchfit-run-mesh-1"
#: the kept body and a new file's agree in size within this (relative): float32 is 6e-8
SCALE_MATCH = 1e-6


@dataclasses.dataclass(eq=False)
class StoredMesh:
    """A tetrahedral mesh read from a run's ``mesh.npz`` (module docstring)."""

    points: np.ndarray
    cells: np.ndarray
    regions: np.ndarray
    surface_vertices: np.ndarray
    surface_faces: np.ndarray
    key: str
    version: str
    options: dict
    build_seconds: float
    path: Path
    #: the body's frame the run's grid was laid in, ``(origin (3,), axes (3, 3))``, or
    #: ``None`` (not recorded): a new animation of the body keeps the fitted grid
    frame: tuple[np.ndarray, np.ndarray] | None = None
    #: where the canonical form of the surface sat in the fitted file (module doc), or
    #: ``None`` (a mesh of the surface as given: matched on its exact surface only)
    placement: Placement | None = None

    def matches(self, vertices: np.ndarray, faces: np.ndarray, options: TetOptions,
                surface: CanonicalSurface | None = None) -> bool:
        """Whether this mesh was built from the rest surface ``vertices``, ``faces`` with
        ``options``: the same arrays, or (``surface``: their canonical form) the same body
        from another file (module doc)."""
        return self.difference(vertices, faces, options, surface) == ""

    def difference(self, vertices: np.ndarray, faces: np.ndarray, options: TetOptions,
                   surface: CanonicalSurface | None = None) -> str:
        """What differs between this mesh's input and ``vertices``/``faces``/``options``
        (one phrase; ``""``: nothing); with ``surface`` (their canonical form) the same
        body from another file matches too (:meth:`placement_for`)."""
        return self.placement_for(vertices, faces, options, surface)[1]

    def placement_for(self, vertices: np.ndarray, faces: np.ndarray, options: TetOptions,
                      surface: CanonicalSurface | None = None
                      ) -> tuple[Placement | None, str]:
        """``(placement, why)``: where this mesh's canonical coordinates sit in the file of
        ``vertices``, ``faces`` (``None``: the kept file itself, nothing to map), and ``""``;
        or ``(None, what differs)``. Another file matches (``surface``: its canonical form)
        where the canonical surfaces are one, or else (a round body whose frame its motion
        settles, turned by another shot's motion) where its welded vertices, in their
        order, are the kept ones moved rigidly (within the canonical match) with the same
        faces; in both cases at the same size (:data:`SCALE_MATCH`)."""
        exact = self._exact_difference(vertices, faces, options)
        if not exact or surface is None or self.placement is None or \
                exact.startswith("tetrahedralisation options"):
            return None, exact
        ours = self.canonical_surface()
        shape = ours.difference(surface)
        placement = surface.placement
        if shape:
            placement = self._moved_rigidly(vertices, faces)
            if placement is None:
                return None, f"not the fitted body's surface in any axes, order or seams: {shape}"
        ratio = placement.scale / self.placement.scale
        if abs(ratio - 1.0) > SCALE_MATCH:
            return None, (f"its rest surface is the fitted body's scaled by {ratio:.6g} (in "
                          "metres: check the file's unit, e.g. USD metersPerUnit)")
        return placement, ""

    def _moved_rigidly(self, vertices: np.ndarray, faces: np.ndarray) -> Placement | None:
        """The kept placement carried by the similarity ``y = s x R^T + t`` that takes the
        kept welded vertices onto ``vertices``' in their order, where it fits within
        :data:`~.canonical.MATCH` of the radius and the faces are the same; else ``None``."""
        _, x, x_faces = welded_surface(self.surface_vertices, self.surface_faces)
        _, y, y_faces = welded_surface(vertices, faces)
        if x.shape != y.shape or not np.array_equal(x_faces, y_faces):
            return None
        x_mean, y_mean = x.mean(axis=0), y.mean(axis=0)
        u, sigma, vt = np.linalg.svd((y - y_mean).T @ (x - x_mean))
        if np.linalg.det(u @ vt) < 0:                              # a mirror image
            return None
        rotation = u @ vt
        scale = float(sigma.sum() / ((x - x_mean) ** 2).sum())
        shift = y_mean - scale * x_mean @ rotation.T
        radius = float(np.linalg.norm(y - y_mean, axis=1).max())
        if np.abs(scale * x @ rotation.T + shift - y).max() > MATCH * radius:
            return None
        kept = self.placement
        return Placement(scale * kept.origin @ rotation.T + shift, kept.axes @ rotation.T,
                         scale * kept.scale)

    def canonical_surface(self) -> CanonicalSurface:
        """The canonical form of the kept rest surface at its recorded placement."""
        return canonical_surface(self.surface_vertices, self.surface_faces,
                                 self.placement.origin, self.placement.axes)

    def _exact_difference(self, vertices: np.ndarray, faces: np.ndarray,
                          options: TetOptions) -> str:
        v, f = np.asarray(vertices, dtype=np.float64), np.asarray(faces)
        ours = options.as_dict()
        changed = sorted(k for k in ours if ours[k] != self.options.get(k))
        if changed:
            return "tetrahedralisation options differ (" + ", ".join(
                f"{k}: {self.options.get(k)!r} fitted, {ours[k]!r} now" for k in changed) + ")"
        if v.shape != self.surface_vertices.shape or f.shape != self.surface_faces.shape:
            return (f"its rest surface has {len(v)} vertices and {len(f)} faces, the fitted "
                    f"body's {len(self.surface_vertices)} and {len(self.surface_faces)}")
        if not np.array_equal(f, self.surface_faces):
            return "its rest surface's faces differ from the fitted body's"
        if not np.array_equal(v, self.surface_vertices):
            moved = float(np.abs(v - self.surface_vertices).max())
            return (f"its rest surface's vertices differ from the fitted body's (by up to "
                    f"{moved:.3g})")
        return ""

    def tet_mesh(self, seconds: float, surface: CanonicalSurface | None = None,
                 placement: Placement | None = None) -> TetMesh:
        """The kept mesh (made of ``surface``, a matching canonical form); with
        ``placement`` (:meth:`placement_for`: another file) its points mapped into that
        file's coordinates."""
        if placement is None or self.placement is None:
            return TetMesh(self.points, self.cells, self.key, True, seconds,
                           self.build_seconds, self.path, surface)
        points = placement.to_file(self.placement.from_file(self.points))
        return TetMesh(points, self.cells, self.key, True, seconds, self.build_seconds,
                       self.path, surface)

    def frame_in(self, placement: Placement | None) -> tuple[np.ndarray, np.ndarray]:
        """The grid's frame, mapped into another file by ``placement``
        (:meth:`placement_for`; ``None``: as kept)."""
        if placement is None or self.placement is None:
            return self.frame
        origin = placement.to_file(self.placement.from_file(self.frame[0]))
        return origin, self.placement.directions_to(placement, self.frame[1])


def write_run_mesh(path: str | Path, tet: TetMesh, options: TetOptions,
                   surface_vertices: np.ndarray, surface_faces: np.ndarray,
                   regions: np.ndarray | None = None,
                   frame: tuple[np.ndarray, np.ndarray] | None = None) -> Path:
    """Write ``mesh.npz`` (module docstring) atomically; returns its path."""

    path = Path(path)
    meta = {"format": _FORMAT, "key": tet.key, "version": _version_or_blank(pytetwild_version),
            "options": options.as_dict(), "build_seconds": float(tet.build_seconds)}
    labels = np.full(len(tet.cells), -1, dtype=np.int64) if regions is None else \
        np.asarray(regions, dtype=np.int64)
    arrays = {"points": np.asarray(tet.points, dtype=np.float64),
              "cells": np.asarray(tet.cells, dtype=np.int64), "regions": labels,
              "surface_vertices": np.asarray(surface_vertices, dtype=np.float64),
              "surface_faces": np.asarray(surface_faces, dtype=np.int64),
              "meta": np.array(json.dumps(meta, sort_keys=True))}
    if frame is not None:
        arrays["frame_origin"] = np.asarray(frame[0], dtype=np.float64)
        arrays["frame_axes"] = np.asarray(frame[1], dtype=np.float64)
    if tet.canonical is not None:
        placement = tet.canonical.placement
        arrays["canonical_origin"] = np.asarray(placement.origin, dtype=np.float64)
        arrays["canonical_axes"] = np.asarray(placement.axes, dtype=np.float64)
        arrays["canonical_scale"] = np.float64(placement.scale)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.0.tmp")   # a stale one is removed
    # by the run that next holds the directory (reporting.results.remove_stale_temporaries)
    # an .npz with fixed time stamps: the same mesh gives the same bytes
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, array in arrays.items():
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, array, allow_pickle=False)
            archive.writestr(zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0)),
                             buffer.getvalue(), compress_type=zipfile.ZIP_DEFLATED)
    os.replace(tmp, path)
    return path


def _version_or_blank(version) -> str:
    try:
        return version()
    except MeshError:
        return ""


def read_run_mesh(path: str | Path) -> StoredMesh:
    """Read a ``mesh.npz``; :class:`~.simplicial.MeshError` (one line) when it is not one."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            if meta.get("format") != _FORMAT:
                raise ValueError(f"format {meta.get('format')!r}, expected {_FORMAT!r}")
            arrays = {k: np.array(data[k]) for k in ("points", "cells", "regions",
                                                     "surface_vertices", "surface_faces")}
            frame = (np.array(data["frame_origin"]), np.array(data["frame_axes"])) \
                if "frame_axes" in data.files else None
            placement = Placement(np.array(data["canonical_origin"]),
                                  np.array(data["canonical_axes"]),
                                  float(data["canonical_scale"])) \
                if "canonical_axes" in data.files else None
    except Exception as e:  # noqa: BLE001  (a truncated, foreign or corrupt file)
        first = (str(e).strip().splitlines() or [type(e).__name__])[0][:160]
        raise MeshError(f"{path} is not a torchfit run mesh ({first})") from None
    if arrays["points"].ndim != 2 or arrays["cells"].ndim != 2 or arrays["cells"].shape[1] != 4:
        raise MeshError(f"{path} is not a torchfit run mesh (points {arrays['points'].shape}, "
                        f"cells {arrays['cells'].shape})")
    return StoredMesh(**arrays, key=str(meta["key"]), version=str(meta["version"]),
                      options=dict(meta["options"]), build_seconds=float(meta["build_seconds"]),
                      path=path, frame=frame, placement=placement)


@dataclasses.dataclass(frozen=True)
class KeptMesh:
    """A run's own mesh handed to the build of a body (an explicit input, no registry).

    Used for its own rest surface and options instead of the cache; with ``required``
    (``simulate`` of a fitted material) any other surface or option is refused rather than
    tetrahedralised, since the fitted field lives on these tetrahedra.
    """

    stored: StoredMesh
    required: bool = False

    def mesh_for(self, vertices: np.ndarray, faces: np.ndarray, options: TetOptions,
                 surface: CanonicalSurface | None = None) -> TetMesh | None:
        """The kept mesh where ``vertices``, ``faces`` and ``options`` are its own, or
        (``surface``: their canonical form) the same body from another file, mapped into
        its coordinates (module doc); else ``None``; raises
        :class:`~..simplicial.MeshError` naming what differs where the mesh is
        ``required``."""
        start = time.perf_counter()
        placement, why = self.stored.placement_for(vertices, faces, options, surface)
        if not why:
            return self.stored.tet_mesh(time.perf_counter() - start, surface, placement)
        if self.required:
            raise MeshError(f"not the fitted body: {why}; the fitted material applies to "
                            "animations of the same rest surface")
        return None

    def frame_for(self, vertices: np.ndarray, faces: np.ndarray, options: TetOptions,
                  surface: CanonicalSurface | None = None
                  ) -> tuple[np.ndarray, np.ndarray] | None:
        """The body frame recorded with the kept mesh, where the surface and options are
        its own (a new animation of the body keeps the fitted grid), mapped into the file
        of ``surface`` (their canonical form) where that is the same body from another
        file; else ``None``."""
        if self.stored.frame is None:
            return None
        placement, why = self.stored.placement_for(vertices, faces, options, surface)
        return None if why else self.stored.frame_in(placement)


def read_kept_mesh(run_dir: str | Path, required: bool = False) -> KeptMesh | None:
    """The mesh ``run_dir`` keeps (its ``mesh.npz``), ``None`` where it has none; raises
    :class:`~..simplicial.MeshError` for an unreadable one."""
    path = Path(run_dir) / RUN_MESH_FILE
    if not path.is_file():
        return None
    return KeptMesh(read_run_mesh(path), required)


def tetrahedralize_kept(vertices: np.ndarray, faces: np.ndarray, options: TetOptions,
                        kept: KeptMesh | None, cache_dir: str | Path | None = None,
                        warn: bool = True) -> TetMesh:
    """:func:`~.tetrahedralize.tetrahedralize`, but the ``kept`` mesh where it is this
    surface's (:meth:`KeptMesh.mesh_for`) comes first."""
    mesh = None if kept is None else kept.mesh_for(vertices, faces, options)
    if mesh is not None:
        return mesh
    return tetrahedralize(vertices, faces, options, cache_dir=cache_dir, warn=warn)
