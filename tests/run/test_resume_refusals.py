"""A resume never starts over and never continues on other inputs (issue 27): a run without a
readable checkpoint is refused naming the file (nothing changed), with one instruction that
a run without resume repeats; a checkpoint records the problem's input digests (a body's tet
mesh and animation) and a resume on other ones is refused naming what changed; a killed
writer's temporary files are removed by the next run."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from helpers.coarse_arm import arm, cache  # noqa: F401  (the module's mesh cache fixture)
from helpers.runs import QUIET, tree_digest
from torchfit.problems import build_problem
from torchfit.run import FitConfigError, ResumeError, fit
from torchfit.run.checkpoint import Checkpointer, read_checkpoint
from torchfit.run.solver import build_solver

GN3 = {"name": "gauss_newton", "max_iter": 3}


def _finished(run_dir):
    problem = build_problem("spring1d", {"n": 8})
    fit(problem, GN3, run_dir=run_dir, options=QUIET)
    return problem


def test_a_finished_run_without_its_checkpoint_is_not_started_over(tmp_path):
    problem = _finished(tmp_path)
    (tmp_path / "checkpoint.pt").unlink()
    before = tree_digest(tmp_path)
    with pytest.raises(ResumeError, match="checkpoint.pt is missing") as refused:
        fit(problem, GN3, run_dir=tmp_path, resume=True, options=QUIET)
    assert "result.json" in str(refused.value) and "history.jsonl" in str(refused.value)
    assert tree_digest(tmp_path) == before


def test_a_checkpoint_that_is_a_directory_is_refused_and_history_kept(tmp_path):
    problem = _finished(tmp_path)
    (tmp_path / "checkpoint.pt").unlink()
    (tmp_path / "checkpoint.pt").mkdir()
    before = tree_digest(tmp_path)
    with pytest.raises(ResumeError, match="checkpoint.pt is not a file"):
        fit(problem, GN3, run_dir=tmp_path, resume=True, options=QUIET)
    assert tree_digest(tmp_path) == before and len(before["history.jsonl"]) == 64


def test_a_corrupt_checkpoint_gives_one_instruction_with_and_without_resume(tmp_path):
    problem = _finished(tmp_path)
    (tmp_path / "checkpoint.pt").write_bytes(b"not a zip archive")
    before = tree_digest(tmp_path)
    with pytest.raises(ResumeError) as with_resume:
        fit(problem, GN3, run_dir=tmp_path, resume=True, options=QUIET)
    with pytest.raises(FitConfigError) as without:
        fit(problem, GN3, run_dir=tmp_path, options=QUIET)
    for refused in (with_resume, without):
        message = str(refused.value)
        assert "start it again in another run directory" in message, message
        assert "resume=false" not in message and "resume=true" not in message, message
    assert "not a readable checkpoint" in str(with_resume.value)
    assert "cannot be read" in str(without.value)
    assert tree_digest(tmp_path) == before


def test_resume_into_a_directory_without_a_run_starts_fresh(tmp_path):
    run_dir = tmp_path / "new"
    result = fit(build_problem("spring1d", {"n": 8}), GN3, run_dir=run_dir, resume=True,
                 options=QUIET)
    assert result.resumed_from is None and (run_dir / "result.json").is_file()


def test_a_resume_on_other_inputs_is_refused_naming_them(tmp_path):
    problem = build_problem("spring1d", {"n": 8})
    problem.input_digests = lambda: {"tet mesh": "aaaa", "animation": "bbbb"}
    fit(problem, {"name": "gauss_newton", "max_iter": 2}, run_dir=tmp_path, options=QUIET)
    payload = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert payload["inputs"] == {"tet mesh": "aaaa", "animation": "bbbb"}
    before = tree_digest(tmp_path)
    problem.input_digests = lambda: {"tet mesh": "cccc", "animation": "bbbb"}
    with pytest.raises(ResumeError) as refused:
        fit(problem, GN3, run_dir=tmp_path, resume=True, options=QUIET)
    message = str(refused.value)
    assert "another tet mesh" in message and "tet mesh: aaaa there, cccc now" in message
    assert "animation" not in message.split("(")[0]
    assert tree_digest(tmp_path) == before
    problem.input_digests = lambda: {"tet mesh": "aaaa", "animation": "bbbb"}
    resumed = fit(problem, GN3, run_dir=tmp_path, resume=True, options=QUIET)
    assert resumed.resumed_from == 2 and resumed.iterations == 3


def test_a_killed_writers_temporary_files_are_removed_by_the_next_run(tmp_path):
    problem = build_problem("spring1d", {"n": 8})
    fit(problem, {"name": "gauss_newton", "max_iter": 2}, run_dir=tmp_path, options=QUIET)
    stale = [tmp_path / ".checkpoint.pt.999999.140.tmp", tmp_path / ".result.json.5.6.tmp",
             tmp_path / "body.vtu.tmp.vtu"]
    for path in stale:
        path.write_bytes(b"half")
    (tmp_path / "notes.tmp").write_text("mine")          # not a name torchfit writes
    fit(problem, GN3, run_dir=tmp_path, resume=True, options=QUIET)
    assert not any(p.exists() for p in stale)
    assert (tmp_path / "notes.tmp").read_text() == "mine"


@pytest.mark.slow       # a coarse arm (a cold tetrahedralisation: ~15 s)
def test_a_rebuilt_tet_mesh_cache_entry_is_named_on_resume(tmp_path, cache):  # noqa: F811
    problem = arm(cache, frames=[0])
    digests = problem.input_digests()
    assert set(digests) == {"tet mesh", "animation"}
    assert arm(cache, frames=[0]).input_digests() == digests, "the same inputs, the same digests"
    assert arm(cache, frames=[3]).input_digests()["animation"] != digests["animation"]
    solver = build_solver(problem, {"name": "gauss_newton", "max_iter": 1})
    Checkpointer(tmp_path, problem, solver, []).commit(0, problem.theta0, {})
    (tmp_path / "history.jsonl").write_text(json.dumps({"iteration": 0}) + "\n")
    assert read_checkpoint(tmp_path, problem, solver).iteration == 0
    (entry,) = (Path(cache) / "tetmesh").rglob("*.npz")     # canonical/<key>/<digest>.npz
    with np.load(entry) as saved:
        arrays = dict(saved)
    arrays["points"] = arrays["points"] * 1.001        # the entry rebuilt into another mesh
    with open(entry, "wb") as f:
        np.savez(f, **arrays)
    rebuilt = arm(cache, frames=[0])
    with pytest.raises(ResumeError, match="another tet mesh than this one builds"):
        read_checkpoint(tmp_path, rebuilt, build_solver(rebuilt, {"name": "gauss_newton"}))


@pytest.mark.parametrize("where, value", [("theta", float("nan")),
                                          ("solver_state/theta", float("nan")),
                                          ("solver_state/gradient", float("inf"))])
def test_a_checkpoint_with_a_non_finite_tensor_is_refused_naming_it(tmp_path, where, value):
    """Issue 38: NaN written into a checkpoint's theta was resumed (a traceback, exit 1)."""
    problem = build_problem("spring1d", {"n": 8})
    fit(problem, {"name": "gauss_newton", "max_iter": 2}, run_dir=tmp_path, options=QUIET)
    payload = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    *parents, leaf = where.split("/")
    holder = payload
    for key in parents:
        holder = holder[key]
    holder[leaf][3] = value
    torch.save(payload, tmp_path / "checkpoint.pt")
    before = tree_digest(tmp_path)
    with pytest.raises(ResumeError) as refused:
        fit(problem, GN3, run_dir=tmp_path, resume=True, options=QUIET)
    message = str(refused.value)
    assert str(tmp_path / "checkpoint.pt") in message and "non-finite" in message, message
    assert f"{where}: 1 of " in message and f"entry 3 is {value}" in message, message
    assert "another run directory" in message, message
    assert tree_digest(tmp_path) == before


def test_first_non_finite_looks_into_nested_state_and_skips_plain_numbers():
    from torchfit.run.checkpoint import first_non_finite

    finite = {"theta": torch.ones(3), "steps": torch.arange(3), "inf_norm": float("inf"),
              "rng": torch.zeros(4, dtype=torch.uint8), "none": None}
    assert first_non_finite(finite) is None
    nested = {**finite, "simulation_state": {"anchors": [torch.zeros(2, 2),
                                                         torch.tensor([[0.0, 1.0],
                                                                       [float("-inf"), 2.0]])]}}
    assert first_non_finite(nested) == ("simulation_state/anchors/1: 1 of 4 entries, entry 2 "
                                        "is -inf")
    assert first_non_finite({"z": torch.tensor([1 + 1j, complex(0, float("nan"))])}) \
        .startswith("z: 1 of 2 entries, entry 1 is")
