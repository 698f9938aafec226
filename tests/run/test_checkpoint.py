"""Checkpoint and resume: exact resume after SIGKILL for every solver, the budget of the whole
run, a refused resume that touches nothing, a finished run left as it is."""
from __future__ import annotations

import json

import pytest
import torch

from helpers.runs import QUIET, load_params, run_script, scalar_steps, tree_digest
from torchfit.problems import build_problem
from torchfit.run import FitConfigError, ResumeError, fit


#: A small run of each solver on spring1d (n = 16): (problem settings, solver settings, kill at).
RUNS = {
    "gauss_newton": ({"n": 16, "noise": 1e-4, "seed": 1},
                     {"name": "gauss_newton"}, 2),
    "levenberg_marquardt": ({"n": 16}, {"name": "levenberg_marquardt", "max_iter": 12}, 5),
    "split_bregman": ({"n": 16, "noise": 1e-4, "seed": 1},
                      {"name": "split_bregman", "max_iter": 60}, 23),
}

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
