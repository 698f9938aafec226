"""FieldSnapshots: the 2-D field as TensorBoard images and the seed's snapshot figure."""
from __future__ import annotations

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from torchfit.logging import FieldSnapshots, MetricsCallback, TensorBoardLogger, supports_field_images
from torchfit.logging.plots import colorize
from torchfit.problems import build_problem
from torchfit.solvers import LevenbergMarquardtConfig, levenberg_marquardt


def test_snapshots_images_scalars_and_files(tmp_path):
    problem = build_problem("membrane2d", {"nx": 16, "ny": 4})
    assert supports_field_images(problem)
    tb = TensorBoardLogger(tmp_path / "tb")
    snaps = FieldSnapshots(problem, tb, tmp_path, snapshot_iterations=[1, 3], every=0,
                           sheet_frame=-1)
    assert snaps.sheet_frame == 7
    levenberg_marquardt(problem.residual(), problem.theta0, LevenbergMarquardtConfig(max_iter=4),
                        [MetricsCallback(problem), tb, snaps])
    written = {p.name for p in snaps.finish()}
    tb.close()
    assert written == {"snapshots.png", "frame_errors.png", "sheet_frame7.png"}
    assert sorted(snaps.snapshots) == [1, 3]
    image, errors = snaps.snapshots[1]
    assert image.shape == (4 * 4, 16 * 4) and errors.shape == (8,)
    acc = EventAccumulator(str(tmp_path / "tb"), size_guidance={"images": 0, "tensors": 0})
    acc.Reload()
    assert [e.step for e in acc.Images("field/E_image")] == [0, 1, 3, 4]
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
