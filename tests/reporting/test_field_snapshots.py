"""FieldSnapshots: the 2-D field (and its error) as TensorBoard images, read back from the
event files, and the seed's snapshot figure."""
from __future__ import annotations

import io
import logging

import numpy as np
import pytest
from PIL import Image
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from torchfit.reporting.field_snapshots import FieldSnapshots
from torchfit.reporting.figures import colorize, field_images, supports_field_images, upscale
from torchfit.reporting.guard import PlotGuard
from torchfit.reporting.tensorboard import TensorBoardLogger
from torchfit.problems import build_problem
from torchfit.run.evaluator import Evaluator
from torchfit.solvers import (GaussNewtonConfig, LevenbergMarquardtConfig, gauss_newton,
                              levenberg_marquardt)


def test_snapshots_images_scalars_and_files(tmp_path):
    problem = build_problem("membrane2d", {"nx": 16, "ny": 4})
    assert supports_field_images(problem)
    tb = TensorBoardLogger(tmp_path / "tb")
    snaps = FieldSnapshots(problem, tb, tmp_path, snapshot_iterations=[1, 3], every=0,
                           sheet_frame=-1)
    assert snaps.sheet_frame == 7
    run = Evaluator(problem)
    result = levenberg_marquardt(problem.residual(), problem.theta0,
                                 LevenbergMarquardtConfig(max_iter=4), [run, tb, run.feed(snaps)])
    written = {p.name for p in snaps.finish(run.final(result.theta))}
    tb.close()
    assert written == {"snapshots.png", "frame_errors.png", "sheet_frame7.png"}
    assert sorted(snaps.snapshots) == [1, 3]
    image, errors = snaps.snapshots[1]
    assert image.shape == (4 * 4, 16 * 4) and errors.shape == (8,)
    acc = EventAccumulator(str(tmp_path / "tb"), size_guidance={"images": 0, "tensors": 0})
    acc.Reload()
    # iteration 0, the snapshots and the last iteration (written by finish)
    assert [e.step for e in acc.Images("field/E_image")] == [0, 1, 3, 4]
    # scale-free: the error image says it is aligned; no unaligned one
    assert [e.step for e in acc.Images("field/E_error_aligned_image")] == [0, 1, 3, 4]
    assert "field/E_error_image" not in acc.Tags()["images"]
    # a 64 x 16 pixel field image, upscaled 4x so that its long side has 256 pixels
    for tag in ("field/E_image", "field/E_error_aligned_image", "field/E_true_image"):
        assert {(e.width, e.height) for e in acc.Images(tag)} == {(256, 64)}, tag
    assert [e.step for e in acc.Images("field/E_true_image")] == [0]
    assert [e.step for e in acc.Images("field/E_panels")] == [4]
    assert [e.step for e in acc.Images("sheet/frame_7")] == [0, 1, 3]
    assert len(acc.Tensors("frames/u_err_inf/frame_7")) == 5


def test_chain_problems_have_no_field_images(tmp_path):
    problem = build_problem("spring1d", {"n": 8})
    assert not supports_field_images(problem)
    with pytest.raises(ValueError, match="image"):
        FieldSnapshots(problem, TensorBoardLogger(tmp_path), tmp_path)


def test_bad_settings(tmp_path):
    problem = build_problem("membrane2d", {"nx": 4, "ny": 2})
    tb = TensorBoardLogger(tmp_path)
    with pytest.raises(ValueError, match="sheet_frame"):
        FieldSnapshots(problem, tb, tmp_path, sheet_frame=8)
    with pytest.raises(ValueError, match="interval"):
        FieldSnapshots(problem, tb, tmp_path, every=-1)
    rgb = colorize([[0.0, 1.0]], 0.0, 1.0)
    assert rgb.shape == (1, 2, 3) and rgb.dtype.name == "uint8"


def read_images(logdir) -> EventAccumulator:
    acc = EventAccumulator(str(logdir), size_guidance={"images": 0, "tensors": 0})
    acc.Reload()
    return acc


def test_poisson2d_field_and_aligned_error_images(tmp_path):
    problem = build_problem("poisson2d", {"N": 9})        # 8 x 8 cells
    tb = TensorBoardLogger(tmp_path / "tb")
    snaps = FieldSnapshots(problem, tb, None, snapshot_iterations=[1], every=2)
    run = Evaluator(problem)
    result = gauss_newton(problem.residual(), problem.theta0, GaussNewtonConfig(max_iter=5),
                          [run, tb, run.feed(snaps)])
    assert snaps.finish(run.final(result.theta)) == []    # no run directory, no files
    tb.close()
    last = result.iterations
    assert last >= 3
    expected = sorted({0, 1, last} | set(range(0, last + 1, 2)))
    acc = read_images(tmp_path / "tb")
    assert [e.step for e in acc.Images("field/k_image")] == expected
    assert [e.step for e in acc.Images("field/k_error_aligned_image")] == expected
    assert [e.step for e in acc.Images("field/k_true_image")] == [0]
    assert [e.step for e in acc.Images("field/k_panels")] == [last]
    # 8 pixels upscaled 16x (the largest factor) -> 128 x 128, as decoded PNG too
    for e in acc.Images("field/k_image") + acc.Images("field/k_error_aligned_image"):
        assert (e.width, e.height) == (128, 128)
        with Image.open(io.BytesIO(e.encoded_image_string)) as png:
            assert png.size == (128, 128) and png.mode == "RGB"
    panels = acc.Images("field/k_panels")[0]
    assert panels.width >= 600 and panels.height >= 200
    # the error image shrinks as the fit converges: the colour of its pixels changes
    # (symmetric range per image), but the field image converges onto the truth's
    truth_png = np.asarray(Image.open(io.BytesIO(acc.Images("field/k_true_image")[0].encoded_image_string)))
    first, final = (np.asarray(Image.open(io.BytesIO(e.encoded_image_string))).astype(int)
                    for e in (acc.Images("field/k_image")[0], acc.Images("field/k_image")[-1]))
    assert np.abs(final - truth_png).mean() < np.abs(first - truth_png).mean()


def test_field_images_align_a_scaled_truth_and_keep_the_orientation():
    problem = build_problem("poisson2d", {"N": 5})        # 4 x 4 cells, cell ci * 4 + cj
    truth = problem.field_true
    images = field_images(problem, 3.0 * truth)
    assert images.aligned and images.scale == pytest.approx(1.0 / 3.0, rel=1e-14)
    np.testing.assert_allclose(images.fitted, images.truth, rtol=1e-14)
    np.testing.assert_allclose(images.error, 0.0, atol=1e-13)
    bump = truth.clone()
    bump[1 * 4 + 3] += 1.0          # cell (x index 1, y index 3): top row, second column
    error = field_images(problem, bump).error
    row, col = np.unravel_index(np.argmax(np.abs(error)), error.shape)
    assert (row, col) == (0, 1)
    assert upscale(np.zeros((4, 2)), 256).shape == (64, 32)          # capped at 16x
    assert upscale(np.zeros((100, 40, 3)), 256).shape == (300, 120, 3)
    assert upscale(np.zeros((300, 40)), 256).shape == (300, 40)


def test_a_failing_drawing_warns_once_and_the_fit_goes_on(tmp_path, caplog, monkeypatch):
    problem = build_problem("poisson2d", {"N": 6})

    def broken(field):
        raise RuntimeError("no ink")

    monkeypatch.setattr(problem, "field_image", broken)
    tb = TensorBoardLogger(tmp_path / "tb")
    guard = PlotGuard()
    snaps = FieldSnapshots(problem, tb, tmp_path, snapshot_iterations=[1], every=1, guard=guard)
    with caplog.at_level(logging.WARNING, logger="torchfit.reporting.guard"):
        run = Evaluator(problem)
        result = gauss_newton(problem.residual(), problem.theta0, GaussNewtonConfig(max_iter=3),
                              [run, tb, run.feed(snaps)])
        written = snaps.finish(run.final(result.theta))
    tb.close()
    assert result.iterations == 3 and written == []
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "no ink" in warnings[0].getMessage()
    assert "not affected" in warnings[0].getMessage()
    assert len(guard.failures) > 1
    assert "field/k_image" not in read_images(tmp_path / "tb").Tags()["images"]
