"""What fTetWild is asked for (:class:`TetOptions`) and what it gives (:class:`TetMesh`).

Conventions: ``points`` ``(n, 3)`` float64 in the unit of the surface's vertices, ``cells``
``(m, 4)`` int64, positively oriented (``det([p1 - p0, p2 - p0, p3 - p0]) > 0``), every
vertex referenced by some cell.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np

from ..simplicial import MeshError, signed_volumes


class TetrahedralizationError(MeshError):
    """fTetWild gave no usable tetrahedral mesh for a surface (nothing enclosed, inverted
    tetrahedra, a volume that does not match the surface); the message says what to do."""


@dataclasses.dataclass(frozen=True)
class TetOptions:
    """fTetWild's settings (part of the cache key).

    Attributes:
        edge_length_fac: target edge length as a fraction of the surface's bounding-box
            diagonal, in ``(0, 1]``.
        edge_length_abs: absolute target edge length (surface units); overrides
            ``edge_length_fac`` when given.
        optimize: improve the tetrahedra's quality (slower, better elements).
        epsilon: envelope size (how far the tetrahedral boundary may stray from the
            surface) relative to the bounding-box diagonal.
        stop_energy: the quality optimisation stops when the conformal AMIPS energy (3 for
            a regular tetrahedron) falls below this.
        num_opt_iter: maximum number of optimisation passes.
        coarsen: coarsen the output as much as the quality allows.
        count: a target number of tetrahedra; when given, the edge length and the
            envelope are chosen for it (:mod:`.size`) and the two above are unused.
    """

    edge_length_fac: float = 0.05
    edge_length_abs: float | None = None
    optimize: bool = True
    epsilon: float = 1e-3
    stop_energy: float = 10.0
    num_opt_iter: int = 80
    coarsen: bool = False
    count: int | None = None

    def __post_init__(self) -> None:
        self.check()

    def check(self) -> None:
        """Raise ``ValueError`` (one line naming the option) for an invalid setting."""
        def positive(name: str, value: Any) -> None:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                    math.isfinite(value) and value > 0):
                raise ValueError(f"TetOptions.{name} must be a positive finite number, "
                                 f"got {value!r}")

        positive("edge_length_fac", self.edge_length_fac)
        if self.edge_length_fac > 1:
            raise ValueError(f"TetOptions.edge_length_fac is a fraction of the bounding-box "
                             f"diagonal and must be at most 1, got {self.edge_length_fac!r}")
        if self.edge_length_abs is not None:
            positive("edge_length_abs", self.edge_length_abs)
        positive("epsilon", self.epsilon)
        positive("stop_energy", self.stop_energy)
        if isinstance(self.num_opt_iter, bool) or not isinstance(
                self.num_opt_iter, (int, np.integer)) or self.num_opt_iter < 1:
            raise ValueError(f"TetOptions.num_opt_iter must be a positive integer, got "
                             f"{self.num_opt_iter!r}")
        if self.count is not None and (isinstance(self.count, bool) or not isinstance(
                self.count, (int, np.integer)) or self.count < 1):
            raise ValueError(f"TetOptions.count must be a positive integer, got {self.count!r}")
        for name in ("optimize", "coarsen"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"TetOptions.{name} must be True or False, got "
                                 f"{getattr(self, name)!r}")

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-serialisable values (floats, ints, bools, ``None``); ``count`` only
        when given (so the keys of meshes made without it stay what they were)."""
        sized = {} if self.count is None else {"count": int(self.count)}
        return sized | {"edge_length_fac": float(self.edge_length_fac),
                "edge_length_abs": None if self.edge_length_abs is None
                else float(self.edge_length_abs),
                "optimize": bool(self.optimize), "epsilon": float(self.epsilon),
                "stop_energy": float(self.stop_energy),
                "num_opt_iter": int(self.num_opt_iter), "coarsen": bool(self.coarsen)}


@dataclasses.dataclass(eq=False)
class TetMesh:
    """A tetrahedral mesh from :func:`tetrahedralize`.

    Attributes:
        points: ``(n, 3)`` float64 vertex positions (the surface's units).
        cells: ``(m, 4)`` int64, positively oriented, every vertex referenced.
        key: the cache key (sha256 hex digest of input, options and pytetwild version).
        from_cache: whether the arrays were read from the cache.
        seconds: wall time of this call (s).
        build_seconds: wall time pytetwild took when the mesh was built (s; stored in the
            cache).
        path: the cache file, or ``None`` when the cache was not used.
        canonical: the :class:`~.canonical.CanonicalSurface` the mesh was made of (its
            placement maps canonical coordinates to ``points``' frame), or ``None`` (a
            mesh of the surface as given, :func:`~.tetrahedralize.tetrahedralize`).
    """

    points: np.ndarray
    cells: np.ndarray
    key: str
    from_cache: bool
    seconds: float
    build_seconds: float
    path: Path | None
    canonical: Any = None

    @property
    def volumes(self) -> np.ndarray:
        """``(m,)`` signed volumes of the tetrahedra (positive; units cubed)."""
        return signed_volumes(self.points, self.cells)
