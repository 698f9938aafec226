"""Result files, checkpoints, and the metrics callback (which must cost no factorisation)."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch

from torchfit.linalg import counting
from torchfit.logging import (CheckpointWriter, MetricsCallback, load_checkpoint, save_checkpoint,
                              save_params, write_result)
from torchfit.problems import build_problem
from torchfit.solvers import (IterationRecord, LevenbergMarquardtConfig, gauss_newton,
                              levenberg_marquardt)

PROBLEM_METRICS = ("misfit", "u_err_inf", "u_err_2", "k_err_inf", "k_err_2", "k_err_rel")


class CountedMetrics(MetricsCallback):
    """The metrics callback, counting what each of its calls costs."""

    def __init__(self, problem):
        super().__init__(problem)
        self.costs: list[tuple[int, int]] = []

    def __call__(self, record):
        with counting() as c:
            super().__call__(record)
        self.costs.append((c.factorizations, c.solves))


@pytest.mark.parametrize("solver,config", [
    (gauss_newton, None),
    # a large initial damping and a slow decrease force rejected steps
    (levenberg_marquardt, LevenbergMarquardtConfig(damping_init=1e-4, decrease=0.1)),
])
def test_metrics_callback_costs_no_factorisation(solver, config):
    problem = build_problem("spring1d", {"noise": 1e-4})
    plain = solver(problem.residual(), problem.theta0, config)
    metrics = CountedMetrics(problem)
    seen: list[dict] = []
    with_metrics = solver(problem.residual(), problem.theta0, config,
                          [metrics, lambda rec: seen.append(dict(rec.extra))])
    assert metrics.costs and all(cost == (0, 0) for cost in metrics.costs)
    # the solver's own cost and path are unchanged
    assert with_metrics.factorizations == plain.factorizations
    assert with_metrics.solves == plain.solves
    assert with_metrics.iterations == plain.iterations
    assert torch.equal(with_metrics.theta, plain.theta)
    # later callbacks see the metrics, and the misfit agrees with the solver's
    for rec, extra in zip(with_metrics.history, seen):
        assert set(PROBLEM_METRICS) <= set(extra)
        assert extra["misfit"] == pytest.approx(rec.misfit, rel=1e-12)


def fake_result(tmp_path):
    problem = build_problem("spring1d", {"n": 8, "noise": 1e-4})
    result = levenberg_marquardt(problem.residual(), problem.theta0,
                                 callbacks=[MetricsCallback(problem)])
    return problem, result


def test_write_result_is_strict_json_with_every_key(tmp_path):
    problem, result = fake_result(tmp_path)
    metrics = problem.metrics(result.theta)
    path = write_result(tmp_path, result, metrics, problem.describe(), {"solver": {"tau": 1.5}})
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text
    data = json.loads(text)
    for key in PROBLEM_METRICS + ("iterations", "wall_s", "factorizations", "solves",
                                  "converged", "stop_reason", "problem", "config", "history"):
        assert key in data, key
    assert data["misfit"] == metrics["misfit"]
    assert data["problem"]["name"] == "spring1d"
    assert data["config"] == {"solver": {"tau": 1.5}}
    assert [row["iteration"] for row in data["history"]] == list(range(result.iterations + 1))
    assert all("k_err_rel" in row for row in data["history"])
    assert [p.name for p in tmp_path.iterdir()] == ["result.json"]   # no temporary left


def test_nan_becomes_null(tmp_path):
    problem, result = fake_result(tmp_path)
    result.history[0].extra["odd"] = float("nan")
    data = json.loads(write_result(tmp_path, result, {"misfit": 1.0}).read_text())
    assert data["history"][0]["odd"] is None


def test_save_params(tmp_path):
    theta = torch.linspace(0, 1, 5)
    params_path, field_path = save_params(tmp_path, theta, theta.exp(), "k")
    saved = torch.load(params_path, weights_only=True)
    assert torch.equal(saved["theta"], theta) and torch.equal(saved["field"], theta.exp())
    assert np.array_equal(np.load(field_path), theta.exp().numpy())


def test_checkpoint_round_trip_and_atomic_rewrite(tmp_path):
    path = tmp_path / "checkpoint.pt"
    writer = CheckpointWriter(path, step_offset=3, problem="spring1d",
                              problem_config={"noise": 1e-4, "loads": [0.0, 1.0], "targets": None})
    for i in range(3):
        writer(IterationRecord(i, torch.full((4,), float(i)), 0.5, 1.0 / (i + 1)))
    ckpt = load_checkpoint(path, n_params=4, problem="spring1d")
    assert ckpt.iteration == 5 and torch.equal(ckpt.theta, torch.full((4,), 2.0))
    assert ckpt.misfit == pytest.approx(1 / 3)
    assert ckpt.problem_config == {"noise": 1e-4, "loads": [0.0, 1.0], "targets": None}
    assert sorted(os.listdir(tmp_path)) == ["checkpoint.pt"]


def test_load_checkpoint_rejects_what_does_not_fit(tmp_path):
    path = save_checkpoint(tmp_path / "checkpoint.pt", 2, torch.zeros(8), 1.0, "spring1d")
    with pytest.raises(ValueError, match="8 parameters but the problem has 64"):
        load_checkpoint(path, n_params=64)
    with pytest.raises(ValueError, match="belongs to problem 'spring1d'"):
        load_checkpoint(path, problem="poisson2d")
    (tmp_path / "broken.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="cannot read checkpoint"):
        load_checkpoint(tmp_path / "broken.pt")


SAVE_OUTPUTS = """
import sys
import torch
from torchfit.logging import save_checkpoint, save_params
run_dir = sys.argv[1]
theta = torch.linspace(-1.0, 2.0, 7, dtype=torch.float64)
save_params(run_dir, theta, torch.exp(theta), "k")
save_checkpoint(run_dir + "/checkpoint.pt", 3, theta, 0.125, "spring1d", {"n": 7, "noise": 1e-4})
"""


def test_outputs_are_byte_identical_across_directories_and_processes(tmp_path):
    """The same content gives the same bytes of params.pt, checkpoint.pt and field.npy,
    whatever the directory's name and the process (the temporary file's name used to end
    up inside torch's zip archive)."""
    import subprocess
    import sys

    repo = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = {**os.environ, "PYTHONPATH": repo + os.pathsep + os.environ.get("PYTHONPATH", "")}
    dirs = [tmp_path / "first", tmp_path / "second_run_with_a_longer_name"]
    for d in dirs:
        proc = subprocess.run([sys.executable, "-c", SAVE_OUTPUTS, str(d)], env=env,
                              capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr
    # and once more in this process
    theta = torch.linspace(-1.0, 2.0, 7, dtype=torch.float64)
    dirs.append(tmp_path / "in_process")
    save_params(dirs[-1], theta, torch.exp(theta), "k")
    save_checkpoint(dirs[-1] / "checkpoint.pt", 3, theta, 0.125, "spring1d",
                    {"n": 7, "noise": 1e-4})
    for name in ("params.pt", "checkpoint.pt", "field.npy"):
        contents = [(d / name).read_bytes() for d in dirs]
        assert contents[0] == contents[1] == contents[2], name
        assert b".tmp" not in contents[0], name
    assert sorted(p.name for p in dirs[0].iterdir()) == ["checkpoint.pt", "field.npy",
                                                         "params.pt"]   # no temporary left
    loaded = load_checkpoint(dirs[0] / "checkpoint.pt", n_params=7, problem="spring1d")
    assert loaded.iteration == 3 and torch.equal(loaded.theta, theta)
    assert loaded.problem_config == {"n": 7, "noise": 1e-4}
