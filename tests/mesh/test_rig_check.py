"""The rig checked against the frames before fitting (torchfit.mesh.rig_check): the frames'
scale, and skinning the rest with the manifest's weights, on a tube that is not the arm."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from helpers.rigged_tube import tube
from torchfit.mesh import AnimationError, DrivenSurface
from torchfit.mesh.rig_check import (RigReport, check_animation, frame_ranges, size, skin)
from torchfit.mesh.rig import blend


def with_transforms(animation, transforms):
    return dataclasses.replace(animation, skeleton=dataclasses.replace(
        animation.skeleton, transforms=transforms))


def refused(animation, *words):
    with pytest.raises(AnimationError) as info:
        check_animation(animation)
    text = str(info.value)
    assert "\n" not in text and all(w in text for w in words), text
    return text


@pytest.mark.parametrize("axis", ["x", "y"])
def test_a_correct_rig_with_bulges_passes(axis):
    """Bulges of 1.5 cm on a 0.6 m tube (up to 2.5 % of its diagonal at one vertex) pass:
    the statistic is the median per frame and bone."""
    animation = tube(axis)
    rest = animation.rest_vertices
    diagonal = np.linalg.norm(rest.max(0) - rest.min(0))
    skinned = skin(rest, animation.skeleton.weights, animation.skeleton.transforms)
    largest = np.linalg.norm(skinned - animation.frames, axis=-1).max()
    assert 0.02 < largest / diagonal < 0.03                    # the bulge is there
    report = check_animation(animation)
    assert isinstance(report, RigReport) and report.skinning_error < 0.005
    assert 0.6 < report.scale_ratios.min() <= report.scale_ratios.max() < 1.0 + 1e-12
    assert "no skinning weights" not in report.line()


def test_skin_is_linear_blend_skinning_in_chunks(monkeypatch):
    animation = tube("x")
    import torchfit.mesh.rig_check as rig_check

    monkeypatch.setattr(rig_check, "_CHUNK_VALUES", 1)         # one frame per chunk
    np.testing.assert_allclose(skin(animation.rest_vertices, animation.skeleton.weights,
                                    animation.skeleton.transforms),
                               blend(animation.rest_vertices, animation.skeleton.weights,
                                     animation.skeleton.transforms), atol=1e-14)


def test_transposed_transforms_are_refused_naming_frames_bones_and_cause():
    animation = tube("x")
    transforms = animation.skeleton.transforms.copy()
    transforms[..., :3] = np.swapaxes(transforms[..., :3], -1, -2)
    text = refused(with_transforms(animation, transforms), "tube-x/animation.yaml",
                   "does not reproduce frames 1-4 (4 of 5) on bones tip",
                   "likely cause: transposed A")
    assert "base" not in text.split("on bones")[1].split(":")[0]


@pytest.mark.parametrize("change,cause", [
    ("translations", "translations in another unit than the surfaces (they fit when "
                     "multiplied by 1/100)"),
    ("inverted", "likely cause: inverted transforms"),
    ("bone-local", "likely cause: bone-local transforms"),
    ("garbage", "no simple mix-up"),
])
def test_other_mix_ups_are_named(change, cause):
    animation = tube("y")
    skeleton = animation.skeleton
    transforms = skeleton.transforms.copy()
    A, t = transforms[..., :3], transforms[..., 3]
    if change == "translations":
        transforms[..., 3] = 100 * t
    elif change == "inverted":
        inverse = np.linalg.inv(A)
        transforms[..., :3] = inverse
        transforms[..., 3] = -np.einsum("fbij,fbj->fbi", inverse, t)
    elif change == "bone-local":
        transforms[..., 3] = t + np.einsum("fbij,bj->fbi", A, skeleton.heads)
    else:
        rng = np.random.default_rng(3)
        q, _ = np.linalg.qr(rng.standard_normal((5, 2, 3, 3)))
        transforms[..., :3] = q * np.sign(np.linalg.det(q))[..., None, None]
    refused(with_transforms(animation, transforms), cause)


def test_frames_in_another_unit_are_refused_with_or_without_a_skeleton():
    animation = tube("x")
    refused(dataclasses.replace(animation, frames=animation.frames * 1000),
            "frames 0-4 (5 of 5) are 1000 times the rest surface's size",
            "frames in mm against a rest in m?")
    driven = dataclasses.replace(animation, skeleton=None, driven=DrivenSurface(
        animation.rest_vertices[:, 0] > 0.5, 0.01))
    frames = animation.frames.copy()
    frames[3] /= 100.0
    refused(dataclasses.replace(driven, frames=frames), "frames 3 (1 of 5) are 0.008",
            "frames in m against a rest in cm?")
    report = check_animation(driven)
    assert report.skinning_error is None and "skinning not checked" in report.line()


def test_a_failing_check_with_a_tolerance_and_the_helpers():
    animation = tube("x")
    animation.frames[1:] += [0.0, 0.0, 0.1]                     # 17 % of the body's size
    with pytest.raises(AnimationError, match="frames 1-4 .* on bones base, tip: a median "
                       r"distance up to 0.1 m, 16.\d % of the body's size \(0.6\d+ m; "
                       r"tolerance 5 %\); no simple mix-up"):
        check_animation(animation)
    assert check_animation(animation, tolerance=0.5).skinning_error < 0.5
    assert frame_ranges([3, 1, 2, 7, 9, 10]) == "1-3, 7, 9-10"
    assert frame_ranges(range(0, 20, 2), limit=3) == "0, 2, 4, ..."
    points = np.array([[[0.0, 0, 0], [2, 0, 0]]])
    assert size(points)[0] == pytest.approx(1.0)


@pytest.mark.parametrize("change", [None, "transposed", "inverted"])
def test_with_weights_from_distance_the_skinning_is_checked_too(change):
    """Issue 38: with ``weights: distance`` transposed bone rotations were fitted (the
    skinning check ran only with a weights file)."""
    animation = tube("x")
    animation = dataclasses.replace(animation, skeleton=dataclasses.replace(
        animation.skeleton, weights=None))
    transforms = animation.skeleton.transforms.copy()
    A, t = transforms[..., :3], transforms[..., 3]
    if change is None:
        report = check_animation(animation)
        assert report.distance_weights and report.skinning_error < 0.01
        assert "skinning the rest with weights from distance reproduces" in report.line()
        return
    if change == "transposed":
        transforms[..., :3] = np.swapaxes(A, -1, -2)
    else:
        inverse = np.linalg.inv(A)
        transforms[..., :3] = inverse
        transforms[..., 3] = -np.einsum("fbij,fbj->fbi", inverse, t)
    refused(with_transforms(animation, transforms),
            "skinning the rest surface with weights from distance (weights: distance)",
            "does not reproduce frames 1-4 (4 of 5) on bones tip",
            f"likely cause: {change}")
