"""torchfit.run.distributed.refusals: what a distributed fit refuses is one line from rank 0,
before anything is written, under torchrun and under ``experiments/launch.py``."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from helpers.capsule_animation import write_capsule
from helpers.fit_app import REPO
from torchfit.problems import build_problem
from torchfit.run import FitConfigError
from torchfit.run.distributed.refusals import (check_resume, check_same_inputs, check_single_job,
                                               check_state, check_supported)
from torchfit.run.distributed.split import partition

TORCHRUN = Path(sys.executable).with_name("torchrun")
SPRING_REFUSED = ("error: problem spring1d / solver gauss_newton does not run distributed yet "
                  "(torchrun runs a quasistatic rigged body with levenberg_marquardt or "
                  "gauss_newton); run it as one process")


def test_what_does_not_run_distributed_is_refused_in_one_line():
    chain = build_problem("spring1d", {})
    with pytest.raises(FitConfigError, match="problem spring1d / solver gauss_newton does not "
                                             "run distributed yet") as info:
        check_supported(chain, {"solver": {"name": "gauss_newton",
                                           "dense_jacobian_max_params": 1000}}, 2)
    assert "\n" not in str(info.value)
    with pytest.raises(FitConfigError, match=r"a sweep \(-m\) does not run under torchrun"):
        check_single_job(True)
    check_single_job(False)


def test_a_problem_in_time_is_refused_naming_problem_dynamic():
    """Issue 50: a run in time under torchrun was refused naming the problem and the solver;
    what does not run distributed is the setting problem.dynamic=true."""
    in_time = build_problem("spring1d", {"dynamic": True})
    with pytest.raises(FitConfigError) as info:
        check_supported(in_time, {"solver": {"name": "levenberg_marquardt"}}, 2)
    assert str(info.value) == ("problem.dynamic=true does not run distributed yet: a body in "
                               "time integrates its frames one after another, torchrun shares "
                               "out the poses of a quasistatic body; run spring1d in time as "
                               "one process")


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


def _env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR",
                                                             "TORCHFIT_LAUNCH")}


@pytest.mark.slow
def test_torchrun_refuses_what_does_not_run_distributed_and_writes_nothing(tmp_path):
    proc = subprocess.run([str(TORCHRUN), "--standalone", "--nproc_per_node=2",
                           "experiments/fit.py", f"hydra.run.dir={tmp_path / 'run'}",
                           "problem=spring1d", "threads=1"], cwd=REPO, env=_env(),
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode != 0
    lines = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert lines == [SPRING_REFUSED]
    assert "exitcode: 2" in proc.stderr           # rank 0's refusal; the worker left quietly
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_refusals_under_the_launcher_are_one_line_and_exit_2(tmp_path):
    """``experiments/launch.py`` (what ``scripts/fit.sh --nproc_per_node=2`` runs): a problem
    that does not run distributed and a resume of a checkpoint written by 1 process are
    each exactly one line on standard error, exit 2, the directory as it was; raw torchrun
    gives the same first line, then its summary (rank 0's ``exitcode: 2``) and exit 1."""
    launch = [sys.executable, "experiments/launch.py", "--standalone", "--nproc_per_node=2"]
    refused = subprocess.run([*launch, f"hydra.run.dir={tmp_path / 'chain'}",
                              "problem=spring1d", "threads=1"], cwd=REPO, env=_env(),
                             capture_output=True, text=True, timeout=300)
    assert refused.returncode == 2, refused.stderr[-3000:]
    assert refused.stderr.splitlines() == [SPRING_REFUSED]
    assert not (tmp_path / "chain").exists()

    run = tmp_path / "one"          # an earlier run's directory, its checkpoint 1 process's
    (run / ".hydra").mkdir(parents=True)
    for name in ("config.yaml", "hydra.yaml", "overrides.yaml"):     # what Hydra writes
        (run / ".hydra" / name).write_text(f"# the earlier run's {name}\n")
    (run / "fit.log").write_text("the earlier run's log\n")
    torch.save({"simulation_state": {"anchor": 0}}, run / "checkpoint.pt")

    def contents() -> dict[str, bytes]:
        return {str(p.relative_to(run)): p.read_bytes() for p in run.rglob("*") if p.is_file()}
    before = contents()
    folder = write_capsule(tmp_path / "capsule", "skeleton", "npz")
    settings = [f"hydra.run.dir={run}", "problem=animation", f"problem.path={folder}",
                f"problem.cache_dir={tmp_path / 'cache'}", "problem.tet_edge_length=0.12",
                "problem.grid=[2,2,3]", "solver=levenberg_marquardt", "threads=1",
                "solver.max_iter=4", "resume=true"]
    resumed = subprocess.run([*launch, *settings], cwd=REPO, env=_env(), capture_output=True,
                             text=True, timeout=300)
    assert resumed.returncode == 2, resumed.stderr[-3000:]
    assert resumed.stderr.splitlines() == [
        f"error: cannot resume: {run / 'checkpoint.pt'} was written by 1 process(es), this run "
        "has 2; resume with torchrun --nproc_per_node=1 (or as one process)"]
    assert contents() == before

    raw = subprocess.run([str(TORCHRUN), "--standalone", "--nproc_per_node=2",
                          "experiments/fit.py", *settings], cwd=REPO,
                         env={**_env(), "OMP_NUM_THREADS": "1"}, capture_output=True,
                         text=True, timeout=300)
    assert raw.returncode == 1                  # torchrun's status for any failed rank
    first = raw.stderr.splitlines()[0]
    assert first == resumed.stderr.splitlines()[0]
    assert [line for line in raw.stderr.splitlines() if line.startswith("error:")] == [first]
    assert re.search(r"rank +: 0 \(local_rank: 0\)\n +exitcode +: 2 ", raw.stderr)
    assert contents() == before
