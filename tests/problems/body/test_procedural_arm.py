"""The procedural arm of docs/problems.md (torchfit.problems.body.procedural_arm)."""
import numpy as np
import pytest
import trimesh

from torchfit.problems.body.procedural_arm import (ArmShape, arm_animation, arm_surface, attach_radius,
                               elbow_angles, elbow_region, region_labels)


def test_surface_is_closed_outward_and_has_the_arm_volume():
    shape = ArmShape()
    vertices, faces = arm_surface(shape)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0                       # outward normals
    # a tapered tube with rounded ends: between the cone frustum minus both caps and the frustum
    L, r0, r1 = shape.length, shape.r_shoulder, shape.r_wrist
    frustum = np.pi * L / 3 * (r0 ** 2 + r0 * r1 + r1 ** 2)
    assert 0.85 * frustum < mesh.volume < 1.05 * frustum
    assert np.isclose(vertices[:, 2].min(), 0) and np.isclose(vertices[:, 2].max(), L)


def test_animation_follows_the_seed_schedule():
    shape = ArmShape()
    angles = elbow_angles(shape)
    assert angles.shape == (48,)
    assert angles[0] == 0 and angles[11] == pytest.approx(120) and angles[23] == pytest.approx(0)
    assert angles[35] == pytest.approx(-10) and angles[47] == pytest.approx(0)
    assert np.all(np.diff(angles[:12]) > 0) and np.all(np.diff(angles[24:36]) < 0)


def test_rig_moves_the_forearm_about_the_elbow_and_bulges_the_front():
    shape = ArmShape()
    data = arm_animation(shape)
    rest, frames = data["rest_vertices"], data["frames"]
    assert frames.shape == (48, len(rest), 3)
    assert np.allclose(frames[0], rest)          # frame 0: rest pose, no bulge
    wrist = np.argmax(rest[:, 2])                # the wrist pole
    elbow = np.array([0, 0, shape.upper])
    # at 120 degrees the wrist pole lies on the rotated forearm axis
    a = np.radians(120)
    expected = elbow + shape.fore * np.array([np.sin(a), 0, np.cos(a)])
    assert np.allclose(frames[11, wrist], expected, atol=1e-9)
    # bicep: front (+x) of the upper arm moves outward at full bend, the back does not
    bulge = data["bulge"]
    rho = np.hypot(rest[:, 0], rest[:, 1])
    middle = np.abs(rest[:, 2] - 0.6 * shape.upper) < 0.03
    front = (rest[:, 0] > 0.95 * rho) & middle
    back = (rest[:, 0] < -0.95 * rho) & middle
    assert bulge[11, front, 0].min() > 0.5 * shape.bicep_bulge
    assert np.abs(bulge[11, back]).max() < 1e-12
    assert bulge[35, back, 0].max() < -0.5 * shape.tricep_bulge   # tricep at -10 degrees
    # the shoulder end does not move
    assert np.allclose(frames[:, np.argmin(rest[:, 2])], rest[np.argmin(rest[:, 2])])


def test_regions_and_elbow():
    shape = ArmShape()
    z = 0.1
    r = 0.05 + (0.035 - 0.05) * z / shape.length
    points = np.array([[0.0, 0, z], [0.6 * r, 0, z], [0.9 * r, 0, z]])
    assert list(region_labels(shape, points)) == [0, 1, 2]
    assert list(elbow_region(shape, np.array([[0, 0, shape.upper], [0, 0, 0.0]]))) == [True, False]
    assert attach_radius(shape) == pytest.approx(0.4 * (0.05 + 0.035) / 2, rel=1e-3)
