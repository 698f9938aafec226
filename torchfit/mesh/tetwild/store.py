"""A run's own copy of its tetrahedral mesh (``mesh.npz``), and tetrahedralisation that uses it.

fTetWild is not deterministic: the on-disk cache (:mod:`.tetrahedralize`) is what gives the
same surface the same tetrahedra. A fit keeps the mesh it used in its run directory
(:func:`write_run_mesh`), so that a resume, or ``simulate`` of the fitted material on
another machine, needs no cache: :func:`register_run_mesh` makes every later
:func:`tetrahedralize_kept` of the same surface and options return that mesh (before the
cache is looked at), and :func:`requiring` (``simulate``) refuses any other surface or
options instead of tetrahedralising it.

``mesh.npz`` holds ``points`` ``(n, 3)`` float64, ``cells`` ``(m, 4)`` int64, ``regions``
``(m,)`` int64 (``-1`` everywhere without region labels), ``surface_vertices`` and
``surface_faces`` (the rest surface that was tetrahedralised), and ``meta`` (JSON: the cache
``key``, the pytetwild ``version`` it was built with, the ``options``
(:meth:`~.tetrahedralize.TetOptions.as_dict`), ``build_seconds``). It is written atomically
(a temporary file, then a rename). Nothing here solves anything.
"""
from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import time
import zipfile
from pathlib import Path
from typing import Iterator

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


#: meshes of runs this process registered, by cache key
_REGISTERED: dict[str, StoredMesh] = {}
#: the mesh :func:`requiring` demands (``simulate``), or ``None``
_REQUIRED: list[StoredMesh] = []


def register_run_mesh(run_dir: str | Path) -> StoredMesh | None:
    """Make the mesh kept in ``run_dir`` (its ``mesh.npz``) the one every later
    :func:`tetrahedralize_kept` of the same surface and options returns, in this process
    (a resume without the cache entry); ``None`` where the run has no ``mesh.npz``.
    Raises :class:`~.simplicial.MeshError` for an unreadable one."""
    path = Path(run_dir) / RUN_MESH_FILE
    if not path.is_file():
        return None
    stored = read_run_mesh(path)
    _REGISTERED[stored.key] = stored
    return stored


@contextlib.contextmanager
def requiring(stored: StoredMesh) -> Iterator[None]:
    """Within: :func:`tetrahedralize_kept` returns ``stored`` for its own surface and
    options and raises :class:`~.simplicial.MeshError` naming what differs for any other
    (nothing is tetrahedralised)."""
    _REQUIRED.append(stored)
    try:
        yield
    finally:
        _REQUIRED.remove(stored)


def kept_mesh(vertices: np.ndarray, faces: np.ndarray, options: TetOptions) -> TetMesh | None:
    """The run mesh registered for this surface and options (:func:`register_run_mesh`,
    :func:`requiring`), or ``None``; raises :class:`~.simplicial.MeshError` where one is
    required and this surface is not its own."""
    start = time.perf_counter()
    if _REQUIRED:
        stored = _REQUIRED[-1]
        if not stored.matches(vertices, faces, options):
            why = stored.difference(vertices, faces, options) or "its cache key differs"
            raise MeshError(f"not the fitted body: {why}; the fitted material applies to "
                            "animations of the same rest surface")
        return stored.tet_mesh(time.perf_counter() - start)
    for stored in _REGISTERED.values():
        if stored.matches(vertices, faces, options):
            return stored.tet_mesh(time.perf_counter() - start)
    return None


def kept_frame(vertices: np.ndarray, faces: np.ndarray, options: TetOptions
               ) -> tuple[np.ndarray, np.ndarray] | None:
    """The body frame recorded with the run mesh registered for this surface and options
    (:func:`kept_mesh`), or ``None``."""
    for stored in ([_REQUIRED[-1]] if _REQUIRED else list(_REGISTERED.values())):
        if stored.frame is not None and stored.matches(vertices, faces, options):
            return stored.frame
    return None


def tetrahedralize_kept(vertices: np.ndarray, faces: np.ndarray, options: TetOptions,
                        cache_dir: str | Path | None = None, warn: bool = True) -> TetMesh:
    """:func:`~.tetrahedralize.tetrahedralize`, but a run mesh registered for this surface
    and options (:func:`kept_mesh`) comes first."""
    kept = kept_mesh(vertices, faces, options)
    if kept is not None:
        return kept
    return tetrahedralize(vertices, faces, options, cache_dir=cache_dir, warn=warn)
