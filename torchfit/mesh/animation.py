"""A rigged animation, whatever file it came from: its frames, what drives them, its units.

Every reader of :mod:`.formats` (the folder format, USD, glTF) builds an :class:`Animation`
(every length in metres) and refuses what it cannot use with one :class:`AnimationError`
line; :data:`UNITS` are the units a file may name and :data:`DEFAULT_FPS` the frame rate of
a file that names none. The rig check (:mod:`.rig_check`) and the body read it; nothing here
reads or writes a file.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from .rig import DrivenSurface, Skeleton
from .simplicial import MeshError

#: frames per second of an animation that does not say (the folder format without ``fps``)
DEFAULT_FPS = 24.0
#: the units a file may name: metres per unit
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254}


class AnimationError(MeshError):
    """An animation that cannot be used; the message names the file and the fault."""


@dataclasses.dataclass
class Animation:
    """A loaded animation (every length in metres).

    Attributes:
        path: the manifest file.
        rest_vertices: ``(V, 3)`` in the user's vertex order; faces ``(T, 3)``.
        frames: ``(F, V, 3)`` animated surface positions.
        skeleton / driven: what drives the body (exactly one is set).
        region_labels: ``(V,)`` int labels per rest vertex, or ``None``; region_names.
        frame_files: where each frame came from (for messages).
        warnings: what is odd about the surface (open, non-manifold, ...).
        file_vertices: ``(V_file,)`` the vertex of this surface each vertex of the file is
            (seams welded, :mod:`.formats.seams`), or ``None``: the file's own vertices.
        file_faces: ``(T_file, 3)`` the file's faces on its own vertices, or ``None``.
        prim: the mesh prim a USD stage's animation was read from ("" otherwise).
        up: ``(3,)`` the file's up direction (a unit vector in these coordinates: a USD
            stage's ``upAxis``, glTF's +Y, the manifest's ``up``), or ``None`` where the file
            says none; the pictures' camera stands the body on it.
        fps: frames per second of ``frames`` (the folder's ``fps``, a USD stage's time
            codes per second, a glTF animation's sampling or key rate; default 24).
    """

    path: Path
    rest_vertices: np.ndarray
    faces: np.ndarray
    frames: np.ndarray
    unit: float
    skeleton: Skeleton | None = None
    driven: DrivenSurface | None = None
    region_labels: np.ndarray | None = None
    region_names: list[str] = dataclasses.field(default_factory=list)
    frame_files: list[str] = dataclasses.field(default_factory=list)
    warnings: list[str] = dataclasses.field(default_factory=list)
    file_vertices: np.ndarray | None = None
    file_faces: np.ndarray | None = None
    prim: str = ""
    up: np.ndarray | None = None
    fps: float = DEFAULT_FPS

    @property
    def n_frames(self) -> int:
        return int(self.frames.shape[0])

    @property
    def n_file_vertices(self) -> int:
        """The vertex count of the file (the welded surface's where nothing was welded)."""
        return self.n_vertices if self.file_vertices is None else len(self.file_vertices)

    def file_points(self, points: np.ndarray) -> np.ndarray:
        """Points ``(..., V, 3)`` of this surface on the file's own vertices
        ``(..., V_file, 3)``, in its order."""
        return points if self.file_vertices is None else \
            np.take(points, self.file_vertices, axis=-2)

    def file_values(self, values: np.ndarray) -> np.ndarray:
        """Per-vertex ``values`` ``(..., V)`` on the file's own vertices ``(..., V_file)``."""
        return values if self.file_vertices is None else \
            np.take(values, self.file_vertices, axis=-1)

    @property
    def output_faces(self) -> np.ndarray:
        """The faces on the file's own vertices (for outputs of :meth:`file_points`)."""
        return self.faces if self.file_faces is None else self.file_faces

    @property
    def n_vertices(self) -> int:
        return int(self.rest_vertices.shape[0])

    def select(self, frames: list[int]) -> "Animation":
        """The animation restricted to the frames ``frames`` (indices, in that order); a frame
        that does not exist (negative, past the last, or a number no index can hold) is an
        :class:`AnimationError` naming it."""
        bad = [int(f) for f in frames if not 0 <= int(f) < self.n_frames]   # Python ints: no
        if bad:                                                # overflow for 10**20
            raise AnimationError(f"{self.path}: frame {bad[0]} does not exist "
                                 f"(the animation has frames 0..{self.n_frames - 1})")
        idx = np.asarray(frames, dtype=np.int64)
        skeleton = None if self.skeleton is None else dataclasses.replace(
            self.skeleton, transforms=self.skeleton.transforms[idx])
        return dataclasses.replace(self, frames=self.frames[idx], skeleton=skeleton,
                                   frame_files=[self.frame_files[i] for i in idx])
