"""What a distributed fit refuses before it starts, each in one line: the checks of its input.

Every refusal is a :class:`~torchfit.run.options.FitConfigError` whose message is one line
naming what to change, raised on rank 0 before anything is written (the workers are then
told to leave: :meth:`.session.DistributedSession.stop`):

- :func:`check_single_job`: a Hydra sweep (``-m``) runs one torchrun per job;
- :func:`check_supported`: a quasistatic rigged body with Gauss-Newton or
  Levenberg-Marquardt, at least one distinct pose per rank, no continuation;
- :func:`check_resume` and :func:`check_state`: warm starts saved by as many processes as
  now, with the poses shared out the same way;
- :func:`check_same_inputs`: every rank built its problem on rank 0's inputs.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from ...problems import MotionProblem, PosedProblem
from ..options import FitConfigError

#: solvers that run distributed (dense Jacobian or matrix-free)
SOLVERS = ("levenberg_marquardt", "gauss_newton")


def check_single_job(multirun: bool) -> None:
    """Refuse a sweep: one torchrun job fits one configuration."""
    if multirun:
        raise FitConfigError("a sweep (-m) does not run under torchrun; launch one torchrun "
                             "per job")


def check_supported(problem: Any, config: dict[str, Any], n_ranks: int) -> None:
    """Refuse what does not run distributed yet: another problem or solver, fewer distinct
    poses than ranks, a continuation."""
    solver = str(config.get("solver", {}).get("name"))
    name = problem.name
    if isinstance(problem, MotionProblem):      # (the line named the problem and solver)
        raise FitConfigError(f"problem.dynamic=true does not run distributed yet: a body in "
                             f"time integrates its frames one after another, torchrun shares "
                             f"out the poses of a quasistatic body; run {name} in time as one "
                             "process")
    supported = isinstance(problem, PosedProblem) and solver in SOLVERS
    if not supported:
        raise FitConfigError(f"problem {name} / solver {solver} does not run distributed yet "
                             f"(torchrun runs a quasistatic rigged body with "
                             f"{' or '.join(SOLVERS)}); run it as one process")
    poses = problem.poses.simulated_poses()
    units = int(problem.n_frames) if isinstance(poses, slice) else len(poses)
    if units < n_ranks:
        raise FitConfigError(f"problem {name} simulates {units} distinct pose(s) "
                             f"({problem.n_frames} frames), fewer than the {n_ranks} "
                             f"processes; start at most --nproc_per_node={units}")
    if config.get("continuation"):
        raise FitConfigError("continuation=true does not run distributed yet; run it as one "
                             "process")


def check_resume(run_dir: Path, n_ranks: int) -> None:
    """Refuse a resume whose checkpoint's warm starts came from another number of processes
    (read before anything is written; an unreadable checkpoint is the resume's to report)."""
    path = run_dir / "checkpoint.pt"
    if not path.is_file():
        return
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
        state = payload.get("simulation_state") or {}
    except Exception:  # noqa: BLE001  (read_checkpoint reports an unreadable file)
        return
    saved = int(state.get("world_size", 1)) if isinstance(state, dict) and state else None
    if saved is not None and saved != n_ranks:
        raise FitConfigError(f"cannot resume: {path} was written by {saved} process(es), this "
                             f"run has {n_ranks}; resume with torchrun --nproc_per_node={saved}"
                             f"{' (or as one process)' if saved == 1 else ''}")


def check_state(state: dict[str, Any], blocks: list[list[int]]) -> None:
    """Refuse warm starts saved by another number of processes, or by the same number with
    the poses shared out otherwise (a checkpoint written before the interleaved
    :func:`.split.partition`: each rank would start its poses from another pose's
    equilibrium)."""
    saved = int(state.get("world_size", 1))
    if saved != len(blocks):
        raise FitConfigError(f"cannot resume: the checkpoint's warm starts come from {saved} "
                             f"process(es), this run has {len(blocks)}; resume with torchrun "
                             f"--nproc_per_node={saved}")
    if [list(b) for b in state.get("blocks", [])] != [list(b) for b in blocks]:
        raise FitConfigError("cannot resume: the checkpoint's warm starts were saved with the "
                             "poses shared over the ranks in another way (an earlier torchfit "
                             "split them in contiguous blocks); start the fit again")


def check_same_inputs(mine: dict[str, str], ranks: list[Any]) -> None:
    """Refuse a rank whose problem was built on other inputs (the tet mesh, the animation:
    their digests) than rank 0's, naming the first rank and input that differ (a worker
    on another node whose cache entry is missing tetrahedralises the surface again, and
    pytetwild's mesh differs from run to run). ``ranks``: every rank's digests, ``None``
    where a rank sent none."""
    for rank, theirs in enumerate(ranks):
        if theirs is None or theirs == mine:
            continue
        differs = sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))
        raise FitConfigError(f"rank {rank} built its problem on another {', '.join(differs)} "
                             "than rank 0; give every rank the same inputs (problem.cache_dir "
                             "on a disk every node reads, or resume where the run directory's "
                             "mesh.npz is readable by every rank)")
