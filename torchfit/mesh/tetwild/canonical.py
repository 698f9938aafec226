"""The canonical surface of a body, and its tetrahedral mesh cached whatever file the body came from.

A body's surface reaches the tetrahedraliser in many representations: other axes (Y-up
glTF, Z-up USD), other units (a stage in centimetres with ``metersPerUnit`` 0.01, converted
to metres with other round-off), float32 or float64, another vertex and face order, seam
vertices split (glTF). :func:`canonical_surface` removes all of these:

1. the surface is turned into a given frame (``origin``, ``axes``: the body's principal
   frame, :func:`torchfit.problems.body.frame.principal_frame`, which follows the body);
2. scaled by its radius (the largest distance of a vertex from ``origin``): size-free;
3. welded: vertices closer than :data:`WELD` (of the radius) are one, at their mean
   (seams); faces that collapse are dropped, vertices no face uses are left out;
4. its coordinates rounded to ``2^-SNAP_BITS`` (of the radius; ``+ 0.0``, no ``-0.0``);
5. vertices sorted by their rounded coordinates (``a2``, then ``a1``, ``a0``), each face
   turned (orientation kept) to start at its lowest vertex, faces sorted.

:func:`tetrahedralize_canonical` meshes that surface (fTetWild on the canonical vertices
and faces) and caches the tetrahedra *in canonical coordinates* under
``cache_dir/canonical/<key>/<digest>.npz``. **What the cache promises:** a surface whose
canonical form has the same welded vertex and face counts, the same options and pytetwild
version (the ``key``, :meth:`CanonicalSurface.key`), and whose every canonical vertex lies
within :data:`MATCH` (of the radius) of the stored one's counterpart with the same
triangles between them (:meth:`CanonicalSurface.difference`), gets the stored tetrahedra,
mapped by its own :class:`Placement` (scale, rotate, translate) into its file's
coordinates: a rotated, rescaled, re-ordered, seam-split or float32 copy of a surface gets
the same tetrahedra (the same count, points equal to the mapped ones to round-off), and
the same :attr:`~.options.TetMesh.key`. A byte-identical canonical surface is found by its
file name (``digest``); any other of the same key by comparing it with each stored one;
failing that, a stored surface that is this one turned (vertex for vertex in the files'
welded order, :func:`turn_between`: a round body whose axes another shot's motion chose)
serves it, its tetrahedra turned alike.
**Not promised:** another triangulation or a remeshed surface of the same shape (other
counts or triangles: another entry), a mirror image, a round body turned by another shot
*and* re-ordered (another entry), the same tetrahedra for a body symmetric in shape and
motion (the same up to that symmetry), nor a fresh cache giving the same mesh: fTetWild's
output changes from build to build even with one thread (docs/notes/axes.md), so the
cache (shared, or the run's own ``mesh.npz``) is what fixes the mesh.

Nothing here solves anything (docs/architecture.md, layer ``mesh``).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import time
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from ...steps import count, step
from ..simplicial import pair_groups
from .cache import default_cache_dir, write_entry
from .options import TetMesh, TetOptions, TetrahedralizationError
from .size import build_for_count
from .tetrahedralize import build_surface, check_volume, pytetwild_version, step_line

log = logging.getLogger(__name__)

#: vertices closer than this (a fraction of the radius) are one vertex (a seam's copies)
WELD = 1e-6
#: canonical coordinates are rounded to this power of two below the radius
SNAP_BITS = 30
#: two canonical surfaces are one where every vertex is within this (of the radius) of its
#: counterpart: float32 (6e-8 relative) and a unit conversion's round-off lie far inside
MATCH = 1e-6
#: version of the canonical cache (part of the key: a new layout never reads old entries)
_FORMAT = "torchfit-canonical-tetmesh-1"


@dataclasses.dataclass(frozen=True, eq=False)
class Placement:
    """Where canonical coordinates sit in a file's: ``file = scale * canonical @ axes + origin``.

    ``origin`` ``(3,)`` and ``scale`` in the file's length unit, ``axes`` ``(3, 3)`` rows
    ``a0, a1, a2`` (orthonormal, right-handed)."""

    origin: np.ndarray
    axes: np.ndarray
    scale: float

    def to_file(self, points: np.ndarray) -> np.ndarray:
        """``(..., 3)`` canonical points in the file's coordinates."""
        return (self.scale * np.asarray(points, dtype=np.float64)) @ self.axes + self.origin

    def from_file(self, points: np.ndarray) -> np.ndarray:
        """``(..., 3)`` file points in canonical coordinates."""
        return ((np.asarray(points, dtype=np.float64) - self.origin) @ self.axes.T) / self.scale

    def directions_to(self, other: Placement, directions: np.ndarray) -> np.ndarray:
        """``(..., 3)`` unit directions in this file's coordinates turned into ``other``'s."""
        return (np.asarray(directions, dtype=np.float64) @ self.axes.T) @ other.axes


@dataclasses.dataclass(frozen=True, eq=False)
class CanonicalSurface:
    """A surface in canonical form (module doc) and where it sits in its file.

    ``vertices`` ``(n, 3)`` float64 canonical coordinates (radius 1), ``faces`` ``(k, 3)``
    int64 in canonical order, ``placement`` the map back into the file's coordinates,
    ``file_order`` ``(n,)`` the canonical vertex of each welded vertex in the file's order
    (``None``: not known)."""

    vertices: np.ndarray
    faces: np.ndarray
    placement: Placement
    file_order: np.ndarray | None = None

    @property
    def digest(self) -> str:
        """sha256 hex digest of the canonical vertex and face bytes (an exact copy's name)."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.vertices, dtype="<f8").tobytes())
        h.update(np.ascontiguousarray(self.faces, dtype="<i8").tobytes())
        return h.hexdigest()

    def key(self, options: TetOptions, version: str) -> str:
        """sha256 hex digest of what is exactly invariant: the welded vertex and face
        counts, the canonical options (:func:`canonical_options`) and the pytetwild
        version."""
        text = json.dumps({"format": _FORMAT, "vertices": len(self.vertices),
                           "faces": len(self.faces),
                           "options": canonical_options(options, self.placement.scale).as_dict(),
                           "pytetwild": version}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()

    def difference(self, other: CanonicalSurface, tolerance: float = MATCH) -> str:
        """What tells this canonical surface from ``other`` (one phrase; ``""``: they are
        one: the same counts, every vertex within ``tolerance`` of its counterpart, the
        same oriented triangles between counterparts). The order of either does not
        matter."""
        if self.vertices.shape != other.vertices.shape or self.faces.shape != other.faces.shape:
            return (f"its surface has {len(other.vertices)} vertices and {len(other.faces)} "
                    f"faces once welded, this one {len(self.vertices)} and {len(self.faces)}")
        if np.array_equal(self.vertices, other.vertices) and \
                np.array_equal(self.faces, other.faces):
            return ""
        distance, nearest = cKDTree(other.vertices).query(self.vertices)
        if distance.max() > tolerance or len(np.unique(nearest)) != len(nearest):
            return (f"its surface differs in shape (a vertex {distance.max():.2g} of the "
                    f"body's radius from the nearest of the other)")
        if not np.array_equal(_sorted_faces(nearest[self.faces]), _sorted_faces(other.faces)):
            return "its surface has the same points but other triangles"
        return ""


def turn_between(stored: CanonicalSurface, surface: CanonicalSurface,
                 tolerance: float = MATCH) -> np.ndarray | None:
    """``Q`` ``(3, 3)``, a rotation with ``stored.vertices @ Q.T`` on ``surface``'s vertices
    (within ``tolerance``, vertex for vertex in the files' welded order, the same
    triangles), or ``None``: the same surface in another canonical frame, as a round body
    gets when another shot's motion settles its axes."""
    if stored.file_order is None or surface.file_order is None or \
            stored.vertices.shape != surface.vertices.shape or \
            stored.faces.shape != surface.faces.shape:
        return None
    x, y = stored.vertices[stored.file_order], surface.vertices[surface.file_order]
    u, _, vt = np.linalg.svd(y.T @ x)
    turn = u @ vt
    if np.linalg.det(turn) < 0 or np.abs(x @ turn.T - y).max() > tolerance:
        return None
    # the same triangles: stored canonical vertex -> the surface's, through the file order
    to_surface = np.empty(len(x), dtype=np.int64)
    to_surface[stored.file_order] = surface.file_order
    if not np.array_equal(_sorted_faces(to_surface[stored.faces]), surface.faces):
        return None
    return turn


def canonical_options(options: TetOptions, scale: float) -> TetOptions:
    """``options`` for the canonical surface: an absolute edge length divided by the
    radius (rounded to 12 significant digits, so round-off keeps the key); the rest are
    fractions of the diagonal already."""
    if options.edge_length_abs is None:
        return options
    return dataclasses.replace(options,
                               edge_length_abs=float(f"{options.edge_length_abs / scale:.12g}"))


def weld_groups(vertices: np.ndarray, tolerance: float) -> np.ndarray:
    """``(V,)`` the welded vertex of each vertex: those within ``tolerance`` (absolute) of
    one another (transitively) are one, numbered in order of their first vertex."""
    return pair_groups(cKDTree(vertices).query_pairs(tolerance, output_type="ndarray"),
                       len(vertices))


def welded_surface(vertices: np.ndarray, faces: np.ndarray, tolerance: float = WELD
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(groups (V,), vertices (W, 3), faces (k, 3))``: the surface with vertices closer
    than ``tolerance`` times its radius (about the vertices' mean) merged at their mean,
    collapsed faces dropped; ``groups`` is each vertex's welded vertex."""
    v = np.asarray(vertices, dtype=np.float64)
    radius = float(np.linalg.norm(v - v.mean(axis=0), axis=1).max()) or 1.0
    groups = weld_groups(v, tolerance * radius)
    return groups, _group_means(v, groups), _uncollapsed(groups[np.asarray(faces, dtype=np.int64)])


def _group_means(points: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """``(G, 3)`` the mean of each group's points."""
    n = int(groups.max()) + 1
    means = np.zeros((n, 3))
    np.add.at(means, groups, points)
    return means / np.bincount(groups, minlength=n)[:, None]


def _uncollapsed(faces: np.ndarray) -> np.ndarray:
    """The faces whose three corners are distinct (welding collapses the others)."""
    return faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
                 & (faces[:, 0] != faces[:, 2])]


def canonical_surface(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray,
                      axes: np.ndarray) -> CanonicalSurface:
    """The canonical form of the surface ``vertices`` ``(V, 3)``, ``faces`` ``(k, 3)`` in
    the frame ``origin`` ``(3,)``, ``axes`` ``(3, 3)`` (rows; module doc, steps 1-5)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    origin = np.asarray(origin, dtype=np.float64)
    axes = np.asarray(axes, dtype=np.float64)
    used = np.unique(f)
    local = (v - origin) @ axes.T
    scale = float(np.linalg.norm(local[used], axis=1).max())
    if not scale > 0:
        raise TetrahedralizationError("the surface has no extent (every vertex at one "
                                      "point); give a surface that encloses a volume")
    groups = weld_groups(local[used] / scale, WELD)
    merged = _group_means(local[used] / scale, groups)
    n = len(merged)
    index = np.full(len(v), -1, dtype=np.int64)
    index[used] = groups
    f = _uncollapsed(index[f])
    unit = 2.0 ** -SNAP_BITS
    snapped = np.round(merged / unit)
    order = np.lexsort((snapped[:, 0], snapped[:, 1], snapped[:, 2]))
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n)
    canonical = snapped[order] * unit + 0.0          # + 0.0: no -0.0 in the bytes
    return CanonicalSurface(canonical, _sorted_faces(rank[f]), Placement(origin, axes, scale),
                            rank)


def _sorted_faces(faces: np.ndarray) -> np.ndarray:
    """Faces each turned to start at their lowest vertex (orientation kept), then sorted."""
    f = np.asarray(faces, dtype=np.int64)
    if not len(f):
        return f.reshape(0, 3)
    start = np.argmin(f, axis=1)
    turned = f[np.arange(len(f))[:, None], (start[:, None] + np.arange(3)) % 3]
    return np.ascontiguousarray(turned[np.lexsort(turned.T[::-1])])


def tetrahedralize_canonical(surface: CanonicalSurface, options: TetOptions = TetOptions(),
                             cache_dir: str | Path | None = None,
                             use_cache: bool = True) -> TetMesh:
    """The tetrahedral mesh of ``surface`` in its file's coordinates, from the canonical
    cache (module doc: what it promises) or built by fTetWild on the canonical surface and
    stored there.

    Returns a :class:`~.options.TetMesh` whose ``points`` are the canonical tetrahedra
    mapped by ``surface.placement``, ``key`` names the cache entry (the same for every
    representation of one surface), ``canonical`` is ``surface``. Raises what
    :func:`~.tetrahedralize.tetrahedralize` raises."""
    start = time.perf_counter()
    options.check()
    work = canonical_options(options, surface.placement.scale)
    version = pytetwild_version()
    key = surface.key(options, version)
    folder = Path(default_cache_dir() if cache_dir is None else cache_dir) / "canonical" / key
    with step(step_line(len(surface.faces), options)) as progress:
        found = _lookup(folder, surface) if use_cache else None
        if found is None:
            points, cells, build_seconds = _build_canonical(surface, work, progress)
            check_volume(points, cells, trimesh.Trimesh(surface.vertices, surface.faces,
                                                         process=False), [])
            path = folder / f"{surface.digest}.npz" if use_cache else None
            digest, from_cache = surface.digest, False
            if path is not None:
                stored = write_entry(path, key, points, cells, build_seconds, work, version,
                                     overwrite=False,
                                     extra={"surface_vertices": surface.vertices,
                                            "surface_faces": surface.faces} | (
                                         {} if surface.file_order is None else
                                         {"surface_order": surface.file_order}))
                if stored is None:
                    path = None
                elif not stored:                     # another process stored it first
                    found = _lookup(folder, surface)
        if found is not None:
            path, points, cells, build_seconds, digest, turn = found
            points = points if turn is None else points @ turn.T
            from_cache = True
        entry = hashlib.sha256(f"{key}/{digest}".encode()).hexdigest()
        mesh = TetMesh(surface.placement.to_file(points), cells, entry, from_cache,
                       time.perf_counter() - start, build_seconds, path, surface)
        where = ("read from the cache " if from_cache else "built and cached in ") + \
            str(path) if path is not None else "built, not cached"
        progress.result = (f"{count(len(cells))} tetrahedra, {count(len(points))} vertices, "
                           f"{where}")
    return mesh


def _build_canonical(surface: CanonicalSurface, options: TetOptions, progress: step
                     ) -> tuple[np.ndarray, np.ndarray, float]:
    if options.count is None:
        return build_surface(surface.vertices, surface.faces, options, progress)
    points, cells, seconds, made = build_for_count(
        lambda trial: build_surface(surface.vertices, surface.faces, trial, progress),
        surface.vertices, surface.faces, options, progress)
    return points, cells, seconds


def _lookup(folder: Path, surface: CanonicalSurface
            ) -> tuple[Path, np.ndarray, np.ndarray, float, str, np.ndarray | None] | None:
    """The stored entry of ``surface`` under ``folder``, ``(path, points, cells,
    build_seconds, digest, turn)``: its own digest first, then every other in name order
    that matches (:meth:`CanonicalSurface.difference`; ``turn`` ``None``), then one that
    matches turned (:func:`turn_between`: ``points @ turn.T`` are the surface's); ``None``
    where none does. Unreadable entries are warned about and skipped."""
    own = folder / f"{surface.digest}.npz"
    others = sorted(p for p in folder.glob("*.npz") if p != own) if folder.is_dir() else []
    entries = []
    for path in ([own] if own.exists() else []) + others:
        try:
            with np.load(path, allow_pickle=False) as data:
                order = np.array(data["surface_order"]) if "surface_order" in data.files \
                    else None
                stored = CanonicalSurface(np.array(data["surface_vertices"]),
                                          np.array(data["surface_faces"]), surface.placement,
                                          order)
                points, cells = np.array(data["points"]), np.array(data["cells"])
                build_seconds = float(data["build_seconds"])
        except Exception as e:  # noqa: BLE001  (a truncated or foreign file)
            log.warning(f"canonical tetrahedral mesh cache file {path} is unreadable "
                        f"({type(e).__name__}: {' '.join(str(e).split())}); skipping it")
            continue
        if surface.difference(stored) == "":
            return path, points, cells, build_seconds, path.stem, None
        entries.append((path, stored, points, cells, build_seconds))
    for path, stored, points, cells, build_seconds in entries:
        turn = turn_between(stored, surface)
        if turn is not None:
            return path, points, cells, build_seconds, path.stem, turn
    return None
