"""The Hydra app ``experiments/fit.py``, run as a user runs it (a subprocess from the repo root)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.util import tensor_util
from conftest import run_fit_app

REPO = Path(__file__).resolve().parents[2]


def fit(run_dir: Path, *overrides: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return run_fit_app(run_dir, *overrides, timeout=timeout)


def ok(proc: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    assert proc.returncode == 0, f"stdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    return proc


def tb_series(logdir: Path, tag: str) -> list[tuple[int, float]]:
    acc = EventAccumulator(str(logdir), size_guidance={"tensors": 0, "scalars": 0})
    acc.Reload()
    if tag in acc.Tags()["tensors"]:
        return [(e.step, float(tensor_util.make_ndarray(e.tensor_proto))) for e in acc.Tensors(tag)]
    return [(e.step, float(e.value)) for e in acc.Scalars(tag)]


@pytest.fixture(scope="module")
def noisy_gn(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("fit") / "gn"
    proc = ok(fit(run_dir, "problem=spring1d", "problem.data=dense", "problem.noise=1e-4",
                  "solver=gauss_newton"))
    return run_dir, proc, json.loads((run_dir / "result.json").read_text())


def test_noisy_gauss_newton_result(noisy_gn):
    run_dir, proc, result = noisy_gn
    assert result["stop_reason"] == "discrepancy"
    assert result["converged"] is True
    assert result["k_err_rel"] <= 0.05
    assert result["factorizations"] > 0 and result["solves"] > 0
    for key in ("misfit", "u_err_inf", "u_err_2", "k_err_inf", "k_err_2", "k_err_rel",
                "iterations", "wall_s", "problem", "config", "history"):
        assert key in result, key
    assert result["config"]["problem"]["noise"] == 1e-4
    assert result["config"]["solver"]["name"] == "gauss_newton"
    assert len(result["history"]) == result["iterations"] + 1
    for name in ("params.pt", "field.npy", "checkpoint.pt", "field.png", "error_curves.png"):
        assert (run_dir / name).is_file(), name
    assert "field.png, error_curves.png" in proc.stdout
    lines = proc.stdout.splitlines()
    assert f"tensorboard --logdir {(run_dir / 'tb').resolve()}" in lines
    assert "Traceback" not in proc.stderr


def test_noisy_gauss_newton_tensorboard(noisy_gn):
    run_dir, _, result = noisy_gn
    steps = list(range(result["iterations"] + 1))
    misfit = tb_series(run_dir / "tb", "fit/misfit")
    k_err = tb_series(run_dir / "tb", "metrics/k_err_rel")
    assert [s for s, _ in misfit] == steps
    assert [s for s, _ in k_err] == steps
    assert misfit[-1][1] == pytest.approx(result["misfit"], rel=1e-12)
    assert k_err[-1][1] == pytest.approx(result["k_err_rel"], rel=1e-12)
    assert misfit[-1][1] < misfit[0][1]
    for tag in ("fit/objective", "solver/cg_iterations", "solver/step_norm", "solver/solves",
                "solver/factorizations", "solver/wall_time", "metrics/u_err_inf"):
        assert [s for s, _ in tb_series(run_dir / "tb", tag)] == steps, tag


def test_levenberg_marquardt_noise_free(tmp_path):
    ok(fit(tmp_path / "lm", "solver=levenberg_marquardt", "problem.noise=0", "progress=false"))
    result = json.loads((tmp_path / "lm" / "result.json").read_text())
    assert result["converged"] is True
    assert result["k_err_rel"] <= 1e-7
    assert result["config"]["solver"]["name"] == "levenberg_marquardt"


@pytest.mark.parametrize("override,expect", [
    ("problem.noise=-1", ["problem.noise"]),
    ("problem.n=0", ["problem.n"]),
    ("problem.fixed_nodes=[]", ["problem.fixed_nodes", "singular", "Dirichlet"]),
    ("solver.tau=0.5", ["solver.tau"]),
    ("objective_metric=k_err", ["objective_metric", "k_err_rel"]),
])
def test_invalid_setting_is_one_clear_line(tmp_path, override, expect):
    run_dir = tmp_path / "run"
    proc = fit(run_dir, override)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1, proc.stderr
    for word in expect:
        assert word in errors[0]
    assert not run_dir.exists()      # only Hydra's own files were there: removed


def test_unknown_problem_lists_choices(tmp_path):
    run_dir = tmp_path / "run"
    proc = fit(run_dir, "problem=nope")
    assert proc.returncode == 2
    assert "spring1d" in proc.stderr + proc.stdout
    assert "Traceback" not in proc.stderr
    assert not run_dir.exists()


@pytest.mark.parametrize("override,expect", [
    ("problem.nosie=0.1", "nosie"),          # misspelt: the schema rejects it
    ("problem.n=abc", "problem.n"),          # mistyped
])
def test_override_hydra_rejects_exits_2(tmp_path, override, expect):
    run_dir = tmp_path / "run"
    proc = fit(run_dir, override)
    assert proc.returncode == 2
    assert expect in proc.stderr and "Traceback" not in proc.stderr
    assert not run_dir.exists()


def test_resume_continues_from_checkpoint(tmp_path):
    run_dir = tmp_path / "run"
    ok(fit(run_dir, "problem.noise=1e-4", "solver.max_iter=2", "progress=false"))
    first = json.loads((run_dir / "result.json").read_text())
    assert first["stop_reason"] == "max_iter" and first["iterations"] == 2

    ok(fit(run_dir, "problem.noise=1e-4", "resume=true", "progress=false"))
    second = json.loads((run_dir / "result.json").read_text())
    assert second["resumed_from_iteration"] == 2
    assert second["history"][0]["iteration"] == 2
    assert second["history"][0]["misfit"] == pytest.approx(first["misfit"], rel=1e-12)
    assert second["stop_reason"] == "discrepancy"
    # TensorBoard steps continue where the first run stopped
    steps = sorted({s for s, _ in tb_series(run_dir / "tb", "fit/misfit")})
    assert steps == list(range(2 + second["iterations"] + 1))


def test_resume_rejects_checkpoint_of_another_size(tmp_path):
    run_dir = tmp_path / "run"
    ok(fit(run_dir, "problem.n=8", "solver.max_iter=1", "progress=false"))
    (run_dir / "result.json").unlink()
    proc = fit(run_dir, "resume=true")
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert "checkpoint" in proc.stderr and "parameters" in proc.stderr
    assert not (run_dir / "result.json").exists()


def test_resume_warns_about_changed_problem_settings(tmp_path):
    run_dir = tmp_path / "run"
    ok(fit(run_dir, "problem.noise=1e-4", "solver.max_iter=1", "progress=false"))
    proc = ok(fit(run_dir, "problem.noise=2e-4", "resume=true", "progress=false"))
    assert "different problem settings ['noise']" in proc.stdout + proc.stderr


def test_multirun_invalid_job_does_not_stop_the_sweep(tmp_path):
    sweep = tmp_path / "sweep"
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    proc = subprocess.run([sys.executable, "experiments/fit.py", "-m", f"hydra.sweep.dir={sweep}",
                           "solver.tau=0.5,1.5", "problem.n=16", "problem.noise=1e-4",
                           "progress=false"], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=120)
    ok(proc)
    assert "error: solver.tau must be > 1" in proc.stderr and "Traceback" not in proc.stderr
    jobs = sorted(p.name for p in sweep.iterdir() if p.is_dir())
    assert jobs == ["1_problem.n=16,problem.noise=0.0001,progress=False,solver.tau=1.5"]
    assert (sweep / jobs[0] / "result.json").is_file()


@pytest.mark.slow
def test_joblib_multirun(tmp_path):
    sweep = tmp_path / "sweep"
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    proc = subprocess.run([sys.executable, "experiments/fit.py", "-m", "hydra/launcher=joblib",
                           "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={sweep}",
                           "solver=gauss_newton,levenberg_marquardt", "problem.noise=1e-4",
                           "progress=false"], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=300)
    ok(proc)
    results = sorted(sweep.glob("*/result.json"))
    assert len(results) == 2
    for path in results:
        result = json.loads(path.read_text())
        assert result["stop_reason"] == "discrepancy" and result["k_err_rel"] <= 0.05
        assert (path.parent / "tb").is_dir()
