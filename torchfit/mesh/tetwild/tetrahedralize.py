"""Tetrahedralisation of closed triangle surfaces with fTetWild (pytetwild), cached on disk.

The cache makes the same surface and options always give the same tetrahedra; nearly
closed surfaces are accepted too.

fTetWild is robust to imperfect surfaces but not deterministic (its output changes from
run to run and with the number of threads); the cache is what makes "the same input gives
the same fit" true: the first call stores the mesh under a key that hashes the input
(vertex and face bytes), the options and the pytetwild version, and every later call
returns the stored arrays bit for bit. A body's surface goes through its canonical form
instead (:mod:`.canonical`: one mesh whatever its axes, units, dtype, order or seams).

Conventions: ``points`` ``(n, 3)`` float64 in the unit of the surface's vertices, ``cells``
``(m, 4)`` int64, positively oriented (``det([p1 - p0, p2 - p0, p3 - p0]) > 0``), every
vertex referenced by some cell.

pytetwild is imported lazily (inside :func:`tetrahedralize`): the rest of ``torchfit.mesh``
works without it. Nothing here solves anything (see docs/architecture.md, layer ``mesh``).
"""
from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import tempfile
import time
import logging
from pathlib import Path

import numpy as np
import trimesh

from ...steps import count, step
from ..simplicial import signed_volumes
from ..surface import surface_volume, surface_warnings
from .cache import cache_key, default_cache_dir, read_entry, write_entry
from .options import TetMesh, TetOptions, TetrahedralizationError
from .size import build_for_count

log = logging.getLogger(__name__)

_NO_TETS = ("tetrahedralisation produced no tetrahedra: the surface is too broken to enclose "
            "a volume{reason}; repair it (close holes, remove self-intersections) or raise "
            "epsilon")
#: Accepted ratio of the tetrahedral volume to a closed surface's enclosed volume.
_VOLUME_RATIO = (0.7, 1.3)
#: Accepted ratio of the tetrahedral volume to the convex hull's for an open surface.
_HULL_RATIO = 1.1
#: seconds between two progress lines while pytetwild runs
HEARTBEAT_S = 10.0
#: the script that runs pytetwild in a child process
WORKER = Path(__file__).with_name("worker.py")


def tetrahedralize(vertices: np.ndarray, faces: np.ndarray,
                   options: TetOptions = TetOptions(),
                   cache_dir: str | Path | None = None, warn: bool = True,
                   use_cache: bool = True) -> TetMesh:
    """Tetrahedral mesh of the volume enclosed by a triangle surface (fTetWild), cached.

    Args:
        vertices: ``(n, 3)`` surface vertices (any length unit; the mesh uses the same).
        faces: ``(k, 3)`` vertex indices of the surface triangles.
        options: fTetWild's settings (:class:`TetOptions`).
        cache_dir: where meshes are stored; ``None`` (the default) means
            :func:`default_cache_dir` at call time.
        warn: emit a ``UserWarning`` naming what is wrong with an imperfect surface (open,
            non-manifold, badly wound, inside out, duplicate vertices), from
            :func:`~torchfit.mesh.surface.surface_warnings`.
        use_cache: ``False`` bypasses the cache (neither read nor written; the result then
            changes from call to call, as fTetWild's does).

    Returns:
        :class:`TetMesh`. A cache hit returns exactly the arrays of the first build.
        Cache files are written atomically (a temporary file, then a rename); an existing
        entry is never overwritten by a concurrent build (the first one stored wins and
        every caller gets it); an unreadable entry is reported with a warning and rebuilt.

    Raises:
        TetrahedralizationError: empty result (flat or broken surface), inverted
            tetrahedra, or a volume that does not match the surface: for a watertight
            surface the tetrahedral volume must be within [0.7, 1.3] times the enclosed
            volume; for an open one, positive and at most 1.1 times the convex hull's.
        ValueError: invalid options.

    fTetWild runs in a child process (:mod:`.worker`: pytetwild holds the GIL, and
    a crash of it ends only the child) working in a temporary directory (it leaves a
    ``__tracked_surface.stl`` there). Progress (:mod:`torchfit.steps`, logger
    ``torchfit.setup``): a line when it starts, one every ``HEARTBEAT_S`` seconds while
    pytetwild runs, and the tetrahedron count and the cache file at the end.
    """
    start = time.perf_counter()
    vertices, faces = _check_surface(vertices, faces)
    options.check()
    with step(step_line(len(faces), options)) as progress:
        mesh = _cached_or_built(vertices, faces, options, cache_dir, warn, use_cache, start,
                                progress)
        where = ("read from the cache " if mesh.from_cache else "built and cached in ") + \
            str(mesh.path) if mesh.path is not None else "built, not cached"
        progress.result = (f"{count(len(mesh.cells))} tetrahedra, {count(len(mesh.points))} "
                           f"vertices, {where}")
    return mesh


def step_line(n_faces: int, options: TetOptions) -> str:
    """The progress line of a tetrahedralisation: the face count and the size asked for."""
    size = f"edge length {options.edge_length_abs:.3g} (absolute)" if options.edge_length_abs \
        is not None else f"edge length {options.edge_length_fac:.3g} of the diagonal"
    if options.count is not None:
        size = f"about {count(options.count)} tetrahedra"
    return (f"tetrahedralising a surface of {count(n_faces)} faces (pytetwild: {size}"
            f"{'' if options.count else f', envelope {options.epsilon:.3g}'})")


def _cached_or_built(vertices: np.ndarray, faces: np.ndarray, options: TetOptions,
                     cache_dir: str | Path | None, warn: bool, use_cache: bool, start: float,
                     progress: step) -> TetMesh:
    """The body of :func:`tetrahedralize`: the cache entry, else a build stored in it."""
    surface = trimesh.Trimesh(vertices, faces, process=False)
    problems = surface_warnings(surface)
    if warn and problems:
        log.warning("surface given to tetrahedralize: " + "; ".join(problems))
    version = pytetwild_version()
    key = cache_key(vertices, faces, options, version)
    path: Path | None = None
    corrupt = False
    if use_cache:
        path = Path(default_cache_dir() if cache_dir is None else cache_dir) / f"{key}.npz"
        if path.exists():
            try:
                points, cells, build_seconds = read_entry(path, key)
            except Exception as e:                    # any unreadable entry is rebuilt
                log.warning(f"tetrahedral mesh cache file {path} is unreadable "
                            f"({type(e).__name__}: {' '.join(str(e).split())}); rebuilding it")
                corrupt = True
            else:
                return TetMesh(points, cells, key, True, time.perf_counter() - start,
                               build_seconds, path)

    if options.count is None:
        points, cells, build_seconds = build_surface(vertices, faces, options, progress)
        made = options
    else:
        points, cells, build_seconds, made = build_for_count(
            lambda trial: build_surface(vertices, faces, trial, progress), vertices, faces, options,
            progress)
        progress.beat(f"kept edge length {made.edge_length_fac:.3g}, envelope {made.epsilon:.3g}")
    check_volume(points, cells, surface, problems)
    from_cache = False
    if path is not None:
        stored = write_entry(path, key, points, cells, build_seconds, made, version,
                              overwrite=corrupt)
        if stored is None:
            path = None
        elif not stored:                              # another process stored it first
            points, cells, build_seconds = read_entry(path, key)
            from_cache = True
    return TetMesh(points, cells, key, from_cache, time.perf_counter() - start,
                   build_seconds, path)


def _check_surface(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise TetrahedralizationError(f"surface vertices must be a non-empty (n, 3) array, "
                                      f"got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise TetrahedralizationError(f"surface faces must be a non-empty (k, 3) array of "
                                      f"vertex indices, got shape {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise TetrahedralizationError(f"surface faces must be integer vertex indices, got "
                                      f"dtype {f.dtype}")
    f = f.astype(np.int64)
    if f.min() < 0 or f.max() >= len(v):
        raise TetrahedralizationError(f"a surface face refers to a vertex out of range "
                                      f"[0, {len(v)}); fix the face indices")
    bad = np.nonzero(~np.isfinite(v).all(axis=1))[0]
    if bad.size:
        raise TetrahedralizationError(f"surface vertex {int(bad[0])} is not finite "
                                      f"{v[bad[0]].tolist()}; fix or remove it")
    return np.ascontiguousarray(v), np.ascontiguousarray(f)


def _flatness(vertices: np.ndarray, faces: np.ndarray) -> tuple[float, float]:
    """Extent of the referenced vertices across their flattest direction, and the
    bounding-box diagonal."""
    p = vertices[np.unique(faces)]
    diagonal = float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
    centred = p - p.mean(axis=0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][-1]
    across = centred @ normal
    return float(across.max() - across.min()), diagonal


def _run_worker(folder: Path, progress: step | None) -> tuple[np.ndarray, np.ndarray]:
    """pytetwild in a child process (:mod:`.worker`) working in ``folder``, a
    heartbeat on ``progress`` every ``HEARTBEAT_S``; the child is killed if this is
    interrupted."""
    with open(folder / "worker.log", "wb") as log_file:
        child = subprocess.Popen([sys.executable, str(WORKER), str(folder)], cwd=folder,
                                 stdin=subprocess.DEVNULL, stdout=log_file, stderr=log_file)
        try:
            while True:
                try:
                    code = child.wait(timeout=HEARTBEAT_S)
                    break
                except subprocess.TimeoutExpired:
                    if progress is not None:
                        progress.beat("pytetwild running")
        finally:
            if child.poll() is None:
                child.kill()
                child.wait()
    if code != 0:
        lines = (folder / "worker.log").read_text(errors="replace").strip().splitlines()
        why = f"signal {signal.Signals(-code).name}" if code < 0 else f"exit status {code}"
        last = f": {' '.join(lines[-1].split())}" if lines else ""
        if "No module named 'pytetwild'" in last:
            raise TetrahedralizationError("pytetwild cannot be imported; install it with "
                                          "pip install 'pytetwild>=0.2,<0.3'")
        raise TetrahedralizationError(f"pytetwild failed ({why}{last}); repair the surface "
                                      "or change the options")
    with np.load(folder / "mesh.npz", allow_pickle=False) as mesh:
        return mesh["points"], mesh["cells"]


def build_surface(vertices: np.ndarray, faces: np.ndarray, options: TetOptions,
                  progress: step | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """fTetWild in a child process and a temporary working directory; unreferenced
    vertices dropped."""
    thickness, diagonal = _flatness(vertices, faces)
    if not thickness > options.epsilon * diagonal:
        # fTetWild finds nothing inside a surface thinner than its envelope, and crashes
        # (segmentation fault) on some exactly flat ones: never hand it those.
        raise TetrahedralizationError(_NO_TETS.format(
            reason=f" (it is flat: {thickness:.3g} thick across, within the envelope "
                   f"epsilon x diagonal = {options.epsilon * diagonal:.3g})"))
    opts = {k: v for k, v in options.as_dict().items() if k != "count"}
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="torchfit-tetwild-") as scratch:
        folder = Path(scratch)
        np.savez(folder / "surface.npz", vertices=vertices, faces=faces.astype(np.int32))
        (folder / "options.json").write_text(json.dumps(opts))
        points, cells = _run_worker(folder, progress)
    seconds = time.perf_counter() - start
    seconds = time.perf_counter() - start
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    cells = np.ascontiguousarray(cells, dtype=np.int64).reshape(-1, 4)
    if len(cells) == 0:
        raise TetrahedralizationError(_NO_TETS.format(reason=""))
    used = np.unique(cells)
    if len(used) < len(points):
        remap = np.full(len(points), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        points, cells = np.ascontiguousarray(points[used]), remap[cells]
    volumes = signed_volumes(points, cells)
    bad = ~(volumes > 0)
    if bad.any():
        raise TetrahedralizationError(
            f"tetrahedralisation produced {int(bad.sum())} of {len(cells)} tetrahedra with "
            f"non-positive volume (smallest {volumes.min():.3e}); retry with optimize=True or "
            "another edge length")
    return points, cells, seconds


def check_volume(points: np.ndarray, cells: np.ndarray, surface: trimesh.Trimesh,
                 problems: list[str]) -> None:
    """The tetrahedra fill about what the surface encloses (see :func:`tetrahedralize`)."""
    volume = float(signed_volumes(points, cells).sum())
    enclosed = surface_volume(surface)
    if enclosed is not None:
        ratio = volume / enclosed if enclosed > 0 else math.inf
        if not _VOLUME_RATIO[0] <= ratio <= _VOLUME_RATIO[1]:
            raise TetrahedralizationError(
                f"the tetrahedral mesh's volume {volume:.4g} is {ratio:.3g} times the "
                f"volume the surface encloses ({enclosed:.4g}), outside {_VOLUME_RATIO}: the "
                "tetrahedra do not match the surface; check it for self-intersections or "
                "lower epsilon")
        return
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = float(ConvexHull(np.asarray(surface.vertices)[np.unique(surface.faces)]).volume)
    except (QhullError, ValueError):
        hull = 0.0
    if not 0 < volume <= _HULL_RATIO * hull:
        raise TetrahedralizationError(
            f"the tetrahedral mesh's volume {volume:.4g} is not in (0, {_HULL_RATIO} x the "
            f"convex hull's {hull:.4g}] for a surface that is not closed "
            f"({'; '.join(problems) or 'no enclosed volume'}); repair the surface")


def pytetwild_version() -> str:
    """The installed pytetwild's version (part of a cache key)."""
    from importlib import metadata

    try:
        return metadata.version("pytetwild")
    except metadata.PackageNotFoundError:
        raise TetrahedralizationError("pytetwild is not installed; install it with "
                                      "pip install 'pytetwild>=0.2,<0.3'") from None
