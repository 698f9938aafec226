"""Frames held out of a body's fit: repeated poses grouped, the rules, bad settings refused."""
from __future__ import annotations

import types

import numpy as np
import pytest

from helpers.repeating_animation import ANGLES, POSES, write_tube
from torchfit.mesh.formats.folder import load_animation
from torchfit.problems import ProblemConfigError, build_problem
from torchfit.problems.body.held_out import pose_groups, split_frames


@pytest.fixture(scope="module")
def tube(tmp_path_factory):
    return load_animation(write_tube(tmp_path_factory.mktemp("tube") / "tube"))


def settings(frames=None, validation_frames=None, validation_every=0, tol=1e-6):
    return types.SimpleNamespace(frames=frames, validation_frames=validation_frames,
                                 validation_every=validation_every, validation_repeat_tol=tol)


def split(tube, **kwargs):
    return split_frames(settings(**kwargs), tube.rest_vertices, tube.frames)


def test_repeated_poses_are_grouped_and_a_tolerance_separates_close_ones(tube):
    labels = pose_groups(tube.frames, 1e-9)
    assert [sorted(np.flatnonzero(labels == g).tolist()) for g in range(labels.max() + 1)] \
        == POSES
    # two poses 12 degrees apart differ by centimetres: one group only beyond that
    moved = np.linalg.norm(tube.frames[1] - tube.frames[0], axis=-1).max()
    assert 0.01 < moved < 0.03
    assert pose_groups(tube.frames, 1.01 * moved)[:2].tolist() == [0, 0]
    # a round-off difference (a re-exported frame) is the same pose
    noisy = tube.frames.copy()
    noisy[4] += 1e-12
    assert pose_groups(noisy, 1e-9).tolist() == pose_groups(tube.frames, 1e-9).tolist()
    assert pose_groups(noisy, 0.0)[4] != pose_groups(noisy, 0.0)[0]


def test_a_validation_frame_takes_its_repeats_out_of_the_fit(tube):
    held = split(tube, validation_frames=[1])
    assert held.validation == [1] and held.repeats == [3]
    assert held.fitted == [0, 2, 4, 5, 6, 7] and held.poses == 5
    line = held.describe()
    assert "frames [1] held out" in line and "fitting 6 frames (4 distinct poses)" in line
    assert "frames [3] repeat a validation pose and leave the fit too" in line
    # problem.frames restricts what is fitted; a validation frame outside it is allowed
    held = split(tube, frames=[0, 1, 3, 4], validation_frames=[2])
    assert held.fitted == [0, 1, 3, 4] and held.validation == [2] and held.repeats == []
    assert split(tube) is None


def test_every_kth_distinct_pose_is_held_out(tube):
    held = split(tube, validation_every=2)     # poses 2 and 4 of 5: frames 1 (+3) and 5 (+7)
    assert held.validation == [1, 5] and held.repeats == [3, 7]
    assert held.fitted == [0, 2, 4, 6]
    held = split(tube, validation_every=3)     # the third pose: frame 2
    assert held.validation == [2] and held.fitted == [0, 1, 3, 4, 5, 6, 7]
    # among problem.frames only: their distinct poses are 0, 12, 24 degrees
    held = split(tube, frames=[0, 1, 2, 3], validation_every=2)
    assert held.validation == [1] and held.repeats == [3] and held.fitted == [0, 2]


@pytest.mark.parametrize("kwargs,match", [
    ({"validation_frames": [8]}, r"problem.validation_frames=\[8\]: frame 8 is not a frame of "
                                 r"the animation \(0..7\)"),
    ({"validation_frames": [-1]}, "frame -1 is not a frame"),
    ({"validation_frames": []}, "lists no frame"),
    ({"validation_frames": [1, 1]}, "lists a frame twice"),
    ({"frames": [0, 1, 2], "validation_frames": [2, 5]},
     r"overlaps problem.frames \(frames \[2\]\): a frame is fitted or validated, not both"),
    ({"frames": [1, 3], "validation_frames": [3]}, "overlaps problem.frames"),
    # frame 3 repeats frame 1's pose: nothing is left to fit
    ({"frames": [3], "validation_frames": [1]}, "holds out every frame of the fit"),
    ({"validation_frames": [0, 1, 2, 5, 6]}, "holds out every frame of the fit"),
    ({"validation_every": 1}, r"problem.validation_every=1: holds out every frame of the fit"),
    ({"validation_every": 6}, "holds out no pose: the frames hold 5 distinct poses; choose "
                              "k <= 5"),
    ({"validation_every": -2}, "must be an integer >= 0"),
    ({"validation_frames": [1], "validation_every": 2}, "give one of them"),
    ({"validation_every": 2, "tol": -1.0}, "validation_repeat_tol=-1.0: must be a number >= 0"),
    ({"frames": [0, 9], "validation_every": 2}, r"problem.frames=\[0, 9\]: frame 9 does not "
                                                r"exist"),
])
def test_bad_validation_settings_are_refused_naming_the_setting(tube, kwargs, match):
    with pytest.raises(ProblemConfigError, match=match):
        split(tube, **kwargs)


def test_the_body_fits_the_other_frames_and_builds_its_validation_problem(tmp_path):
    folder = write_tube(tmp_path / "tube")
    settings = {"path": str(folder), "tet_edge_length": 0.3, "grid": [2, 2, 2],
                "cache_dir": str(tmp_path / "cache")}
    body = build_problem("animation", {**settings, "validation_frames": [2, 5]})
    assert body.frame_numbers() == [0, 1, 3, 4, 6] and body.n_frames == 5
    np.testing.assert_array_equal(body.animation.frames, load_animation(folder).frames[
        [0, 1, 3, 4, 6]])
    held = body.validation_problem()
    assert held.frame_numbers() == [2, 5] and held.frame_split is None
    assert held.validation_problem() is None
    # the same mesh and parameters; the animation's own targets on the held-out frames
    assert held.tet.key == body.tet.key
    assert held.parameterization.n_params == body.parameterization.n_params
    np.testing.assert_array_equal(held.data.reshape(2, -1, 3).numpy(),
                                  load_animation(folder).frames[[2, 5]][:, held.observed_vertices])
    assert [round(a) for a in np.asarray(ANGLES)[held.frame_numbers()]] == [24, -12]
    # the problem on a subset of its frames (a continuation's first stage) validates nothing
    assert body.with_frames([0, 1]).frame_split is None
    with pytest.raises(ProblemConfigError, match="overlaps problem.frames"):
        build_problem("animation", {**settings, "frames": [0, 1, 2], "validation_frames": [2]})
