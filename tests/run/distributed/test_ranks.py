"""torchfit.run.distributed.ranks: frames over torchrun ranks give the one-process fit."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from helpers.capsule_animation import write_capsule
from helpers.fit_app import REPO, run_fit_app
from helpers.repeating_animation import POSES, write_tube
from torchfit.problems import build_problem
from torchfit.run import FitConfigError
from torchfit.run.distributed.ranks import (check_resume, check_same_inputs, check_state,
                                      check_supported, partition)

TORCHRUN = Path(sys.executable).with_name("torchrun")


def test_partition_interleaves_the_poses_balanced():
    assert partition(5, 2) == [[0, 2, 4], [1, 3]]
    assert partition(23, 2)[1] == list(range(1, 23, 2))     # the arm: 12 + 11 poses
    assert partition(2, 3) == [[0], [1], []]
    for poses, ranks in ((48, 5), (7, 3), (11, 4), (3, 1)):
        blocks = partition(poses, ranks)
        sizes = [len(block) for block in blocks]
        assert max(sizes) - min(sizes) <= 1 and sizes == sorted(sizes, reverse=True)
        assert sorted(sum(blocks, [])) == list(range(poses))       # each pose once
        # a run of neighbouring poses (alike in cost) is shared out evenly
        for start in range(0, poses - ranks + 1):
            window = range(start, start + ranks)
            assert sorted(r for r, b in enumerate(blocks) for p in b if p in window) == \
                list(range(ranks))
    with pytest.raises(ValueError):
        partition(4, 0)


def test_what_does_not_run_distributed_is_refused_in_one_line():
    chain = build_problem("spring1d", {})
    with pytest.raises(FitConfigError, match="problem spring1d / solver gauss_newton does not "
                                             "run distributed yet") as info:
        check_supported(chain, {"solver": {"name": "gauss_newton",
                                           "dense_jacobian_max_params": 1000}}, 2)
    assert "\n" not in str(info.value)


def test_a_resume_with_another_number_of_processes_is_refused(tmp_path):
    state = {"world_size": 2, "blocks": [[0, 2], [2, 3]], "ranks": [{"a": 1}, {"a": 2}]}
    torch.save({"simulation_state": state}, tmp_path / "checkpoint.pt")
    check_resume(tmp_path, 2)
    with pytest.raises(FitConfigError, match="written by 2 process.*--nproc_per_node=2"):
        check_resume(tmp_path, 1)
    torch.save({"simulation_state": {"anchor": 0}}, tmp_path / "checkpoint.pt")
    with pytest.raises(FitConfigError, match="written by 1 process"):
        check_resume(tmp_path, 3)
    torch.save({"simulation_state": {}}, tmp_path / "checkpoint.pt")   # linear: nothing saved
    check_resume(tmp_path, 3)


def test_warm_starts_shared_out_otherwise_are_refused_in_one_line():
    # a 2-rank checkpoint written with contiguous blocks (before the interleaved partition)
    old = {"world_size": 2, "blocks": [[0, 2], [2, 3]], "ranks": [{}, {}]}
    with pytest.raises(FitConfigError, match="shared over the ranks in another way") as info:
        check_state(old, partition(3, 2))
    assert "\n" not in str(info.value)
    with pytest.raises(FitConfigError, match="--nproc_per_node=2"):
        check_state(old, partition(3, 3))
    check_state({**old, "blocks": [[0, 2], [1]]}, partition(3, 2))      # the same split


def test_a_rank_on_other_inputs_is_refused_in_one_line():
    mine = {"tet mesh": "a1", "animation": "b1"}
    check_same_inputs(mine, [None, dict(mine), dict(mine)])
    with pytest.raises(FitConfigError, match="rank 2 built its problem on another tet mesh "
                                             "than rank 0") as info:
        check_same_inputs(mine, [None, dict(mine), {"tet mesh": "a2", "animation": "b1"}])
    assert "\n" not in str(info.value)


def _torchrun(run_dir: Path, *overrides: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    return subprocess.run([str(TORCHRUN), "--standalone", "--nproc_per_node=2",
                           "experiments/fit.py", f"hydra.run.dir={run_dir}", *overrides],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=600)


def _theta(run: Path) -> torch.Tensor:
    return torch.load(run / "params.pt", weights_only=False)["theta"]


@pytest.mark.slow
def test_two_ranks_give_the_one_process_iterates_and_resume_exactly(tmp_path):
    """Three frames of a capsule split 2 + 1: iterations, stop reason and the whole-job
    counters equal to the one-process run's, theta and the surface error to round-off
    (1e-10 relative; measured 1.0e-13 after 3 iterations: ``J^T J`` and ``J^T r`` are
    summed per rank, not in one product); a 2-rank run stopped after 2 iterations and
    resumed to 3 ends at the uninterrupted 2-rank run's theta bit for bit (the sums have a
    fixed order), with the mesh cache gone (every rank builds on the run's mesh.npz); a
    one-process resume of it is refused."""
    folder = write_capsule(tmp_path / "capsule", "skeleton", "npz")
    settings = ["problem=animation", f"problem.path={folder}",
                f"problem.cache_dir={tmp_path / 'cache'}", "problem.tet_edge_length=0.12",
                "problem.grid=[2,2,3]", "solver=levenberg_marquardt", "threads=1"]
    one = run_fit_app(tmp_path / "one", *settings, "solver.max_iter=3")
    assert one.returncode == 0, one.stderr[-3000:]
    two = _torchrun(tmp_path / "two", *settings, "solver.max_iter=3")
    assert two.returncode == 0, two.stderr[-3000:]
    first = json.loads((tmp_path / "one" / "result.json").read_text())
    second = json.loads((tmp_path / "two" / "result.json").read_text())
    one_theta, two_theta = _theta(tmp_path / "one"), _theta(tmp_path / "two")
    assert float((one_theta - two_theta).abs().max()) <= 1e-10 * float(one_theta.abs().max())
    for key in ("iterations", "stop_reason", "factorizations", "solves"):
        assert first[key] == second[key], key
    assert abs(first["surface_err_mean"] - second["surface_err_mean"]) <= \
        1e-10 * first["surface_err_mean"]
    checkpoint = torch.load(tmp_path / "two" / "checkpoint.pt", weights_only=True)
    assert checkpoint["simulation_state"]["blocks"] == [[0, 2], [1]]     # interleaved

    part = _torchrun(tmp_path / "resumed", *settings, "solver.max_iter=2")
    assert part.returncode == 0, part.stderr[-3000:]
    refused = run_fit_app(tmp_path / "resumed", *settings, "solver.max_iter=3", "resume=true")
    assert refused.returncode == 2
    assert "error: cannot resume" in refused.stderr and "--nproc_per_node=2" in refused.stderr
    shutil.rmtree(tmp_path / "cache")       # every rank resumes on the run's mesh.npz
    resumed = _torchrun(tmp_path / "resumed", *settings, "solver.max_iter=3", "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert torch.equal(two_theta, _theta(tmp_path / "resumed"))


def _tube_on_one_and_two_ranks(tmp_path: Path, *overrides: str, counted: tuple[str, ...] = (
        "iterations", "stop_reason", "factorizations", "solves")) -> tuple[dict, dict, float]:
    """The repeating tube fitted by one process and by 2 ranks: both results, ``counted``
    checked equal, and theta's largest difference relative to its size."""
    folder = write_tube(tmp_path / "tube")
    settings = ["problem=animation", f"problem.path={folder}",
                f"problem.cache_dir={tmp_path / 'cache'}", "problem.tet_edge_length=0.3",
                "problem.grid=[2,2,2]", "solver=levenberg_marquardt", "threads=1", *overrides]
    one = run_fit_app(tmp_path / "one", *settings)
    assert one.returncode == 0, one.stderr[-3000:]
    two = _torchrun(tmp_path / "two", *settings)
    assert two.returncode == 0, two.stderr[-3000:]
    first = json.loads((tmp_path / "one" / "result.json").read_text())
    second = json.loads((tmp_path / "two" / "result.json").read_text())
    for key in counted:
        assert first[key] == second[key], key
    one_theta, two_theta = _theta(tmp_path / "one"), _theta(tmp_path / "two")
    return first, second, float((one_theta - two_theta).abs().max() / one_theta.abs().max())


@pytest.mark.slow
def test_repeated_poses_are_split_over_the_ranks_once(tmp_path):
    """A tube whose 8 frames are 5 poses: the 2 ranks simulate poses 0, 2, 4 and 1, 3 (each once in
    the whole job: the counters equal one process's, which simulates the 5 poses), and
    ``J^T J`` weights a pose's rows by its frames: the iterates of one process to round-off."""
    _, _, difference = _tube_on_one_and_two_ranks(tmp_path, "solver.max_iter=3")
    assert difference <= 1e-10
    checkpoint = torch.load(tmp_path / "two" / "checkpoint.pt", weights_only=True)
    assert checkpoint["simulation_state"]["blocks"] == [[0, 2, 4], [1, 3]]
    assert len(POSES) == 5


@pytest.mark.slow
def test_the_matrix_free_path_gives_the_one_process_iterates(tmp_path):
    """``solver.dense_jacobian_max_params=0``: LM's CGLS takes ``J v`` and ``J^T w`` by
    autograd through the distributed simulation (each rank's graph; backward summed, jvp
    gathered): the one-process iterates and factorisations. Tolerance 1e-6 relative:
    CGLS carries the per-rank sums' round-off through its inner iterations (measured
    2.1e-8, 3.0e-9 and under 1e-8 on three meshes after 2 LM iterations), and its
    relative stopping test may then stop one inner iteration apart (8 against 7 on one
    mesh: 10 solves more for the 5 poses), so the inner iterations may differ by one."""
    first, second, difference = _tube_on_one_and_two_ranks(
        tmp_path, "solver.max_iter=2", "solver.dense_jacobian_max_params=0",
        counted=("iterations", "stop_reason", "factorizations"))
    assert "dense_jacobian" not in first["history"][-1]       # the matrix-free path
    assert difference <= 1e-6
    for a, b in zip(first["history"], second["history"]):
        assert abs(a["cg_iterations"] - b["cg_iterations"]) <= 1


@pytest.mark.slow
def test_torchrun_refuses_what_does_not_run_distributed_and_writes_nothing(tmp_path):
    proc = _torchrun(tmp_path / "run", "problem=spring1d", "threads=1")
    assert proc.returncode != 0
    lines = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert lines == ["error: problem spring1d / solver gauss_newton does not run distributed "
                     "yet (torchrun runs a quasistatic rigged body with levenberg_marquardt or "
                     "gauss_newton); run it as one process"]
    assert "exitcode: 2" in proc.stderr           # rank 0's refusal; the worker left quietly
    assert not (tmp_path / "run").exists()
