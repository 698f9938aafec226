"""How many tetrahedra: a target count turned into fTetWild's edge length and envelope.

fTetWild sizes its mesh by two settings: the target edge length and the envelope
``epsilon`` (how far the boundary may stray from the surface). On a finely tessellated
surface the envelope decides: with ``epsilon`` fixed at 1e-3, raising the edge length from
0.05 to 0.08 of the diagonal gave *more* tetrahedra on a 16k-face capsule (docs/notes/
tet_size.md). A target count (``TetOptions.count``, ``problem.tet_count``) therefore sets
both: the edge length from the body's volume (closed surface: the enclosed one; open: its
convex hull's), as if it were filled with regular tetrahedra of that edge, times
``TETS_PER_REGULAR`` measured; the envelope ``ENVELOPE_PER_EDGE`` times the edge length.
fTetWild's count varies from run to run and with the shape: on thin bodies the boundary's
refinement dominates and the count falls only as about ``edge ** -1.3`` (docs/notes/
tet_size.md), not ``edge ** -3``. So a build off by more than ``COUNT_TOLERANCE`` is built
again with the edge length scaled by ``(count / target) ** (1 / COUNT_EXPONENT)``, and from
the second build on by the exponent the last two builds measured (a secant in log-log), at
most ``MAX_BUILDS`` builds; the closest one is kept and cached under a key that holds the
target, so a second run reads it back.

Nothing here solves anything (docs/architecture.md, layer ``mesh``).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np
import trimesh

from ..surface import surface_volume

#: envelope per edge length (both fractions of the diagonal)
ENVELOPE_PER_EDGE = 0.05
#: tetrahedra fTetWild makes per regular tetrahedron of the target edge that fits the volume
TETS_PER_REGULAR = 3.0
#: accepted relative difference between the count made and the target
COUNT_TOLERANCE = 0.10
#: builds at most per target
MAX_BUILDS = 4
#: assumed ``-d log(count) / d log(edge)`` before two builds have measured it
COUNT_EXPONENT = 1.5


def body_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The volume a surface encloses (its convex hull's when it is not closed)."""
    surface = trimesh.Trimesh(vertices, faces, process=False)
    volume = surface_volume(surface)
    if volume is None or not volume > 0:
        from scipy.spatial import ConvexHull, QhullError

        try:
            volume = float(ConvexHull(vertices[np.unique(faces)]).volume)
        except (QhullError, ValueError):
            volume = 0.0
    return float(volume)


def edge_for_count(volume: float, diagonal: float, count: int) -> float:
    """Edge length (fraction of the diagonal) at which about ``count`` tetrahedra fill
    ``volume``, clipped to ``(0, 1]``."""
    regular = 1.0 / (6.0 * math.sqrt(2.0))                    # volume of a unit-edge tet
    edge = (TETS_PER_REGULAR * volume / (regular * count)) ** (1.0 / 3.0)
    return float(min(max(edge / diagonal, 1e-4), 1.0))


def sized(options, edge_fac: float):
    """``options`` with the edge length ``edge_fac`` and the envelope matched to it."""
    return dataclasses.replace(options, edge_length_fac=edge_fac, edge_length_abs=None,
                               epsilon=ENVELOPE_PER_EDGE * edge_fac)


def build_for_count(build: Callable, vertices: np.ndarray, faces: np.ndarray, options,
                    progress=None) -> tuple[np.ndarray, np.ndarray, float, object]:
    """``build(options)`` -> ``(points, cells, seconds)`` until about ``options.count``
    tetrahedra (module docstring). Returns the closest build and the options that made it
    (seconds summed over the builds)."""
    used = vertices[np.unique(faces)]
    diagonal = float(np.linalg.norm(used.max(axis=0) - used.min(axis=0)))
    target = int(options.count)
    trial = sized(options, edge_for_count(body_volume(vertices, faces), diagonal, target))
    best, total, last = None, 0.0, None
    for attempt in range(MAX_BUILDS):
        points, cells, seconds = build(trial)
        total += seconds
        miss = abs(math.log(len(cells) / target))
        if best is None or miss < best[0]:
            best = (miss, points, cells, trial)
        if miss <= math.log(1.0 + COUNT_TOLERANCE) or attempt == MAX_BUILDS - 1:
            break
        exponent = COUNT_EXPONENT
        if last is not None and last[0] != trial.edge_length_fac and last[1] != len(cells):
            measured = -math.log(len(cells) / last[1]) / math.log(
                trial.edge_length_fac / last[0])
            exponent = min(max(measured, 0.5), 3.0)
        last = (trial.edge_length_fac, len(cells))
        edge = min(trial.edge_length_fac * (len(cells) / target) ** (1.0 / exponent), 1.0)
        if progress is not None:
            progress.beat(f"{len(cells):,} tetrahedra for a target of {target:,}; again with "
                          f"edge length {edge:.3g}")
        trial = sized(options, edge)
    _, points, cells, trial = best
    return points, cells, total, trial
