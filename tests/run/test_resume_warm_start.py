"""Exact resume of a warm-started problem: the checkpoint carries the equilibria the next
iteration's Newton starts from (``problem.warm_starts.warm_start_state()``), so a run stopped after any
iteration and resumed in a fresh process (a fresh problem, a cold solution cache) goes on
bit for bit as the uninterrupted one.

``threads=1``: with more threads MKL PARDISO's factorisation is not bit-reproducible even
between two uninterrupted runs."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from helpers.coarse_arm import arm, cache  # noqa: F401  (the fixture)
from helpers.repeating_animation import write_tube
from torchfit.problems import build_problem
from torchfit.run import FitOptions, ResumeError, fit

OPTIONS = FitOptions(progress=False, threads=1)


class Killed(Exception):
    pass


def kill_after(k):
    def callback(record):
        if record.iteration == k:
            raise Killed(k)
    return callback


def without_time(rows):
    return [{key: v for key, v in row.items() if key != "wall_time"} for row in rows]


def check_resumes(make, tmp_path, max_iter, kills):
    """Kill (an exception from a callback) after each iteration of ``kills``, resume with a
    fresh problem from ``make()`` (what a new process has: a cold solution cache), compare
    with the uninterrupted run bit for bit."""
    torch.set_num_threads(1)
    solver = {"name": "levenberg_marquardt", "max_iter": max_iter}
    full = fit(make(), solver, run_dir=tmp_path / "full", options=OPTIONS)
    assert full.iterations > max(kills), "the kills must fall inside the run"
    for k in kills:
        run_dir = tmp_path / f"killed{k}"
        with pytest.raises(Killed):
            fit(make(), solver, run_dir=run_dir, options=OPTIONS,
                callbacks=[kill_after(k)])
        resumed = fit(make(), solver, run_dir=run_dir, resume=True,
                      options=OPTIONS)
        assert resumed.resumed_from == k
        assert torch.equal(resumed.theta, full.theta), k
        assert (resumed.iterations, resumed.stop_reason, resumed.converged) == \
            (full.iterations, full.stop_reason, full.converged)
        assert resumed.metrics == full.metrics
        assert without_time(resumed.history) == without_time(full.history)
        assert (resumed.factorizations, resumed.solves) == (full.factorizations, full.solves)
        assert resumed.validation == full.validation        # frames held out: the same choice
        errors = tmp_path / "full" / "frame_errors.jsonl"   # a body's per-frame errors
        if errors.is_file():    # (issue 50: a resume drew no frame_errors_history.png)
            assert (run_dir / "frame_errors.jsonl").read_text() == errors.read_text()
            assert len(errors.read_text().splitlines()) == full.iterations + 1
            assert (run_dir / "frame_errors_history.png").is_file()


def test_the_checkpoint_holds_the_warm_start_anchor(cache, tmp_path):  # noqa: F811
    """``checkpoint.pt`` (read with ``weights_only=True``) holds the equilibria of the
    checkpointed point: the anchor first, at the checkpoint's parameters, every frame."""
    problem = arm(cache, frames=[11])
    with pytest.raises(Killed):
        fit(problem, {"name": "levenberg_marquardt", "max_iter": 3}, run_dir=tmp_path,
            options=OPTIONS, callbacks=[kill_after(0)])
    with open(tmp_path / "checkpoint.pt", "rb") as f:
        saved = torch.load(f, weights_only=True)
    state = saved["simulation_state"]
    assert state["anchor"] == 0
    anchor = state["solutions"][0]
    assert torch.equal(anchor["params"], problem.field(saved["theta"]))
    equilibrium = problem.poses.quasistatic.equilibrium
    assert anchor["x"].shape == (1, equilibrium.model.n_dofs)
    assert anchor["reference"].shape == (1,)


def test_warm_started_arm_resumes_exactly(cache, tmp_path):  # noqa: F811
    """The folded frame alone (several equilibria: a cold re-solve of the checkpointed
    point went elsewhere before the checkpoint held the warm-start state)."""
    check_resumes(lambda: arm(cache, frames=[11]), tmp_path, 3, [1])


@pytest.mark.slow
def test_warm_started_arm_resumes_exactly_after_any_iteration(cache, tmp_path):  # noqa: F811
    check_resumes(lambda: arm(cache, frames=[0, 11]), tmp_path, 4, [1, 2])


def test_a_body_with_validation_frames_resumes_exactly(tmp_path):
    """Frames held out of the fit (``problem.validation_frames``): the checkpoint holds the
    chosen iteration so far and the validation's own warm starts, so the validation errors
    of every iteration, the choice and the counts (the validation's work is not the
    solver's) are the uninterrupted run's."""
    settings = {"path": str(write_tube(tmp_path / "tube")), "tet_edge_length": 0.3,
                "grid": [2, 2, 2], "cache_dir": str(tmp_path / "cache"), "frames": [0, 2, 6],
                "validation_frames": [1]}
    check_resumes(lambda: build_problem("animation", settings), tmp_path, 3, [1])


def test_a_body_killed_after_its_last_iteration_draws_the_whole_history(tmp_path):
    """Killed after its last iteration, before its outputs (issue 50): the resume has one
    record of its own, yet frame_errors_history.png and frame_errors.jsonl cover every
    iteration, as the uninterrupted run's."""
    torch.set_num_threads(1)
    settings = {"path": str(write_tube(tmp_path / "tube")), "tet_edge_length": 0.3,
                "grid": [2, 2, 2], "cache_dir": str(tmp_path / "cache"), "frames": [0, 2, 6]}
    solver = {"name": "levenberg_marquardt", "max_iter": 2}
    full = fit(build_problem("animation", settings), solver, run_dir=tmp_path / "full",
               options=OPTIONS)
    run_dir = tmp_path / "killed"
    with pytest.raises(Killed):
        fit(build_problem("animation", settings), solver, run_dir=run_dir, options=OPTIONS,
            callbacks=[kill_after(full.iterations)])
    assert not (run_dir / "frame_errors_history.png").exists()
    resumed = fit(build_problem("animation", settings), solver, run_dir=run_dir, resume=True,
                  options=OPTIONS)
    assert torch.equal(resumed.theta, full.theta)
    assert (run_dir / "frame_errors.jsonl").read_text() == \
        (tmp_path / "full" / "frame_errors.jsonl").read_text()
    assert len((run_dir / "frame_errors.jsonl").read_text().splitlines()) == full.iterations + 1
    assert (run_dir / "frame_errors_history.png").is_file()


@pytest.mark.slow
def test_warm_started_membrane_resumes_exactly(tmp_path):
    check_resumes(lambda: build_problem("membrane2d", {"nx": 32, "ny": 8}), tmp_path, 4, [1])


def test_a_checkpoint_of_the_old_format_is_refused_with_one_line(tmp_path):
    """Format 2 had no simulation state: its resume would not be exact, so it is refused,
    and the directory is left as it was."""
    problem = build_problem("spring1d", {"n": 8})
    with pytest.raises(Killed):
        fit(problem, "gauss_newton", run_dir=tmp_path, options=OPTIONS,
            callbacks=[kill_after(1)])
    path = tmp_path / "checkpoint.pt"
    payload = torch.load(path, weights_only=True)
    assert payload["format"] == 3 and payload["simulation_state"] == {}   # a linear problem
    del payload["simulation_state"]
    torch.save({**payload, "format": 2}, path)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    with pytest.raises(ResumeError) as refused:
        fit(problem, "gauss_newton", run_dir=tmp_path, resume=True, options=OPTIONS)
    message = str(refused.value)
    assert "\n" not in message and "checkpoint format 2" in message and "format 3" in message
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before
