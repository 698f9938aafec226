"""Joint trees to bones and back (torchfit.mesh.formats.joints)."""
from __future__ import annotations

import numpy as np
import pytest

from torchfit.mesh.formats.folder import AnimationError
from torchfit.mesh.formats.joints import bone_joints, fan_triangles, skeleton_from_joints
from torchfit.mesh.rig import Skeleton, blend


def test_fans_keep_the_polygon_order_and_refuse_bad_counts():
    faces = fan_triangles(np.array([3, 4, 5]), np.arange(12), "x")
    assert faces.tolist() == [[0, 1, 2], [3, 4, 5], [3, 5, 6], [7, 8, 9], [7, 9, 10],
                              [7, 10, 11]]
    with pytest.raises(AnimationError, match="do not match"):
        fan_triangles(np.array([3, 2]), np.arange(5), "x")


def rigid(F, J, seed=0):
    rng = np.random.default_rng(seed)
    from scipy.spatial.transform import Rotation

    T = np.zeros((F, J, 3, 4))
    T[..., :3] = Rotation.random(F * J, random_state=seed).as_matrix().reshape(F, J, 3, 3)
    T[..., 3] = rng.normal(size=(F, J, 3))
    return T


def test_a_branching_joint_splits_its_weight_and_skins_the_same():
    # root 0 with two children 1, 2; joint 2 a weighted end joint, joint 1 an unweighted one
    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]])
    parents = np.array([-1, 0, 0])
    points = np.random.default_rng(1).normal(size=(10, 3))
    weights = np.stack([np.full(10, 0.7), np.zeros(10), np.full(10, 0.3)], 1)
    T = rigid(2, 3)
    skeleton = skeleton_from_joints(positions, parents, T, weights, ["r", "x", "y"], 0.1,
                                    points, "s")
    assert skeleton.names == ["r->x", "r->y", "y"]
    assert np.allclose(skeleton.heads, [[0, 0, 0], [0, 0, 0], [0, 1, 0]])
    assert np.allclose(skeleton.tails, [[1, 0, 0], [0, 1, 0], [0, 1, 0]])
    assert np.allclose(skeleton.weights[0], [0.35, 0.35, 0.3])
    assert np.allclose(blend(points, skeleton.weights, skeleton.transforms),
                       blend(points, weights, T))


def test_bones_to_joints_and_back_is_the_same_rig():
    heads = np.array([[0, 0, 0], [0, 0, 1.0]])
    tails = np.array([[0, 0, 1.0], [0, 0, 2.0]])
    weights = np.array([[1.0, 0.0], [0.5, 0.5], [0.0, 1.0]])
    skeleton = Skeleton(heads, tails, rigid(3, 2), 0.2, weights, ["up", "fore"])
    paths, parents, positions, mover = bone_joints(skeleton)
    assert paths == ["up", "up/fore", "up/fore/fore_end"]
    assert parents.tolist() == [-1, 0, 1] and mover.tolist() == [0, 1, 1]
    joint_weights = np.concatenate([weights, np.zeros((3, 1))], 1)
    back = skeleton_from_joints(positions, parents, skeleton.transforms[:, mover],
                                joint_weights, ["up", "fore", "end"], None, heads + [0.3, 0, 0],
                                "s")
    assert back.names == ["up", "fore"]
    assert np.allclose(back.heads, heads) and np.allclose(back.tails, tails)
    assert np.allclose(back.transforms, skeleton.transforms)
    assert np.allclose(back.weights, weights)
    assert back.attach_radius == pytest.approx(0.4 * 0.3)       # 0.4 x the median distance


def test_a_vertex_without_weight_is_refused():
    with pytest.raises(AnimationError, match="vertex 1 has all skinning weights zero"):
        skeleton_from_joints(np.zeros((2, 3)), np.array([-1, 0]), rigid(1, 2),
                             np.array([[1.0, 0], [0, 0]]), ["a", "b"], 0.1, np.zeros((2, 3)),
                             "s")
