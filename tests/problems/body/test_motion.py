"""What of a body's motion the pictures show (torchfit.problems.body.motion): the most
deformed frame, the camera, the most strained tetrahedra; each rotation-equivariant."""
from __future__ import annotations

import numpy as np
import pytest
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


# -- the pictures' up: the file's up axis, else the rig's ----------------------------------
def test_the_camera_stands_on_the_given_up_exactly_looking_across_it():
    rest, frames = bent_tube()
    frames = frames[:3].copy()
    frames[2, :, 1] += 0.1 * rest[:, 1]          # the bend stretches it: motion in the y-z plane
    tilted = np.array([0.5, 1.0, 0.6])           # not across the least motion (x)
    view = view_axes(rest, frames, tilted)
    np.testing.assert_allclose(view[2], tilted / np.linalg.norm(tilted), atol=1e-12)
    np.testing.assert_allclose(view @ view.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(view) > 0
    # depth: the least motion among the directions across up
    motion = (frames - rest[None]).reshape(-1, 3)
    motion = motion - motion.mean(axis=0)
    spread = motion.T @ motion
    angles = np.linspace(0, np.pi, 181)
    across = np.cos(angles)[:, None] * view[0] + np.sin(angles)[:, None] * view[1]
    assert view[1] @ spread @ view[1] <= np.einsum("ai,ij,aj->a", across, spread,
                                                   across).min() + 1e-15
    turned = view_axes(rest @ TURN.T, frames @ TURN.T, TURN @ tilted)
    np.testing.assert_allclose(turned, view @ TURN.T, atol=1e-9)


def test_the_rig_signs_the_long_axis_from_its_root_to_its_largest_branch():
    from helpers.standing_figure import figure_animation
    from torchfit.mesh import Skeleton
    from torchfit.problems.body.motion import picture_up, rig_up

    figure = figure_animation()["skeleton"]         # pelvis root: legs 2+2 bones, spine 4
    down = np.array([0.0, -1.0, 0.0])
    np.testing.assert_array_equal(rig_up(figure, down), [0, 1, 0])
    np.testing.assert_array_equal(rig_up(figure, -down), [0, 1, 0])
    arm = Skeleton(np.array([[0, 0, 0], [0, 0, 0.3]]), np.array([[0, 0, 0.3], [0, 0, 0.58]]),
                   np.zeros((1, 2, 3, 4)), 0.02)    # the procedural arm: shoulder to wrist
    np.testing.assert_array_equal(rig_up(arm, [0, 0, -1.0]), [0, 0, 1])
    across = Skeleton(np.zeros((1, 3)), np.array([[0.2, 0, 0.01]]), np.zeros((1, 1, 3, 4)),
                      0.02)                         # a bone across the long axis: no say
    assert rig_up(across, [0, 0, 1.0]) is None and rig_up(None, [0, 0, 1.0]) is None
    assert picture_up(np.array([0, 2.0, 0]), figure, down)[0].tolist() == [0, 1, 0]
    assert picture_up(None, None, down)[0].tolist() == down.tolist()


FIGURE_SETTINGS = {"tet_edge_length": 0.1}


def figure_problem(tmp_path, kind, **options):
    from helpers.standing_figure import write_figure
    from torchfit import build_problem

    suffix = {"usd-y": ".usda", "usd-z": ".usda", "gltf": ".glb"}.get(kind, "")
    path = write_figure(tmp_path / f"figure-{kind}{suffix}", kind, **options)
    return build_problem("animation", {"path": str(path), "cache_dir": str(tmp_path / "cache"),
                                       **FIGURE_SETTINGS})


@pytest.mark.parametrize("kind,up", [("usd-y", [0, 1, 0]), ("gltf", [0, 1, 0]),
                                     ("usd-z", [0, 0, 1])])
def test_a_standing_figure_is_drawn_on_its_files_up_axis(tmp_path, kind, up):
    pytest.importorskip("pxr" if kind.startswith("usd") else "pygltflib")
    problem = figure_problem(tmp_path, kind)
    np.testing.assert_array_equal(problem.animation.up, up)
    # the volume's long tail is the legs: the principal axis points down (the old up)
    assert problem.grid.axes[2] @ up < -0.99
    np.testing.assert_allclose(problem.view_axes[2], up, atol=1e-12)
    assert np.linalg.det(problem.view_axes) > 0
    assert problem.view_axes[0] @ [1, 0, 0] > 0.99      # the spine bends towards +x: right


def test_without_a_file_up_the_rig_stands_a_turned_figure(tmp_path):
    problem = figure_problem(tmp_path, "folder", rotation=TURN)
    assert problem.animation.up is None
    assert problem.grid.axes[2] @ (TURN @ [0, 1, 0]) < -0.99
    # up is the long axis (of the tetrahedra: within 1e-4 of the figure's), signed by the rig
    np.testing.assert_allclose(problem.view_axes[2], TURN @ [0, 1, 0], atol=1e-4)


def test_the_manifest_names_the_up_axis_of_a_body_without_a_rig(tmp_path):
    plain = figure_problem(tmp_path / "plain", "folder", rig=False)
    # no rig, no up: the long axis with its own sign (down here: the legs' tail)
    np.testing.assert_allclose(plain.view_axes[2], plain.grid.axes[2], atol=1e-12)
    named = figure_problem(tmp_path / "named", "folder", rig=False, up="y")
    np.testing.assert_array_equal(named.animation.up, [0, 1, 0])
    np.testing.assert_allclose(named.view_axes[2], [0, 1, 0], atol=1e-12)
