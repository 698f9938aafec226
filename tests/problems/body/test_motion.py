"""What of a body's motion the pictures show (torchfit.problems.body.motion): the most
deformed frame, the camera, the most strained tetrahedra; each rotation-equivariant."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from torchfit.mesh import box_tetrahedra
from torchfit.problems.body.motion import most_deformed_frame, most_strained_cells, view_axes

TURN = Rotation.from_euler("zyx", [-50.0, 33.0, 160.0], degrees=True).as_matrix()


def bent_tube():
    """A tube along y bent towards +z in the y-z plane by frames 1 and 2 (frame 2 the
    most), frame 3 the rest moved rigidly far away: ``(rest (V, 3), frames (4, V, 3))``."""
    rest = box_tetrahedra(2, 10, 2, (0.1, 1.0, 0.1)).points
    y = rest[:, 1]
    frames = np.stack([rest, rest, rest, rest]).copy()
    frames[1, :, 2] += 0.05 * y ** 2
    frames[2, :, 2] += 0.20 * y ** 2
    rigid = Rotation.from_euler("x", 80, degrees=True).as_matrix()
    frames[3] = rest @ rigid.T + [3.0, -2.0, 1.0]
    return rest, frames


def test_the_most_deformed_frame_ignores_rigid_motion():
    rest, frames = bent_tube()
    assert most_deformed_frame(rest, frames) == 2
    assert most_deformed_frame(rest @ TURN.T, frames @ TURN.T) == 2


def test_the_camera_looks_across_the_plane_of_motion_long_axis_up():
    rest, frames = bent_tube()
    frames = frames[:3]                                 # the bend only: motion in y-z
    view = view_axes(rest, frames, np.array([0.0, 1.0, 0.0]))
    np.testing.assert_allclose(view @ view.T, np.eye(3), atol=1e-12)
    assert abs(view[1] @ [1, 0, 0]) > 0.999            # depth: x, the axis without motion
    np.testing.assert_allclose(view[2], [0, 1, 0], atol=1e-9)    # up: the long axis
    np.testing.assert_allclose(view[0], [0, 0, 1], atol=1e-9)    # the bend goes right
    assert np.linalg.det(view) > 0
    turned = view_axes(rest @ TURN.T, frames @ TURN.T, TURN @ [0.0, 1.0, 0.0])
    np.testing.assert_allclose(turned, view @ TURN.T, atol=1e-9)


def test_the_most_strained_cells_are_the_stretched_ones():
    mesh = box_tetrahedra(4, 1, 1, (4.0, 1.0, 1.0))
    pose = mesh.points.copy()
    far = mesh.points[:, 0] > 3.5
    pose[far, 0] += 0.5 * (mesh.points[far, 0] - 3.5) * 2       # stretch the last cube
    cells = most_strained_cells(mesh.points, mesh.cells, pose, share=0.25)
    assert len(cells) == 6
    assert (mesh.points[mesh.cells[cells]][..., 0].mean(axis=1) > 3.0).all()
    turned = most_strained_cells(mesh.points @ TURN.T, mesh.cells, pose @ TURN.T, share=0.25)
    np.testing.assert_array_equal(turned, cells)
