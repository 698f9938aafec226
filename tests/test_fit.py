"""torchfit.fit: a whole run in-process (no Hydra), byte-identical outputs, exact resume after
SIGKILL for every solver, and a refused resume that touches nothing."""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

from torchfit.fit import (FitConfigError, FitOptions, ResumeError, RunDirectoryError,
                          build_solver, fit, initial_theta, verify)
from torchfit.reporting.results import save_params
from torchfit.problems import build_problem
from torchfit.solvers import SolverConfigError

REPO = Path(__file__).resolve().parents[1]
QUIET = FitOptions(progress=False)

#: A small run of each solver on spring1d (n = 16): (problem settings, solver settings, kill at).
RUNS = {
    "gauss_newton": ({"n": 16, "noise": 1e-4, "seed": 1},
                     {"name": "gauss_newton"}, 2),
    "levenberg_marquardt": ({"n": 16}, {"name": "levenberg_marquardt", "max_iter": 12}, 5),
    "split_bregman": ({"n": 16, "noise": 1e-4, "seed": 1},
                      {"name": "split_bregman", "max_iter": 60}, 23),
}

SCRIPT = """
import json, os, signal, sys
from torchfit.fit import FitOptions, fit
from torchfit.problems import build_problem
run_dir, problem, solver, kill_at, resume = sys.argv[1:6]
def killer(record):
    if record.iteration == int(kill_at):
        os.kill(os.getpid(), signal.SIGKILL)   # no cleanup, no flush: as a crash or OOM kill
fit(build_problem("spring1d", json.loads(problem)), json.loads(solver), run_dir=run_dir,
    resume=resume == "1", callbacks=[killer], options=FitOptions(progress=False))
"""


def run_script(run_dir: Path, problem: dict, solver: dict, kill_at: int = -1,
               resume: bool = False) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-c", SCRIPT, str(run_dir), json.dumps(problem),
                           json.dumps(solver), str(kill_at), "1" if resume else "0"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=300)


def scalar_steps(logdir: Path, tag: str) -> list[int]:
    """Every step written for ``tag`` in every event file (not a sample)."""
    steps = []
    for path in sorted(logdir.glob("events.out.tfevents.*")):
        for event in EventFileLoader(str(path)).Load():
            steps += [event.step for value in event.summary.value if value.tag == tag]
    return sorted(steps)


def load_params(run_dir: Path) -> dict:
    with open(run_dir / "params.pt", "rb") as f:
        return torch.load(f, weights_only=True)


def tree_digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


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


@pytest.mark.parametrize("solver", sorted(RUNS))
def test_killed_run_resumes_exactly(tmp_path, solver):
    problem, settings, kill_at = RUNS[solver]
    fit(build_problem("spring1d", problem), settings, run_dir=tmp_path / "straight",
        options=QUIET)                    # the uninterrupted run (in this process)
    killed = run_script(tmp_path / "killed", problem, settings, kill_at=kill_at)
    assert killed.returncode == -9, killed.stderr
    assert not (tmp_path / "killed" / "result.json").exists()
    resumed = run_script(tmp_path / "killed", problem, settings, resume=True)
    assert resumed.returncode == 0, resumed.stderr

    a = json.loads((tmp_path / "straight" / "result.json").read_text())
    b = json.loads((tmp_path / "killed" / "result.json").read_text())
    assert b["resumed_from_iteration"] == kill_at
    assert a["iterations"] > kill_at + 1, "the kill must fall inside the run"
    for key in ("misfit", "k_err_rel", "u_err_2", "iterations", "stop_reason", "converged"):
        assert a[key] == b[key], key
    # whole-run counts (the resumed process's re-simulation of the checkpointed point is
    # not counted: it repeats work the killed process did and counted)
    assert (b["factorizations"], b["solves"]) == (a["factorizations"], a["solves"])
    assert torch.equal(load_params(tmp_path / "straight")["theta"],
                       load_params(tmp_path / "killed")["theta"])
    counted = {"wall_time"}
    assert [{k: v for k, v in r.items() if k not in counted} for r in a["history"]] == \
        [{k: v for k, v in r.items() if k not in counted} for r in b["history"]]
    steps = scalar_steps(tmp_path / "killed" / "tb", "fit/misfit")
    assert steps == list(range(a["iterations"] + 1)), "every step once in TensorBoard"


@pytest.mark.slow      # also at the solver level (tests/solvers/test_base.py)
def test_max_iter_is_the_budget_of_the_whole_run(tmp_path):
    problem, solver = {"n": 16}, {"name": "levenberg_marquardt", "max_iter": 6}
    assert run_script(tmp_path / "run", problem, solver, kill_at=3).returncode == -9
    assert run_script(tmp_path / "run", problem, solver, resume=True).returncode == 0
    saved = json.loads((tmp_path / "run" / "result.json").read_text())
    assert saved["iterations"] == 6 and saved["stop_reason"] == "max_iter"


def test_refused_resume_touches_nothing(tmp_path):
    problem = build_problem("spring1d", {"n": 8})
    fit(problem, {"name": "gauss_newton", "max_iter": 3}, run_dir=tmp_path, options=QUIET)
    before = tree_digest(tmp_path)
    with pytest.raises(ResumeError, match="tau"):
        fit(problem, {"name": "gauss_newton", "tau": 2.0}, run_dir=tmp_path, resume=True,
            options=QUIET)
    with pytest.raises(ResumeError, match="levenberg_marquardt"):
        fit(problem, "levenberg_marquardt", run_dir=tmp_path, resume=True, options=QUIET)
    with pytest.raises(ResumeError, match="n"):
        fit(build_problem("spring1d", {"n": 9}), "gauss_newton", run_dir=tmp_path, resume=True,
            options=QUIET)
    with pytest.raises(FitConfigError, match="already holds a run"):
        fit(problem, "gauss_newton", run_dir=tmp_path, options=QUIET)   # without resume
    assert tree_digest(tmp_path) == before


def test_resuming_a_finished_run_rewrites_nothing(tmp_path):
    problem = build_problem("spring1d", {"n": 8})
    first = fit(problem, {"name": "gauss_newton", "max_iter": 3}, run_dir=tmp_path, options=QUIET)
    before = tree_digest(tmp_path)
    again = fit(problem, {"name": "gauss_newton", "max_iter": 3}, run_dir=tmp_path, resume=True,
                options=QUIET)
    assert tree_digest(tmp_path) == before
    assert torch.equal(again.theta, first.theta) and again.metrics == first.metrics


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


def test_init_starts_where_an_earlier_run_ended_and_a_resume_must_repeat_it(tmp_path):
    settings = {"n": 16, "noise": 1e-4, "seed": 1}
    first = fit(build_problem("spring1d", settings), {"name": "gauss_newton", "max_iter": 1},
                run_dir=tmp_path / "first", options=QUIET)
    problem = build_problem("spring1d", settings)
    second = fit(problem, "gauss_newton", run_dir=tmp_path / "second", options=QUIET,
                 init=tmp_path / "first")
    # record 0 of the second run is the first run's last point, not the initial guess
    assert second.history[0]["misfit"] == first.metrics["misfit"]
    initial = fit(problem, {"name": "gauss_newton", "max_iter": 0}, options=QUIET)
    assert second.history[0]["misfit"] < 0.9 * initial.metrics["misfit"]
    assert second.stop_reason == "discrepancy" and second.metrics["misfit"] < first.metrics["misfit"]
    same = fit(problem, "gauss_newton", options=QUIET, init=first.theta)   # a tensor
    assert torch.equal(same.theta, second.theta)
    # the second run's checkpoint remembers its start: resuming from another one is refused
    for other in (None, torch.zeros(16)):
        with pytest.raises(ResumeError, match="init"):
            fit(problem, "gauss_newton", run_dir=tmp_path / "second", resume=True,
                options=QUIET, init=other)
    again = fit(problem, "gauss_newton", run_dir=tmp_path / "second", resume=True,
                options=QUIET, init=tmp_path / "first" / "params.pt")
    assert torch.equal(again.theta, second.theta)


def test_init_refuses_a_run_of_another_parameterisation(tmp_path):
    problem = build_problem("spring1d", {"n": 8})
    theta = problem.theta0
    for key, saved in (("transform", ("k", "identity")), ("field_name", ("E", "exp"))):
        save_params(tmp_path / key, theta, theta.exp(), *saved)
        with pytest.raises(FitConfigError, match=f"{key} '.*', but spring1d's is") as info:
            initial_theta(problem, tmp_path / key)
        assert str(tmp_path / key / "params.pt") in str(info.value)
    save_params(tmp_path / "same", theta + 1, theta.exp(), "k", "exp")
    assert torch.equal(initial_theta(problem, tmp_path / "same"), theta + 1)


def test_solvers_get_what_their_registry_entry_asks_of_the_parameterisation():
    class NoDifferences:
        n_params = 3

    class Custom:                      # only what build_solver looks at
        name = "custom"
        parameterization = NoDifferences()

    with pytest.raises(ValueError, match="split_bregman needs the difference operator D.*custom"):
        build_solver(Custom(), "split_bregman")
    assert build_solver(Custom(), "gauss_newton").config.name == "gauss_newton"
    with pytest.raises(ValueError, match="levenberg_marquardt needs the difference operator D"):
        build_solver(Custom(), {"name": "levenberg_marquardt", "preconditioner": "difference"})
    spring = build_problem("spring1d", {"n": 6})
    solver = build_solver(spring, {"name": "levenberg_marquardt", "preconditioner": "difference"})
    assert solver.D.shape == (5, 6)
    with pytest.raises(ValueError, match="no difference operator"):
        build_solver(build_problem("spring1d", {"n": 1}), "split_bregman")


def test_split_bregman_run_records_its_terms(tmp_path):
    # (its accuracy: tests/solvers/test_split_bregman.py)
    problem = build_problem("spring1d", {"n": 16, "noise": 1e-4})
    result = fit(problem, {"name": "split_bregman", "max_iter": 12}, run_dir=tmp_path,
                 options=QUIET)
    last = result.history[-1]
    for key in ("tv", "split_residual", "inner_iterations", "mu", "beta", "stage"):
        assert key in last, key
    for tag in ("fit/tv", "fit/objective", "solver/split_residual", "solver/inner_iterations",
                "solver/mu", "solver/beta", "solver/stage", "metrics/k_err_rel"):
        assert scalar_steps(tmp_path / "tb", tag) == list(range(result.iterations + 1)), tag


def test_verify_writes_its_report_and_checks_its_settings_first(tmp_path):
    problem = build_problem("spring1d", {"n": 16})
    report = verify(problem, run_dir=tmp_path / "ok")
    saved = json.loads((tmp_path / "ok" / "verify.json").read_text())
    assert report.passed and saved["passed"] is True
    assert abs(saved["taylor_rate"] - 2.0) <= 0.05 and saved["dot_product_rel_error"] <= 1e-10
    assert saved["config"]["problem"]["name"] == "spring1d" and saved["point"]["at"] == "initial"
    for bad, message in (({"at": "nowhere"}, "at="), ({"perturbation": -0.5}, "perturbation"),
                         ({"perturbation": float("inf")}, "perturbation"),
                         ({"dot_tol": 0.0}, "dot_tol")):
        with pytest.raises(FitConfigError, match=message):
            verify(problem, run_dir=tmp_path / "bad", **bad)
    assert not (tmp_path / "bad").exists()


# -- what a user sees of a 2-D run: TensorBoard (a real server, default options) and PNGs ----
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


def test_verify_on_membrane2d():
    report = verify(build_problem("membrane2d", {"nx": 8, "ny": 4}))
    assert report.passed and abs(report.taylor.rate - 2.0) <= 0.05
