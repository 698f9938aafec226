"""A run's own copy of its tetrahedral mesh (``mesh.npz``), and tetrahedralisation that uses it.

fTetWild is not deterministic: the on-disk cache (:mod:`.cache`) is what gives the same
surface the same tetrahedra. A fit keeps the mesh it used in its run directory
(:func:`write_run_mesh`), so that a resume, or ``simulate`` of the fitted material on
another machine, needs no cache: the run reads it back (:func:`read_kept_mesh`) and hands
it to the body's build as a :class:`KeptMesh`, whose :func:`tetrahedralize_kept` returns
it for its own surface and options before the cache is looked at; a ``required`` one
(``simulate``) refuses any other surface or options instead of tetrahedralising them.

``mesh.npz`` holds ``points`` ``(n, 3)`` float64, ``cells`` ``(m, 4)`` int64, ``regions``
``(m,)`` int64 (``-1`` everywhere without region labels), ``surface_vertices`` and
``surface_faces`` (the rest surface that was tetrahedralised), and ``meta`` (JSON: the cache
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
from .tetrahedralize import TetMesh, TetOptions, pytetwild_version, tetrahedralize

#: The file a run keeps its mesh in.
RUN_MESH_FILE = "mesh.npz"
_FORMAT = "torchfit-run-mesh-1"


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

    def matches(self, vertices: np.ndarray, faces: np.ndarray, options: TetOptions) -> bool:
        """Whether this mesh was built from the rest surface ``vertices``, ``faces`` with
        ``options`` (compared as given: a body tetrahedralised in its own frame is matched
        on its surface, not on the frame's cache key)."""
        return self.difference(vertices, faces, options) == ""

    def difference(self, vertices: np.ndarray, faces: np.ndarray, options: TetOptions) -> str:
        """What differs between this mesh's input and ``vertices``/``faces``/``options``
        (one phrase; ``""``: nothing)."""
        v, f = np.asarray(vertices, dtype=np.float64), np.asarray(faces)
        if v.shape != self.surface_vertices.shape or f.shape != self.surface_faces.shape:
            return (f"its rest surface has {len(v)} vertices and {len(f)} faces, the fitted "
                    f"body's {len(self.surface_vertices)} and {len(self.surface_faces)}")
        if not np.array_equal(f, self.surface_faces):
            return "its rest surface's faces differ from the fitted body's"
        if not np.array_equal(v, self.surface_vertices):
            moved = float(np.abs(v - self.surface_vertices).max())
            return (f"its rest surface's vertices differ from the fitted body's (by up to "
                    f"{moved:.3g})")
        ours = options.as_dict()
        changed = sorted(k for k in ours if ours[k] != self.options.get(k))
        if changed:
            return "tetrahedralisation options differ (" + ", ".join(
                f"{k}: {self.options.get(k)!r} fitted, {ours[k]!r} now" for k in changed) + ")"
        return ""

    def tet_mesh(self, seconds: float) -> TetMesh:
        return TetMesh(self.points, self.cells, self.key, True, seconds, self.build_seconds,
                       self.path)


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
    except Exception as e:  # noqa: BLE001  (a truncated, foreign or corrupt file)
        first = (str(e).strip().splitlines() or [type(e).__name__])[0][:160]
        raise MeshError(f"{path} is not a torchfit run mesh ({first})") from None
    if arrays["points"].ndim != 2 or arrays["cells"].ndim != 2 or arrays["cells"].shape[1] != 4:
        raise MeshError(f"{path} is not a torchfit run mesh (points {arrays['points'].shape}, "
                        f"cells {arrays['cells'].shape})")
    return StoredMesh(**arrays, key=str(meta["key"]), version=str(meta["version"]),
                      options=dict(meta["options"]), build_seconds=float(meta["build_seconds"]),
                      path=path, frame=frame)


@dataclasses.dataclass(frozen=True)
class KeptMesh:
    """A run's own mesh handed to the build of a body (an explicit input, no registry).

    Used for its own rest surface and options instead of the cache; with ``required``
    (``simulate`` of a fitted material) any other surface or option is refused rather than
    tetrahedralised, since the fitted field lives on these tetrahedra.
    """

    stored: StoredMesh
    required: bool = False

    def mesh_for(self, vertices: np.ndarray, faces: np.ndarray, options: TetOptions
                 ) -> TetMesh | None:
        """The kept mesh where ``vertices``, ``faces`` and ``options`` are its own, else
        ``None``; raises :class:`~..simplicial.MeshError` naming what differs where the mesh
        is ``required``."""
        start = time.perf_counter()
        if self.stored.matches(vertices, faces, options):
            return self.stored.tet_mesh(time.perf_counter() - start)
        if self.required:
            why = self.stored.difference(vertices, faces, options) or "its cache key differs"
            raise MeshError(f"not the fitted body: {why}; the fitted material applies to "
                            "animations of the same rest surface")
        return None

    def frame_for(self, vertices: np.ndarray, faces: np.ndarray, options: TetOptions
                  ) -> tuple[np.ndarray, np.ndarray] | None:
        """The body frame recorded with the kept mesh, where the surface and options are
        its own (a new animation of the body keeps the fitted grid), else ``None``."""
        if self.stored.frame is not None and self.stored.matches(vertices, faces, options):
            return self.stored.frame
        return None


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
