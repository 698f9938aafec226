"""What a user sees of a 2-D run: TensorBoard (a real server, default options), PNGs and the
frames of a mesh problem."""
from __future__ import annotations

import numpy as np
import pytest

from helpers.runs import scalar_steps
from torchfit.problems import build_problem
from torchfit.run import FitOptions, fit



def test_poisson2d_run_as_tensorboard_shows_it(tmp_path, tensorboard_server):
    problem = build_problem("poisson2d", {"N": 8, "noise": 1e-3})
    result = fit(problem, {"name": "split_bregman", "max_iter": 5}, run_dir=tmp_path,
                 options=FitOptions(progress=False, snapshot_iterations=[1], snapshot_every=2))
    assert result.iterations == 5
    server = tensorboard_server(tmp_path)
    run = server.wait_until(lambda: next(iter(server.runs()), None), what="the run")
    assert run == "tb"
    history = result.history
    per_iteration = {"fit/misfit": "misfit", "fit/tv": "tv", "metrics/k_err_rel_aligned":
                     "k_err_rel_aligned", "metrics/u_err_2": "u_err_2", "solver/mu": "mu"}
    server.wait_until(lambda: all(len(server.scalars(run, tag)) == len(history)
                                  for tag in per_iteration)
                      if set(per_iteration) <= set(server.scalar_tags().get(run, {})) else False,
                      what="every per-iteration curve")
    for tag, key in per_iteration.items():
        shown = server.scalars(run, tag)
        assert [step for step, _ in shown] == list(range(6)), tag          # iterations + 1
        assert [value for _, value in shown] == pytest.approx(
            [row[key] for row in history], rel=1e-6), tag                  # float32 of them
    assert server.scalars(run, "final/iterations") == [(5, 5.0)]
    images = server.image_tags()[run]
    steps = {tag: [entry["step"] for entry in server.images(run, tag)] for tag in images}
    assert steps["field/k_image"] == steps["field/k_error_aligned_image"] == [0, 1, 2, 4, 5]
    assert steps["field/k_true_image"] == [0] and steps["field/k_panels"] == [5]
    for name in ("field.png", "error_curves.png", "snapshots.png"):
        assert (tmp_path / name).stat().st_size > 10_000, name


def test_membrane2d_run_recovers_the_letters_and_writes_its_frames(tmp_path):
    # The membrane preset (Levenberg-Marquardt, geodesic acceleration, Nielsen damping,
    # difference preconditioner) on a 16 x 4 sheet: 0.82 at the start, one Gauss-Newton step
    # 0.67, the preset below 1e-3 after 12 iterations (2.4e-4 after 11, measured).
    problem = build_problem("membrane2d", {"nx": 16, "ny": 4})
    preset = {"name": "levenberg_marquardt", "max_iter": 12, "geodesic_acceleration": True,
              "damping_update": "nielsen", "preconditioner": "difference"}
    result = fit(problem, preset, run_dir=tmp_path, options=FitOptions(
        progress=False, threads=1, snapshot_iterations=[1, 2], snapshot_every=0))
    assert result.history[0]["k_err_rel_aligned"] > 0.8
    assert result.metrics["k_err_rel_aligned"] <= 1e-3
    frames = np.load(tmp_path / "frames.npz")
    assert frames["positions"].shape == (8, 85, 2) == frames["true_positions"].shape
    assert frames["cells"].shape == (128, 3)
    assert np.abs(frames["positions"] - frames["true_positions"]).max() <= 1e-4
    for name in ("snapshots.png", "frame_errors.png", "sheet_frame5.png", "field.png"):
        assert (tmp_path / name).is_file(), name
    steps = scalar_steps(tmp_path / "tb", "frames/u_err_2/frame_7")
    assert steps == list(range(result.iterations + 1))
