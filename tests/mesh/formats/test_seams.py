"""Seam vertices welded for the simulation, the file's own vertices back for outputs
(torchfit.mesh.formats.seams)."""
from __future__ import annotations

import numpy as np
import trimesh

from torchfit.mesh.formats.folder import Animation
from torchfit.mesh.formats.seams import weld_seams
from torchfit.mesh.rig import DrivenSurface
from torchfit.mesh.surface import surface_warnings


def split_capsule():
    """A closed capsule whose every vertex is split once per face using it (as a glTF of a
    flat-shaded body): 3 T vertices, each face on its own corners; frames move it."""
    mesh = trimesh.creation.capsule(height=0.3, radius=0.05, count=[8, 8])
    rest = mesh.vertices[mesh.faces.reshape(-1)]
    faces = np.arange(len(rest)).reshape(-1, 3)
    shear = np.linspace(0, 0.1, 4)[:, None, None] * rest[None, :, 2:3] * [1, 0, 0]
    return mesh, rest, faces, rest[None] + shear


def test_a_split_closed_body_is_closed_and_maps_back():
    mesh, rest, faces, frames = split_capsule()
    split = Animation("x", rest, faces, frames, 1.0,
                      driven=DrivenSurface(rest[:, 2] < -0.1, 0.01),
                      warnings=surface_warnings(trimesh.Trimesh(rest, faces, process=False)))
    assert any("not watertight" in w for w in split.warnings)
    welded = weld_seams(split)
    assert welded.n_vertices == len(mesh.vertices) and welded.n_file_vertices == len(rest)
    assert welded.warnings == []                                   # closed: no warning
    assert trimesh.Trimesh(welded.rest_vertices, welded.faces, process=False).is_watertight
    # every file vertex gets its welded vertex's positions back, in the file's order
    assert np.array_equal(welded.file_points(welded.frames), frames)
    assert np.array_equal(welded.output_faces, faces)
    assert np.array_equal(welded.file_values(welded.driven.mask), split.driven.mask)
    assert np.array_equal(welded.rest_vertices[welded.faces], rest[faces])


def test_vertices_that_part_in_a_frame_stay_apart():
    mesh, rest, faces, frames = split_capsule()
    frames = frames.copy()
    lips = np.flatnonzero(np.all(np.isclose(rest, rest[0]), axis=1))
    frames[2, lips[1:]] += [0, 0.01, 0]                     # two copies part in frame 2
    welded = weld_seams(Animation("x", rest, faces, frames, 1.0))
    assert welded.n_vertices == len(mesh.vertices) + 1
    assert np.array_equal(welded.file_points(welded.frames), frames)
    # nothing coincides: the animation as it is
    plain = Animation("x", mesh.vertices, mesh.faces, mesh.vertices[None], 1.0)
    assert weld_seams(plain) is plain
