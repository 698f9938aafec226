"""Linear blend skinning and the bone-transform checks (torchfit.mesh.rig)."""
import numpy as np
import pytest

from torchfit.mesh import MeshError
from torchfit.mesh.rig import (axial_coordinates, blend, check_transforms, distance_weights,
                               segment_distances)


def rotation_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_segment_distances_match_brute_force():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(50, 3))
    heads, tails = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
    s = np.linspace(0, 1, 20001)
    for b in range(3):
        samples = heads[b] + s[:, None] * (tails[b] - heads[b])
        brute = np.linalg.norm(points[:, None] - samples[None], axis=-1).min(axis=1)
        assert np.allclose(segment_distances(points, heads, tails)[:, b], brute, atol=1e-4)
    axial = axial_coordinates(heads[:1] + 0.25 * (tails[:1] - heads[:1]), heads, tails)
    assert axial[0, 0] == pytest.approx(0.25)


def test_distance_weights_rows_sum_to_one_and_follow_the_nearest_bone():
    d = np.array([[0.0, 5.0], [1.0, 1.0], [5.0, 6.0]])
    w = distance_weights(d, reach=2.0)
    assert np.allclose(w.sum(axis=1), 1.0)
    assert w[0, 0] == pytest.approx(1.0)          # only bone 0 within reach
    assert w[1, 0] == pytest.approx(0.5)          # equidistant: blended equally
    assert w[2, 0] > w[2, 1] > 0                   # none within reach: all bones, nearer heavier


def test_blend_reproduces_rigid_and_affine_motion():
    rng = np.random.default_rng(1)
    points = rng.normal(size=(30, 3))
    A = rotation_z(0.7) @ np.diag([1.2, 0.9, 1.1])
    t = np.array([0.1, -0.2, 0.3])
    transforms = np.broadcast_to(np.concatenate([A, t[:, None]], axis=1), (4, 2, 3, 4))
    weights = rng.random((30, 2))
    weights /= weights.sum(axis=1, keepdims=True)
    moved = blend(points, weights, transforms)
    assert moved.shape == (4, 30, 3)
    assert np.allclose(moved, points @ A.T + t, atol=1e-13)   # same transform on every bone


def test_blend_interpolates_between_bones():
    T = np.zeros((1, 2, 3, 4))
    T[0, :, :, :3] = np.eye(3)
    T[0, 1, :, 3] = [1.0, 0, 0]                   # bone 1 translates by +x
    moved = blend(np.zeros((1, 3)), np.array([[0.25, 0.75]]), T)
    assert np.allclose(moved[0, 0], [0.75, 0, 0])


def test_check_transforms_names_the_bad_bone_and_frame():
    T = np.zeros((3, 2, 3, 4))
    T[..., :3] = np.eye(3)
    assert check_transforms(T, 2, 3, "rig").shape == (3, 2, 3, 4)
    bad = T.copy()
    bad[2, 1, 0, 3] = np.nan
    with pytest.raises(MeshError, match="bone 1 in frame 2 is not finite"):
        check_transforms(bad, 2, 3, "rig")
    with pytest.raises(MeshError, match=r"shape \(frames, 2, 3, 4\)"):
        check_transforms(T[:, :1], 2, 3, "rig")
    with pytest.raises(MeshError, match="3 frames of bone transforms for 5 frames"):
        check_transforms(T, 2, 5, "rig")
    mirror = T.copy()
    mirror[1, 0, 0, 0] = -1
    with pytest.raises(MeshError, match="bone 0 in frame 1 is not invertible or mirrors"):
        check_transforms(mirror, 2, 3, "rig")
    homogeneous = np.zeros((3, 2, 4, 4))
    homogeneous[..., :3, :3] = np.eye(3)
    homogeneous[..., 3, 3] = 1
    assert np.array_equal(check_transforms(homogeneous, 2, 3, "rig"), T)
