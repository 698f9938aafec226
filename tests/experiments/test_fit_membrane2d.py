"""``experiments/fit.py problem=membrane2d`` run as a user runs it, and its picture outputs."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from conftest import run_fit_app

REPO = Path(__file__).resolve().parents[2]


def fit(run_dir: Path, *overrides: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return run_fit_app(run_dir, *overrides, timeout=timeout)


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("membrane") / "lm"
    proc = fit(run_dir, "problem=membrane2d", "problem.nx=16", "problem.ny=4",
               "solver.max_iter=3", "solver=levenberg_marquardt", "snapshot_iterations=[1,2]",
               "snapshot_every=2", "progress=false")
    assert proc.returncode == 0, f"stdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    return run_dir, proc


def test_smoke_result_and_files(small_run):
    run_dir, proc = small_run
    result = json.loads((run_dir / "result.json").read_text())
    assert result["iterations"] == 3 and result["stop_reason"] == "max_iter"
    for key in ("misfit", "u_err_inf", "u_err_2", "k_err_inf", "k_err_2", "k_err_rel",
                "k_err_rel_aligned"):
        assert key in result, key
    assert result["config"]["problem"]["model"] == "corotated"
    assert result["problem"]["n_params"] == 128 and result["problem"]["scale_free"] is True
    assert result["history"][-1]["misfit"] < result["history"][0]["misfit"]
    for name in ("snapshots.png", "frame_errors.png", "sheet_frame5.png", "frames.npz",
                 "params.pt", "field.npy", "checkpoint.pt", "field.png", "error_curves.png"):
        assert (run_dir / name).is_file(), name
    frames = np.load(run_dir / "frames.npz")
    assert frames["positions"].shape == (8, 85, 2) == frames["true_positions"].shape
    assert frames["cells"].shape == (128, 3)
    assert "snapshots.png" in proc.stdout and "Traceback" not in proc.stderr


def test_smoke_tensorboard_images_and_frame_errors(small_run):
    run_dir, _ = small_run
    acc = EventAccumulator(str(run_dir / "tb"), size_guidance={"images": 0, "tensors": 0})
    acc.Reload()
    tags = acc.Tags()
    assert {"field/E_image", "field/E_true_image", "sheet/frame_5"} <= set(tags["images"])
    # iteration 0, the snapshot iterations 1 and 2 and every 2nd
    # and the last one
    assert [e.step for e in acc.Images("field/E_image")] == [0, 1, 2, 3]
    assert [e.step for e in acc.Images("field/E_error_aligned_image")] == [0, 1, 2, 3]
    assert [e.step for e in acc.Images("field/E_panels")] == [3]
    for f in range(8):
        assert f"frames/u_err_inf/frame_{f}" in tags["tensors"]
        assert [e.step for e in acc.Tensors(f"frames/u_err_2/frame_{f}")] == [0, 1, 2, 3]
    assert "metrics/k_err_rel_aligned" in tags["tensors"]


def test_membrane_default_solver_is_levenberg_marquardt(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    out = subprocess.run([sys.executable, "experiments/fit.py", "problem=membrane2d", "--cfg",
                          "job"], cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "name: levenberg_marquardt" in out.stdout
    out = subprocess.run([sys.executable, "experiments/fit.py", "problem=membrane2d",
                          "solver=gauss_newton", "--cfg", "job"], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "name: gauss_newton" in out.stdout
    out = subprocess.run([sys.executable, "experiments/fit.py", "--cfg", "job"], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=120)
    assert "name: gauss_newton" in out.stdout and "name: spring1d" in out.stdout


@pytest.mark.parametrize("override,expect", [
    ("problem.nu=0.5", "problem.nu"),
    ("problem.model=mooney", "problem.model"),
    ("sheet_frame=9", "sheet_frame"),
    ("snapshot_every=-1", "snapshot_every"),
])
def test_invalid_membrane_setting_is_one_clear_line(tmp_path, override, expect):
    run_dir = tmp_path / "run"
    proc = fit(run_dir, "problem=membrane2d", "problem.nx=4", "problem.ny=2", override)
    assert proc.returncode == 2, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and expect in errors[0], proc.stderr
    assert "Traceback" not in proc.stderr
    assert not run_dir.exists()


def test_verify_app_on_membrane2d(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    proc = subprocess.run([sys.executable, "experiments/verify.py", "problem=membrane2d",
                           "problem.nx=8", "problem.ny=4", f"hydra.run.dir={tmp_path / 'v'}"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    report = json.loads((tmp_path / "v" / "verify.json").read_text())
    assert report["passed"] and abs(report["taylor_rate"] - 2.0) <= 0.05
    assert report["config"]["threads"] == 1            # the membrane2d run default
