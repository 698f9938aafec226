"""torchfit.run.fit: a whole run in-process (no Hydra), byte-identical outputs, and bad input
refused before anything is written."""
from __future__ import annotations

import json

import pytest
import torch

from helpers.runs import QUIET, load_params, scalar_steps
from torchfit.problems import build_problem
from torchfit.run import FitConfigError, FitOptions, RunDirectoryError, fit
from torchfit.solvers import SolverConfigError



def test_fit_in_process_writes_the_run_directory(tmp_path):
    problem = build_problem("spring1d", {"n": 16, "noise": 1e-4, "seed": 1})
    result = fit(problem, "gauss_newton", run_dir=tmp_path / "run", options=QUIET)
    run = tmp_path / "run"
    saved = json.loads((run / "result.json").read_text())
    assert saved["status"] == "completed" and saved["stop_reason"] == "discrepancy"
    assert saved["iterations"] == result.iterations and len(saved["history"]) == result.iterations + 1
    assert saved["misfit"] == pytest.approx(result.metrics["misfit"], rel=1e-15)
    assert result.metrics["misfit"] <= 1.5 * problem.noise_level
    assert set(problem.metric_names()) <= set(saved)
    for name in ("params.pt", "field.npy", "checkpoint.pt", "history.jsonl", "field.png",
                 "error_curves.png"):
        assert (run / name).is_file(), name
    assert torch.equal(load_params(run)["theta"], result.theta)
    assert scalar_steps(run / "tb", "fit/misfit") == list(range(result.iterations + 1))


def test_fit_without_run_dir_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = fit(build_problem("spring1d", {"n": 8}), "levenberg_marquardt", options=QUIET)
    assert list(tmp_path.iterdir()) == []
    assert len(result.history) == result.iterations + 1 and result.run_dir is None


def test_identical_runs_write_identical_bytes(tmp_path):
    for name in ("a", "b"):
        problem = build_problem("poisson2d", {"N": 9, "noise": 1e-3})
        fit(problem, {"name": "gauss_newton", "max_iter": 4}, run_dir=tmp_path / name,
            options=QUIET)
    for file in ("params.pt", "checkpoint.pt", "field.npy"):
        assert (tmp_path / "a" / file).read_bytes() == (tmp_path / "b" / file).read_bytes(), file


@pytest.mark.parametrize("call,error,match", [
    (lambda p, d: fit(p, {"name": "gauss_newton", "tau": float("inf")}, run_dir=d),
     SolverConfigError, "solver.tau"),
    (lambda p, d: fit(p, {"name": "split_bregman", "growth": float("inf")}, run_dir=d),
     SolverConfigError, "solver.growth"),
    (lambda p, d: fit(p, {"name": "levenberg_marquardt", "damping_init": float("inf")},
                      run_dir=d), SolverConfigError, "solver.damping_init"),
    (lambda p, d: fit(p, {"name": "gauss_newton", "tua": 2}, run_dir=d), ValueError, "solver.tua"),
    (lambda p, d: fit(p, "newton", run_dir=d), ValueError, "newton"),
    (lambda p, d: fit(p, "gauss_newton", run_dir=d, options=FitOptions(log_every=0)),
     ValueError, "log_every"),
    (lambda p, d: fit(p, "gauss_newton", run_dir=d,
                      options=FitOptions(objective_metric="k_err_rel_aligned")),
     ValueError, "objective_metric"),
    (lambda p, d: fit(p, "gauss_newton", run_dir=d, options=FitOptions(sheet_frame=7)),
     ValueError, "sheet_frame"),
    (lambda p, d: fit(p, "gauss_newton", run_dir=d / "file" / "run"),
     RunDirectoryError, "is a file"),
    (lambda p, d: fit(p, "gauss_newton", run_dir=d / "run", init=d / "missing"),
     FitConfigError, "init=.*missing: no such file"),
    (lambda p, d: fit(p, "gauss_newton", run_dir=d / "run", init=d / "file"),
     FitConfigError, "is not a torchfit params.pt"),
    (lambda p, d: fit(p, "gauss_newton", run_dir=d / "run", init=torch.zeros(9)),
     FitConfigError, r"init has \(9,\) parameters.*\(8,\)"),
    (lambda p, d: fit(p, "gauss_newton", run_dir=d / "run",
                      init=torch.tensor([0.0] * 7 + [float("nan")])),
     FitConfigError, "parameter 7 is nan"),
])
def test_bad_input_writes_nothing(tmp_path, call, error, match):
    (tmp_path / "file").write_text("not a directory")
    problem = build_problem("spring1d", {"n": 8, "noise": 1e-4})
    with pytest.raises(error, match=match) as info:
        call(problem, tmp_path)
    assert "\n" not in str(info.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_split_bregman_run_records_its_terms(tmp_path):
    # (its accuracy: tests/solvers/split_bregman/test_solver.py)
    problem = build_problem("spring1d", {"n": 16, "noise": 1e-4})
    result = fit(problem, {"name": "split_bregman", "max_iter": 12}, run_dir=tmp_path,
                 options=QUIET)
    last = result.history[-1]
    for key in ("tv", "split_residual", "inner_iterations", "mu", "beta", "stage"):
        assert key in last, key
    for tag in ("fit/tv", "fit/objective", "solver/split_residual", "solver/inner_iterations",
                "solver/mu", "solver/beta", "solver/stage", "metrics/k_err_rel"):
        assert scalar_steps(tmp_path / "tb", tag) == list(range(result.iterations + 1)), tag
