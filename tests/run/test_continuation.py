"""torchfit.run.continuation: the frames far from a fold first, then all (``continuation=true``),
and ``continuation=auto``'s rule (on a capsule, not the arm).

A coarse arm (pytetwild, a fresh mesh per session) with the frames 0 and 3 (elbow up to
30 degrees, no tetrahedron far from its rest volume) and 11 (full bend, where the inner
elbow folds). Which frame counts as near a fold is decided with a threshold taken between
the two measured ratios, so the split does not depend on the mesh pytetwild made.
"""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import pytest
import torch

from torchfit import build_problem, fit
from torchfit.run import FitConfigError, fit_continued
from torchfit.run.continuation import (FIRST_STAGE_DIR, FIRST_STAGE_ITER_FACTOR,
                                       continuation_applies, continuation_setting,
                                       frames_near_fold)
from torchfit.run.start import digest

from helpers.capsule_animation import write_capsule
from helpers.coarse_arm import arm, cache  # noqa: F401 (cache: a fixture)

LM = {"name": "levenberg_marquardt", "max_iter": 3, "max_step": 1.0}
DATA = Path(__file__).resolve().parents[1] / "data"


def between(problem) -> float:
    """A threshold between frame 3's and frame 11's smallest volume ratio at the start
    (half frame 3's: frame 11's may be far below 0, an inverted tetrahedron)."""
    # independent: a solution the test made would warm-start the fit's first simulation
    with torch.no_grad(), problem.warm_starts.independent():
        ratios = problem.report.min_volume_ratio(problem.simulate(problem.field(problem.theta0)))
    numbers = problem.frame_numbers()
    bent, mild = ratios[numbers.index(11)], ratios[numbers.index(3)]
    assert bent < 0.5 * mild < 0.5, ratios    # full bend compresses the inner elbow most
    return float(0.5 * mild)


def test_with_frames_keeps_the_targets_noise_included(cache):
    problem = arm(cache, frames=[0, 3, 11], target="synthetic", noise_of_bulge=0.01)
    sub = problem.with_frames([11, 0])             # in the order given
    rows = problem.data.reshape(3, -1)
    assert torch.equal(sub.data, torch.cat([rows[2], rows[0]]))   # the same draw of noise
    assert sub.noise_level == pytest.approx(problem.noise_level * math.sqrt(2 / 3), rel=1e-12)
    assert sub.cfg.noise == problem.cfg.noise and sub.cfg.frames == [11, 0]
    assert sub.tet.key == problem.tet.key and sub.frame_numbers() == [11, 0]
    # the truth simulated again on the subset: frame 0 (the rest pose) as before
    assert torch.allclose(sub.x_true[1], problem.x_true[0], rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match=r"frames \[5\] are not fitted frames"):
        problem.with_frames([0, 5])


def test_frames_near_a_fold_and_the_two_stages(cache, tmp_path):
    problem = arm(cache, frames=[0, 3, 11], target="synthetic")
    threshold = between(problem)
    assert frames_near_fold(problem, problem.theta0, threshold) == [11]
    run = tmp_path / "run"
    result = fit_continued(problem, LM, run_dir=run, min_volume=threshold, first_max_iter=3)
    first = result.first_stage
    assert first is not None and first.iterations >= 1
    stage = json.loads((run / FIRST_STAGE_DIR / "result.json").read_text())
    assert stage["problem"]["n_frames"] == 2 and stage["status"] == "completed"
    assert stage["config"]["problem"]["frames"] == [0, 3]
    assert stage["config"]["continuation_stage"]["near_fold_left_for_stage_2"] == [11]
    final = json.loads((run / "result.json").read_text())
    assert final["config"]["continuation_first_stage"]["frames"] == [0, 3]
    # the second stage starts where the first ended: its checkpoint records that start
    saved = torch.load(run / FIRST_STAGE_DIR / "params.pt", weights_only=True)["theta"]
    assert torch.equal(saved, first.theta)
    checkpoint = torch.load(run / "checkpoint.pt", weights_only=True)
    assert checkpoint["init"] == digest(first.theta)
    assert (run / "tb").is_dir() and (run / FIRST_STAGE_DIR / "tb").is_dir()
    # killed in the second stage before its first checkpoint: a resume reads the first
    # stage back (no new iteration there) and repeats the second exactly
    history = (run / FIRST_STAGE_DIR / "history.jsonl").read_bytes()
    for name in ("checkpoint.pt", "history.jsonl", "result.json", "params.pt"):
        (run / name).unlink()
    again = fit_continued(arm(cache, frames=[0, 3, 11], target="synthetic"), LM, run_dir=run,
                          min_volume=threshold, first_max_iter=3, resume=True)
    assert (run / FIRST_STAGE_DIR / "history.jsonl").read_bytes() == history
    assert again.first_stage.iterations == first.iterations
    # the same iterates (to round-off: 1.5e-13 measured, PARDISO's threads and the start)
    assert torch.allclose(again.theta, result.theta, rtol=0, atol=1e-9)
    assert again.iterations == result.iterations


def test_no_frame_near_a_fold_is_one_run(cache, tmp_path):
    problem = arm(cache, frames=[0, 3])
    result = fit_continued(problem, LM, run_dir=tmp_path / "run", min_volume=0.1)
    assert result.first_stage is None and not (tmp_path / "run" / FIRST_STAGE_DIR).exists()
    assert (tmp_path / "run" / "result.json").is_file()


def test_bad_input_is_refused_before_anything_is_written(cache, tmp_path):
    spring = build_problem("spring1d", {"n": 8})
    with pytest.raises(FitConfigError, match="continuation=true needs a body fitted to an "
                                             "animation.*spring1d"):
        fit_continued(spring, "gauss_newton", run_dir=tmp_path / "a")
    problem = arm(cache, frames=[0, 3])
    for bad in (0.0, 1.0, float("nan"), True):
        with pytest.raises(FitConfigError, match="continuation_min_volume=.* must lie in"):
            fit_continued(problem, LM, run_dir=tmp_path / "b", min_volume=bad)
    for bad in (-1, 2.5, True):
        with pytest.raises(FitConfigError, match="continuation_first_max_iter=.* must be an "):
            fit_continued(problem, LM, run_dir=tmp_path / "b", first_max_iter=bad)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    fit(problem, {**LM, "max_iter": 1}, run_dir=tmp_path / "c")
    with pytest.raises(FitConfigError, match="already holds a run"):
        fit_continued(problem, LM, run_dir=tmp_path / "c")


@pytest.mark.slow
def test_continuation_recovers_the_field_where_one_run_stalls(tmp_path):
    """The short arm (frames 0, 3, 6, 9, 11; frames 9 and 11 fold) on the 0.06 mesh kept in
    tests/data/arm_saddle, noise-free blocks: one LM run from the homogeneous material stalls
    with the folded frames on other equilibria than the target's; the continuation reaches
    the truth."""
    shutil.copytree(DATA / "arm_saddle", tmp_path / "cache", dirs_exist_ok=True)
    settings = {"cache_dir": str(tmp_path / "cache"), "tet_edge_length": 0.06,
                "frames": [0, 3, 6, 9, 11], "target": "synthetic"}
    problem = build_problem("arm3d", settings)
    assert problem.tet.from_cache
    solver = {"name": "levenberg_marquardt", "max_iter": 12, "max_step": 1.0}
    one_run = fit(problem, solver)
    continued = fit_continued(build_problem("arm3d", settings), solver)
    assert continued.first_stage is not None
    errors = (one_run.metrics["k_err_rel_aligned"], continued.metrics["k_err_rel_aligned"])
    assert errors[0] > 0.1 and errors[1] < 0.01, errors


def capsule(tmp_path, **settings):
    """The capsule (0, 15 and 30 degrees) on its mesh kept in tests/data/capsule_mesh."""
    if not (tmp_path / "cache").exists():
        shutil.copytree(DATA / "capsule_mesh", tmp_path / "cache")
    folder = tmp_path / "capsule"
    if not folder.exists():
        write_capsule(folder, "skeleton", "npz")
    problem = build_problem("animation", {"path": str(folder), "cache_dir": str(tmp_path / "cache"),
                                          "tet_edge_length": 0.12, "grid": [2, 2, 3],
                                          "newton_rtol": 1e-9, **settings})
    assert problem.tet.from_cache, "the capsule's mesh options changed: see tests/problems/" \
        "test_rigged_body.py (tests/data/capsule_mesh)"
    return problem


def test_the_continuation_setting_is_true_false_or_auto():
    assert [continuation_setting(v) for v in (True, False, "auto", "true", "False")] == \
        [True, False, "auto", True, False]
    for bad in ("maybe", 1, None, [True]):
        with pytest.raises(FitConfigError, match="continuation=.* must be true .*, false .* or "
                                               "auto"):
            continuation_setting(bad)


def test_auto_considers_only_bodies_fitted_to_their_own_simulations(tmp_path):
    """A rig target (not the model's equilibria) is one plain run without a fold check; a
    problem with a truth but no frames (spring1d) too; a synthetic body is considered."""
    spring = build_problem("spring1d", {"n": 8})
    assert spring.field_true is not None and not continuation_applies(spring)
    assert not continuation_applies(capsule(tmp_path))                   # target=rig
    assert continuation_applies(capsule(tmp_path, target="synthetic"))


def test_auto_splits_a_synthetic_body_only_where_a_frame_is_near_a_fold(tmp_path):
    """The capsule's 30-degree frame compresses its inner side most: a threshold above its
    smallest volume ratio puts it in the second stage (the first stage gets
    FIRST_STAGE_ITER_FACTOR x max_iter iterations), one below every ratio is one run."""
    problem = capsule(tmp_path, target="synthetic")
    with torch.no_grad(), problem.warm_starts.independent():
        ratios = problem.report.min_volume_ratio(problem.simulate(problem.field(problem.theta0)))
    assert problem.frame_numbers() == [0, 1, 2] and ratios[2] < ratios[1] < 1, ratios
    folding = float(0.5 * (ratios[1] + ratios[2]))
    one_iteration = {**LM, "max_iter": 1}
    split = fit_continued(problem, one_iteration, run_dir=tmp_path / "split", min_volume=folding)
    assert split.first_stage is not None and split.iterations <= 1
    assert 1 <= split.first_stage.iterations <= FIRST_STAGE_ITER_FACTOR
    stage = json.loads((tmp_path / "split" / FIRST_STAGE_DIR / "result.json").read_text())
    assert stage["config"]["problem"]["frames"] == [0, 1]
    assert stage["config"]["solver"]["max_iter"] == FIRST_STAGE_ITER_FACTOR
    below_all = 0.5 * float(ratios.min())
    whole = fit_continued(capsule(tmp_path, target="synthetic"), one_iteration,
                          run_dir=tmp_path / "whole", min_volume=below_all)
    assert whole.first_stage is None and not (tmp_path / "whole" / FIRST_STAGE_DIR).exists()
