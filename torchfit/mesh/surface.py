"""Triangle surfaces supplied by users: loading, checks and the enclosed volume.

Loading (OBJ, PLY, OFF, STL, ...), the problems a tetrahedraliser cares about (holes,
non-manifold edges, winding, inside-out, duplicate vertices), and the enclosed volume.

Conventions: vertices are ``(n, 3)`` float64 in the length unit the caller chooses (the
``scale`` of :func:`load_surface` converts the file's unit into it), faces ``(k, 3)`` int64
vertex indices, counter-clockwise seen from outside for an outward-facing surface.

Nothing here solves anything (see docs/architecture.md, layer ``mesh``).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import trimesh

from .simplicial import MeshError


class SurfaceError(MeshError):
    """A surface file cannot be used (missing, unreadable, empty, invalid values or indices);
    the message names the file and what to do."""


def load_surface(path: str | Path, scale: float = 1.0) -> trimesh.Trimesh:
    """Load a triangle surface from any format trimesh reads (OBJ, PLY, OFF, STL, ...).

    The file is read with ``process=False, maintain_order=True`` so that the vertices keep
    the file's order (a rig's vertex ``i`` is the surface's vertex ``i``); nothing is merged
    or reordered, except for STL, a format that stores the three corners of every triangle
    separately: there exactly coincident vertices are merged, in order of first appearance
    (otherwise every edge of an STL surface would be a boundary edge).

    Args:
        path: the surface file.
        scale: unit conversion applied to the vertices (``0.01`` for a file in cm when the
            simulation works in m); positive and finite.

    Returns:
        A ``trimesh.Trimesh`` with ``vertices`` ``(n, 3)`` float64 (times ``scale``) and
        ``faces`` ``(k, 3)`` int64.

    Raises:
        SurfaceError: missing file, unreadable or unknown format, no vertices or no faces,
            a vertex that is NaN or infinite (named by index), a face that refers to a
            vertex out of range.
    """
    path = Path(path)
    try:
        factor = float(scale)
    except (TypeError, ValueError):
        factor = math.nan
    if not (math.isfinite(factor) and factor > 0):
        raise SurfaceError(f"scale for surface {path} must be a positive finite number, "
                           f"got {scale!r}")
    if not path.is_file():
        raise SurfaceError(f"surface file {path} does not exist (or is not a file); check "
                           "the path")
    try:
        mesh = trimesh.load(path, process=False, maintain_order=True, force="mesh")
    except IndexError as e:
        raise SurfaceError(f"surface file {path}: a face refers to a vertex that does not "
                           f"exist ({_one_line(e)}); fix the face indices") from e
    except Exception as e:                           # trimesh raises many kinds
        raise SurfaceError(f"cannot read surface file {path} ({type(e).__name__}: "
                           f"{_one_line(e)}); give a valid OBJ, PLY, OFF or STL file") from e
    if not isinstance(mesh, trimesh.Trimesh):
        raise SurfaceError(f"surface file {path} holds no triangle mesh (trimesh read a "
                           f"{type(mesh).__name__}); give a file with vertices and faces")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if vertices.ndim != 2 or len(vertices) == 0:
        raise SurfaceError(f"surface file {path} has no triangles (no vertices read); give "
                           "a triangle mesh")
    if faces.ndim != 2 or len(faces) == 0:
        raise SurfaceError(f"surface file {path} has no faces ({len(vertices)} vertices "
                           "only); give a triangle mesh, not a point cloud")
    bad = np.nonzero(~np.isfinite(vertices).all(axis=1))[0]
    if bad.size:
        i = int(bad[0])
        more = f" ({bad.size} such vertices)" if bad.size > 1 else ""
        raise SurfaceError(f"surface file {path}: vertex {i} is not finite "
                           f"{vertices[i].tolist()}{more}; fix or remove it")
    if faces.min() < 0 or faces.max() >= len(vertices):
        f = int(np.nonzero((faces < 0).any(axis=1) | (faces >= len(vertices)).any(axis=1))[0][0])
        raise SurfaceError(f"surface file {path}: face {f} {faces[f].tolist()} refers to a "
                           f"vertex out of range [0, {len(vertices)}); fix the face indices")
    if path.suffix.lower() == ".stl":
        vertices, faces = _merge_exact_duplicates(vertices, faces)
        mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.vertices = vertices * factor
    return mesh


def _one_line(error: BaseException) -> str:
    return " ".join(str(error).split()) or type(error).__name__


def _merge_exact_duplicates(vertices: np.ndarray,
                            faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices with identical coordinates merged, kept in order of first appearance."""
    _, first, inverse = np.unique(vertices, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)                       # unique rows by first appearance
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return vertices[first[order]], rank[inverse.reshape(-1)][faces]


def _edge_statistics(faces: np.ndarray) -> dict[str, int]:
    """Counts of boundary (1 face), non-manifold (> 2 faces) and inconsistently wound (two
    faces traversing it the same way) edges of a triangle list."""
    faces = np.asarray(faces, dtype=np.int64)
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    undirected = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(undirected, axis=0, return_inverse=True,
                                   return_counts=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")     # the directed edges of each edge together
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    pairs = starts[counts == 2]
    first, second = directed[order[pairs]], directed[order[pairs + 1]]
    return {"edges": int(len(counts)), "boundary": int(np.sum(counts == 1)),
            "non_manifold": int(np.sum(counts > 2)),
            "inconsistent": int(np.sum(np.all(first == second, axis=1)))}


def _signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume enclosed by a closed triangle surface (positive when the faces are
    counter-clockwise seen from outside)."""
    v = np.asarray(vertices, dtype=np.float64)
    v = v - v.mean(axis=0)                          # fewer cancellations far from the origin
    a, b, c = (v[np.asarray(faces)[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


def surface_warnings(mesh: trimesh.Trimesh) -> list[str]:
    """Human sentences about what makes ``mesh`` a poor boundary of a volume.

    Checked: open (boundary edges, i.e. edges of one face only: not watertight),
    non-manifold edges (shared by more than two faces), inconsistent winding (an edge
    traversed the same way by its two faces), inside-out (negative signed volume of a
    watertight, consistently wound surface), duplicate vertices (identical coordinates).

    Returns:
        One sentence per problem; empty for a clean closed surface.
    """
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if len(faces) == 0:
        return ["the surface has no faces, so it encloses no volume"]
    out = []
    stats = _edge_statistics(faces)
    if stats["boundary"]:
        out.append(f"the surface is not watertight: it is open, with {stats['boundary']} "
                   f"boundary edge(s) (of {stats['edges']}) that belong to one face only; "
                   "close the holes so that its inside is well defined")
    if stats["non_manifold"]:
        out.append(f"the surface has {stats['non_manifold']} non-manifold edge(s) shared by "
                   "more than two faces; remove the extra faces")
    if stats["inconsistent"]:
        out.append(f"the face winding is inconsistent: {stats['inconsistent']} edge(s) are "
                   "traversed in the same direction by both their faces; orient the faces "
                   "consistently (trimesh.repair.fix_winding)")
    if not (stats["boundary"] or stats["non_manifold"] or stats["inconsistent"]):
        volume = _signed_volume(vertices, faces)
        if volume < 0:
            out.append(f"the surface is inside out: its signed volume is {volume:.4g} "
                       "(negative); reverse its faces (mesh.invert())")
    _, counts = np.unique(vertices, axis=0, return_counts=True)
    duplicates = int(np.sum(counts[counts > 1] - 1))
    if duplicates:
        out.append(f"{duplicates} vertex(es) duplicate the position of another vertex, which "
                   "splits the surface along them; merge them (mesh.merge_vertices())")
    return out


def surface_volume(mesh: trimesh.Trimesh) -> float | None:
    """Volume enclosed by ``mesh`` (its units cubed), from the signed volume.

    Returns the absolute signed volume when the surface is watertight (every edge shared by
    exactly two faces) and consistently wound, so an inside-out surface still gives its
    volume (:func:`surface_warnings` reports it); ``None`` otherwise (no enclosed volume is
    defined).
    """
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if len(faces) == 0:
        return None
    stats = _edge_statistics(faces)
    if stats["boundary"] or stats["non_manifold"] or stats["inconsistent"]:
        return None
    return abs(_signed_volume(mesh.vertices, faces))
