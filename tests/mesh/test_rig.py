"""What drives a body (torchfit.mesh.rig): linear blend skinning, the bone-transform checks,
the drive of a tetrahedral mesh by a skeleton or a driven surface, joints and the most
rotated frame."""
import numpy as np
import pytest

from torchfit.mesh import DrivenSurface, MeshError, Skeleton, box_tetrahedra, boundary_faces
from torchfit.mesh.rig import (axial_coordinates, blend, check_transforms, distance_weights,
                               rig_description, rig_lines,
                               joint_cells, most_rotated_frame, segment_distances,
                               skeleton_drive, surface_drive)


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
    row_vector = homogeneous.copy()
    row_vector[..., 3, :3] = [0.1, 0.2, 0.3]                    # x' = x M: t in the last row
    with pytest.raises(MeshError, match=r"last row 0 0 0 1; these have it as their last "
                       r"column, the translation in the last row: a row-vector layout"):
        check_transforms(row_vector, 2, 3, "rig")
    skewed = homogeneous.copy()
    skewed[..., 3, 0] = 0.5
    skewed[..., 0, 3] = 0.5
    with pytest.raises(MeshError, match="last row 0 0 0 1$"):
        check_transforms(skewed, 2, 3, "rig")


# -- the drive of a tetrahedral mesh ---------------------------------------------------------
SHIFT = np.array([0.1, -0.05, 0.02])


def translated_box():
    """A 2 x 2 x 4 box (0.5 cubes), its boundary as the animated surface, two frames: at rest
    and moved by ``SHIFT``; ``(points, cells, rest, faces, frames, transforms)``."""
    box = box_tetrahedra(2, 2, 4, size=(1.0, 1.0, 2.0))
    faces = boundary_faces(box.cells)[0]
    frames = np.stack([box.points, box.points + SHIFT])
    transforms = np.zeros((2, 1, 3, 4))
    transforms[:, 0, :, :3] = np.eye(3)
    transforms[1, 0, :, 3] = SHIFT
    return box.points, box.cells, box.points, faces, frames, transforms


def test_skeleton_drive_prescribes_the_vertices_near_the_bone():
    points, cells, rest, faces, frames, transforms = translated_box()
    axis = np.flatnonzero((points[:, 0] == 0.5) & (points[:, 1] == 0.5))
    skeleton = Skeleton(np.array([[0.5, 0.5, 0.0]]), np.array([[0.5, 0.5, 2.0]]), transforms, 0.1)
    drive = skeleton_drive(points, cells, skeleton, rest, faces, frames)
    assert np.array_equal(drive.vertices, axis)
    assert np.allclose(drive.positions, np.stack([points[axis], points[axis] + SHIFT]))
    assert np.array_equal(drive.start[:, axis], drive.positions)
    assert np.allclose(drive.start, frames, atol=1e-12)      # every vertex moves with the rig
    assert drive.per_bone.tolist() == [len(axis)]
    far = Skeleton(skeleton.heads + [5.0, 0, 0], skeleton.tails + [5.0, 0, 0], transforms, 0.1)
    with pytest.raises(MeshError, match=r"^no material point lies within attach_radius=0\.1 m"):
        skeleton_drive(points, cells, far, rest, faces, frames)
    everything = Skeleton(skeleton.heads, skeleton.tails, transforms, 10.0)
    with pytest.raises(MeshError, match="every material point lies within attach_radius"):
        skeleton_drive(points, cells, everything, rest, faces, frames)


def test_surface_drive_prescribes_the_vertices_near_the_driven_region():
    points, cells, rest, faces, frames, _ = translated_box()
    bottom = points[:, 2] == 0.0
    drive = surface_drive(points, DrivenSurface(bottom, 1e-9), rest, faces, frames)
    assert np.array_equal(drive.vertices, np.flatnonzero(bottom))
    assert np.allclose(drive.positions[1], points[bottom] + SHIFT, atol=1e-12)
    assert np.allclose(drive.start, frames, atol=1e-12)
    with pytest.raises(MeshError, match="^no tetrahedron vertex lies within driven.tolerance"):
        surface_drive(points + [0, 0, 5.0], DrivenSurface(bottom, 1e-9), rest, faces, frames)
    with pytest.raises(MeshError, match="every tetrahedron vertex lies within driven.tolerance"):
        surface_drive(points, DrivenSurface(bottom, 10.0), rest, faces, frames)


def test_joint_cells_and_the_most_rotated_frame():
    centroids = np.array([[0.0, 0.0, 0.95], [0.0, 0.0, 0.5], [0.0, 0.0, 1.1]])
    transforms = np.zeros((3, 2, 3, 4))
    transforms[..., :3] = np.eye(3)
    skeleton = Skeleton(np.array([[0, 0, 0.0], [0, 0, 1.0]]), np.array([[0, 0, 1.0], [0, 0, 2.0]]),
                        transforms, 0.05)
    assert joint_cells(centroids, skeleton).tolist() == [0, 2]       # within 3 * 0.05 of z = 1
    assert joint_cells(centroids, None).tolist() == [0, 1, 2]
    apart = Skeleton(skeleton.heads, skeleton.tails + [0, 0, -0.5], transforms, 0.05)
    assert joint_cells(centroids, apart).tolist() == [0, 1, 2]       # no joint: every cell
    for f, degrees in enumerate((0.0, 30.0, 10.0)):
        transforms[f, 1, :, :3] = rotation_z(np.radians(degrees))
    assert most_rotated_frame(skeleton) == 1 and most_rotated_frame(None) == 0


def test_the_rig_described_with_its_origins_and_driven_vertices():
    points, cells, rest, faces, frames, transforms = translated_box()
    two = np.concatenate([transforms, transforms], axis=1)
    heads = np.array([[0.5, 0.5, 0.0], [0.5, 0.5, 1.0]])
    tails = np.array([[0.5, 0.5, 1.0], [0.5, 0.5, 1.75]])
    authored = Skeleton(heads, tails, two, 0.1, names=["lower", "upper"])
    drive = skeleton_drive(points, cells, authored, rest, faces, frames)
    description = rig_description(authored, drive)
    assert [b["length_m"] for b in description["bones"]] == pytest.approx([1.0, 0.75])
    counts = [b["driven_vertices"] for b in description["bones"]]
    assert sum(counts) == len(drive.vertices) and min(counts) > 0
    assert description["bones"][1]["length_from"] == "authored: the file's bone segment"
    assert description["attach_radius_from"] == "authored: the file's attach radius"
    assert description["weights_from"].startswith("derived: from each vertex's distance")
    derived = Skeleton(heads, tails, two, 0.1, names=["lower", "upper"],
                       origin={"lengths": ["authored: a", "derived: b"],
                               "attach_radius": "derived: c", "weights": "authored: d"})
    lines = rig_lines(rig_description(derived))
    assert lines == ["bone lower: 1 m; length authored: a", "bone upper: 0.75 m; length derived: b",
                     "attach radius 0.1 m: derived: c", "weights authored: d"]
    assert rig_lines(description)[0] == f"bone lower: 1 m, {counts[0]:,} driven vertices; " \
        "length authored: the file's bone segment"
