"""Joint trees to bones and back (torchfit.mesh.formats.joints)."""
from __future__ import annotations

import numpy as np
import pytest

from torchfit.mesh.formats.folder import AnimationError
from torchfit.mesh.formats.joints import (bone_joints, end_bone_tails, end_extent,
                                           fan_triangles,
                                          skeleton_from_joints)
from torchfit.mesh.rig import Skeleton, blend, skeleton_drive


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
    assert np.allclose(skeleton.tails[:2], [[1, 0, 0], [0, 1, 0]])
    # the weighted end joint y: a bone along its axis (from r), over its region's reach
    assert np.allclose(skeleton.tails[2, [0, 2]], 0) and skeleton.tails[2, 1] > 1
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
                                joint_weights, ["up", "fore", "end"], None,
                                np.array([[0.3, 0, 0], [0.3, 0, 1], [0.3, 0, 2]]), "s")
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


def limb(n_around=12, n_rings=31, length=0.5, radius=0.05, bend=60.0):
    """A capped tube along x, three joints at 0, 1/3, 2/3 of it, weights by thirds blended
    over a ring either side; the end joint alone turns about z by ``0 .. bend`` degrees."""
    from scipy.spatial.transform import Rotation

    phi = 2 * np.pi * np.arange(n_around) / n_around
    x = np.linspace(0, length, n_rings)
    ring = np.stack([np.broadcast_to(x[:, None], (n_rings, n_around)),
                     radius * np.cos(phi)[None].repeat(n_rings, 0),
                     radius * np.sin(phi)[None].repeat(n_rings, 0)], -1).reshape(-1, 3)
    rest = np.concatenate([ring, [[0, 0, 0], [length, 0, 0]]])
    joints = np.array([[0, 0, 0], [length / 3, 0, 0], [2 * length / 3, 0, 0]])
    ramp = np.clip((rest[:, :1] - joints[None, 1:, 0]) / (length / 15) + 0.5, 0, 1)  # (V, 2)
    weights = np.stack([1 - ramp[:, 0], ramp[:, 0] - ramp[:, 1], ramp[:, 1]], 1)
    angles = np.linspace(0, bend, 4)
    T = np.zeros((len(angles), 3, 3, 4))
    T[..., :3] = np.eye(3)
    R = Rotation.from_euler("z", angles[:, None], degrees=True).as_matrix()
    T[:, 2, :, :3] = R
    T[:, 2, :, 3] = joints[2] - np.einsum("fij,j->fi", R, joints[2])
    return rest, joints, np.array([-1, 0, 1]), weights, T


def test_a_weighted_end_joint_drives_the_flesh_its_weights_cover():
    rest, joints, parents, weights, T = limb()
    skeleton = skeleton_from_joints(joints, parents, T, weights, ["upper", "lower", "end"],
                                    None, rest, "limb")
    assert skeleton.names == ["upper", "lower", "end"]
    # the end bone: from its joint along the axis from its parent to the flat end (0.5) its
    # weights reach, and says so
    assert np.allclose(skeleton.heads[2], [1 / 3, 0, 0])
    assert np.allclose(skeleton.tails[2], [0.5, 0, 0])
    assert skeleton.origin["lengths"][2].endswith("along its axis (a flat end)")
    assert skeleton.origin["lengths"][:2] == ["authored: the joint to its child joint"] * 2
    assert skeleton.origin["attach_radius"].startswith("derived: 0.4 x the median distance")
    # material points inside the tube (tet vertices): those of the end bone follow it
    rng = np.random.default_rng(0)
    inside = rng.uniform([0, -0.05, -0.05], [0.5, 0.05, 0.05], size=(4000, 3))
    inside = inside[np.linalg.norm(inside[:, 1:], axis=1) < 0.048]
    cells = np.arange(12).reshape(3, 4)                       # boundary only for the start
    drive = skeleton_drive(inside, cells, skeleton, rest, np.array([[0, 1, 2]]),
                           blend(rest, weights, T))
    assert drive.idle_bones == []
    driven = inside[drive.vertices]
    along_end = driven[:, 0] > 0.4                            # the end bone's flesh
    assert along_end.sum() > 10 and driven[:, 0].max() > 0.44
    # in the full bend each of them is where the end joint's rotation takes it
    R, t = T[-1, 2, :, :3], T[-1, 2, :, 3]
    assert np.abs(drive.positions[-1][along_end] - (driven[along_end] @ R.T + t)).max() < 1e-12
    tip = drive.positions[-1][along_end].mean(0) - joints[2]
    direction = np.degrees(np.arctan2(tip[1], tip[0]))
    assert direction == pytest.approx(60.0, abs=1.0)         # the bent bone's direction
    # the same skeleton with the end joint a point (the old reading) drives no flesh there
    point = Skeleton(skeleton.heads, np.concatenate([skeleton.tails[:2], skeleton.heads[2:]]),
                     skeleton.transforms, skeleton.attach_radius, skeleton.weights,
                     skeleton.names)
    held = skeleton_drive(inside, cells, point, rest, np.array([[0, 1, 2]]),
                          blend(rest, weights, T))
    assert (inside[held.vertices][:, 0] > 0.4).sum() == 0


def test_end_bones_authored_rootless_tiny_and_idle():
    rest, joints, parents, weights, T = limb()
    normalised = weights / weights.sum(1, keepdims=True)
    # an authored length wins over the data (glTF extras / USD torchfit:boneLength)
    tails, how = end_bone_tails(joints, parents, normalised, rest, np.array([2]),
                                np.array([0.0, 0.0, 0.1]), "torchfit:boneLength")
    assert np.allclose(tails, [[1 / 3 + 0.1, 0, 0]])
    assert how == ["authored: torchfit:boneLength"]
    # a single weighted root joint: the principal axis of its vertices, to their side
    single, _ = end_bone_tails(np.array([[0.0, 0, 0]]), np.array([-1]),
                               np.ones((len(rest), 1)), rest, np.array([0]))
    assert single[0, 0] > 0.3 and np.allclose(single[0, 1:], 0, atol=1e-9)
    # a tiny region (the end joint dominates no vertex): where its weight is >= half its most
    tiny = normalised.copy()
    tiny[:, 2] *= 0.3
    tiny /= tiny.sum(1, keepdims=True)
    tails, _ = end_bone_tails(joints, parents, tiny, rest, np.array([2]))
    assert tails[0, 0] > 0.4 and np.allclose(tails[0, 1:], 0)
    # a bone far from every material point drives nothing and is named
    skeleton = skeleton_from_joints(joints, parents, T, weights, ["upper", "lower", "end"],
                                    0.01, rest, "limb")
    skeleton.heads[2] += [0, 1.0, 0]
    skeleton.tails[2] += [0, 1.0, 0]
    inside = np.random.default_rng(1).uniform([0, -0.04, -0.04], [0.5, 0.04, 0.04], (2000, 3))
    drive = skeleton_drive(inside, np.arange(12).reshape(3, 4), skeleton, rest,
                           np.array([[0, 1, 2]]), blend(rest, weights, T))
    assert drive.idle_bones == ["end"]


def test_an_end_bone_ends_at_a_flat_end_or_at_its_caps_centre():
    """A tube of radius 0.05 whose last 0.3 m an end bone's weights dominate: flat, the bone
    reaches the end; capped by a hemisphere (15-degree rings), the cap's centre."""
    phi = np.radians(np.arange(0, 360, 30))
    ring = lambda s, r: np.stack([np.full(phi.size, s), r * np.cos(phi), r * np.sin(phi)], 1)  # noqa: E731
    body = np.concatenate([ring(s, 0.05) for s in np.linspace(0, 0.3, 13)])
    flat = np.concatenate([body, [[0.3, 0, 0]]])
    angles = np.radians(np.arange(15, 90, 15))
    cap = np.concatenate([body] + [ring(0.3 + 0.05 * np.sin(a), 0.05 * np.cos(a))
                                   for a in angles] + [[[0.35, 0, 0]]])
    for points, length, rounding in ((flat, 0.3, 0.0), (cap, 0.3, 0.05)):
        radial = np.linalg.norm(points[:, 1:], axis=1)
        got = end_extent(points[:, 0], radial)
        assert got == pytest.approx((length, rounding), abs=2e-3)
    # a cone tapering to a point (a fingertip): its end radius near the tip is small, so the
    # bone reaches within it of the tip (0.3)
    cone = np.stack([np.linspace(0, 0.3, 20), np.linspace(0.05, 0, 20), np.zeros(20)], 1)
    assert 0.29 < end_extent(cone[:, 0], cone[:, 1])[0] < 0.3


def test_coinciding_or_misplaced_joints_are_refused_naming_them():
    rest, joints, parents, weights, T = limb()
    names = ["upper", "lower", "end"]
    at_origin = np.zeros_like(joints)
    with pytest.raises(AnimationError) as err:
        skeleton_from_joints(at_origin, parents, T, weights, names, None, rest, "limb.usda")
    message = str(err.value)
    assert "\n" not in message and message.startswith("limb.usda: joints upper, lower, end "
                                                       "coincide (all at (0, 0, 0) m")
    assert "apply the armature's rest pose" in message
    # the end joint moved 0.3 m off the limb (0.5 m long): its flesh lies far from it
    off = joints.copy()
    off[2] += [0, 0.3, 0]
    with pytest.raises(AnimationError, match=r"limb.usda: the bones of joint end lie far "
                       r"from the vertices their weights dominate \(joint end: a median "
                       r"0\.3\d+ m away on a body 0\.52 m across"):
        skeleton_from_joints(off, parents, T, weights, names, None, rest, "limb.usda")
    # a weightless root on the first joint is no fault
    with_root = np.concatenate([joints[:1], joints])
    skeleton = skeleton_from_joints(with_root, np.array([-1, 0, 1, 2]),
                                    np.concatenate([T[:, :1], T], 1),
                                    np.concatenate([0 * weights[:, :1], weights], 1),
                                    ["root"] + names, None, rest, "limb.usda")
    assert skeleton.names[0] == "root" and skeleton.n_bones == 4


def test_siblings_may_share_a_point_but_a_bone_may_not_have_no_length():
    """Two thighs and a spine from one hip share a point: a rig. A weighted joint on its
    weighted parent's point: a bone of no length, refused naming both."""
    from torchfit.mesh.formats.joints import check_joint_placement

    rest = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    hip = np.zeros(3)
    positions = np.array([hip, hip, hip, hip, [0, 0, 0.5]])      # root, 3 siblings, a knee
    parents = np.array([-1, 0, 0, 0, 1])
    weights = np.zeros((4, 5))
    weights[:, [1, 2, 3, 4]] = 0.25
    names = ["root", "thigh_l", "thigh_r", "spine", "knee_l"]
    check_joint_placement(positions, parents, weights, rest, names, "figure")   # accepted
    positions[4] = hip                                                         # knee on hip
    with pytest.raises(AnimationError, match=r"figure: joints thigh_l, knee_l coincide"):
        check_joint_placement(positions, parents, weights, rest, names, "figure")
