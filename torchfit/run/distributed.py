"""One fit over several processes (``torchrun``): the frames of a rigged body split over ranks.

Launched under ``torchrun`` (``WORLD_SIZE > 1``), every process builds the same problem from
the same settings (mesh, rig, data: cheap and identical), then the frames are split by a
static balanced partition (:func:`partition`: contiguous blocks in frame order, the first
``F mod W`` ranks one frame more) and each rank simulates only its block: its Newton
solves, factorisations and warm starts stay on it (:class:`FrameSplit` replaces the
problem's ``quasistatic``).

Leader and workers: rank 0 runs the whole fit (:func:`torchfit.fit`, the solver, every
output: it alone writes the run directory); ranks 1.. only serve (:func:`serve`). Each
simulation the problem asks for on rank 0 (``simulate``, ``forward_jacobian``, a cold
``independent`` block, the warm-start state for a checkpoint or a resume) is broadcast as
a command, every rank computes its frames, and the blocks are gathered to rank 0 in frame
order. So the solver sees exactly the residual, ``r`` and the dense ``J`` it sees in one
process (all gathered: for the arm ``J`` is ``F * n_obs * 3 x n`` doubles, about 220 MB,
and the normal equations are then formed on rank 0 as in one process). The iterates are
those of one process bit for bit where every frame's equilibrium does not depend on which
other frames share its batch (Newton is per frame; measured: docs/run/distributed.md).
What rank 0 alone runs (pictures, the model comparison's other materials) is unchanged
and may simulate any time: a worker is idle until the next command. Counters of
factorisations and solves of the other ranks are added to rank 0's (the result's totals
are the whole job's).

Checkpoints: rank 0's ``checkpoint.pt`` holds every rank's warm-start state (gathered,
``{"world_size", "blocks", "ranks"}``), scattered back on a resume; a resume must use the
same number of processes (:func:`check_resume`). A worker that dies ends the job (torchrun
stops the others; rank 0 reports which rank failed where it can) and ``resume=true``
continues from the last checkpoint. Collectives time out after
``TORCHFIT_DISTRIBUTED_TIMEOUT`` seconds (default 1800: a worker waits while rank 0 writes
pictures or simulates the model comparison alone).

Supported: quasistatic rigged bodies (``problem=arm3d``, ``arm3d_short``, ``animation``)
with Gauss-Newton or Levenberg-Marquardt on the dense Jacobian; the rest is refused
(:func:`check_supported`).
"""
from __future__ import annotations

import contextlib
import datetime
import logging
import os
import sys
import warnings
from pathlib import Path
from typing import Any, Callable, Iterator

import torch
import torch.distributed as dist
from torch import Tensor

from ..errors import SimulationError
from ..linalg.counters import COUNTERS
from .options import FitConfigError

SIMULATE, JACOBIAN, INDEPENDENT_ON, INDEPENDENT_OFF, STATE, RESTORE, STOP = range(7)
#: solvers whose dense-Jacobian path runs distributed
SOLVERS = ("levenberg_marquardt", "gauss_newton")
_OK, _SIMULATION_FAILED, _FAILED = 0, 1, 2
_SHARED = False     # rank 0 has handed the settings to the workers (they serve commands)
#: rank 0 is inside a command's exchange: stopped there (SIGTERM, a lost worker), it sends no
#: STOP (the workers are inside the same exchange; torchrun ends them when rank 0 exits)
_EXCHANGING = False


def _exchange(started: bool) -> None:
    global _EXCHANGING
    _EXCHANGING = started


def rank() -> int:
    """This process's rank under torchrun (0 outside it)."""
    return int(os.environ.get("RANK", "0"))


def world_size() -> int:
    """The number of processes torchrun started (1 outside torchrun)."""
    return int(os.environ.get("WORLD_SIZE", "1"))


def launched() -> bool:
    """Whether this process is one of several started by torchrun."""
    return world_size() > 1


def partition(n_frames: int, n_ranks: int) -> list[tuple[int, int]]:
    """``[start, stop)`` of each rank's contiguous block of frames; sizes differ by at most
    one (the first ``n_frames mod n_ranks`` ranks one more); a rank may get none."""
    if n_ranks < 1 or n_frames < 0:
        raise ValueError(f"cannot split {n_frames} frames over {n_ranks} ranks")
    base, extra = divmod(n_frames, n_ranks)
    blocks, start = [], 0
    for rank in range(n_ranks):
        stop = start + base + (1 if rank < extra else 0)
        blocks.append((start, stop))
        start = stop
    return blocks


def timeout_seconds() -> float:
    return float(os.environ.get("TORCHFIT_DISTRIBUTED_TIMEOUT", "1800"))


def start_group() -> None:
    """The process group (gloo: frames on the CPU) from torchrun's environment."""
    if not dist.is_initialized():
        dist.init_process_group("gloo", timeout=datetime.timedelta(seconds=timeout_seconds()))


def check_supported(problem: Any, config: dict[str, Any], n_ranks: int) -> None:
    """:class:`~.options.FitConfigError` (one line) for what does not run distributed yet."""
    from ..problems.rigged_body import RiggedBody
    solver = str(config.get("solver", {}).get("name"))
    name = getattr(problem, "name", type(problem).__name__)
    dense = int(config.get("solver", {}).get("dense_jacobian_max_params", 0))
    n = int(problem.parameterization.n_params)
    supported = isinstance(problem, RiggedBody) and not getattr(problem, "dynamic", False) \
        and solver in SOLVERS and 0 < n <= dense
    if not supported:
        raise FitConfigError(f"problem {name} / solver {solver} does not run distributed yet "
                             f"(torchrun runs a quasistatic rigged body with {' or '.join(SOLVERS)}"
                             f" on the dense Jacobian, n_params <= "
                             "solver.dense_jacobian_max_params); run it as one process")
    if problem.n_frames < n_ranks:
        raise FitConfigError(f"problem {name} has {problem.n_frames} frames, fewer than the "
                             f"{n_ranks} processes; start at most "
                             f"--nproc_per_node={problem.n_frames}")
    if config.get("continuation"):
        raise FitConfigError("continuation=true does not run distributed yet; run it as one "
                             "process")


def check_resume(run_dir: Path, n_ranks: int) -> None:
    """Refuse (one line) a resume whose checkpoint's warm starts came from another number of
    processes (nothing is written before)."""
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


class _Channel:
    """The collectives of the protocol (rank 0 commands, every rank answers)."""

    def __init__(self, blocks: list[tuple[int, int]]) -> None:
        self.rank, self.size = dist.get_rank(), dist.get_world_size()
        self.blocks = blocks
        self.longest = max(stop - start for start, stop in blocks)

    def command(self, code: int, *values: int) -> list[int]:
        header = torch.zeros(4, dtype=torch.int64)
        if self.rank == 0 and code in (SIMULATE, JACOBIAN, STATE, RESTORE):
            _exchange(True)
        if self.rank == 0:
            header[0] = code
            header[1:1 + len(values)] = torch.as_tensor(values, dtype=torch.int64)
        dist.broadcast(header, 0)
        return [int(v) for v in header]

    def share(self, tensor: Tensor | None, shape: tuple[int, ...], dtype: torch.dtype) -> Tensor:
        """``tensor`` of rank 0 on every rank (float64 over the wire)."""
        buffer = tensor.detach().to("cpu", torch.float64).contiguous() if self.rank == 0 \
            else torch.empty(shape, dtype=torch.float64)
        dist.broadcast(buffer, 0)
        return buffer.to(dtype)

    def collect(self, compute: Callable[[], Tensor]) -> Tensor | None:
        """Run ``compute`` (this rank's frames, frame-major first axis), then on rank 0 the
        blocks of every rank concatenated in frame order. A :class:`SimulationError` on any
        rank is raised on rank 0 (the workers go on serving); another error ends that
        worker after rank 0 has been told."""
        before = COUNTERS.snapshot()
        local: Tensor | None = None
        error: BaseException | None = None
        status = _OK
        try:
            local = compute()
        except SimulationError as err:
            error, status = err, _SIMULATION_FAILED
        except Exception as err:  # noqa: BLE001  (reported to rank 0, then raised)
            error, status = err, _FAILED
        spent = COUNTERS.snapshot() - before
        mine = torch.tensor([status, spent.factorizations, spent.solves, spent.rhs_columns],
                            dtype=torch.int64)
        everyone = [torch.zeros_like(mine) for _ in range(self.size)]
        dist.all_gather(everyone, mine)
        if self.rank == 0:
            _exchange(False)
            for row in everyone[1:]:
                COUNTERS.factorizations += int(row[1])
                COUNTERS.solves += int(row[2])
                COUNTERS.rhs_columns += int(row[3])
        failed = [(r, int(row[0])) for r, row in enumerate(everyone) if int(row[0]) != _OK]
        if failed:
            if self.rank != 0 and error is not None and status == _FAILED:
                raise error
            if self.rank == 0:
                if error is not None and status == _FAILED:
                    raise error
                worst = max(failed, key=lambda item: item[1])
                if worst[1] == _FAILED:
                    raise RuntimeError(f"rank {worst[0]} of {self.size} failed (its error line "
                                       "is above)")
                if isinstance(error, SimulationError):
                    raise error
                raise SimulationError(f"the simulation of rank {worst[0]}'s frames failed")
            return None
        assert local is not None
        padded = local.new_zeros((self.longest,) + tuple(local.shape[1:]))
        padded[:local.shape[0]] = local.detach()
        if self.rank != 0:
            dist.gather(padded.cpu(), dst=0)
            return None
        parts = [torch.empty_like(padded.cpu()) for _ in range(self.size)]
        _exchange(True)
        dist.gather(padded.cpu(), parts, dst=0)
        _exchange(False)
        pieces = [local] + [parts[r][:stop - start].to(local)
                            for r, (start, stop) in enumerate(self.blocks) if r > 0]
        return torch.cat(pieces, 0)


class _SplitEquilibrium:
    """``quasistatic.equilibrium`` as rank 0's problem sees it: cold blocks, warm-start
    state and its restore reach every rank; anything else is this rank's."""

    def __init__(self, split: "FrameSplit") -> None:
        self._split = split

    def __getattr__(self, name: str) -> Any:
        return getattr(self._split.inner.equilibrium, name)

    @contextlib.contextmanager
    def independent(self) -> Iterator[None]:
        split = self._split
        split.channel.command(INDEPENDENT_ON)
        try:
            with split.inner.equilibrium.independent():
                yield
        finally:
            split.channel.command(INDEPENDENT_OFF)

    def warm_start_state(self) -> dict[str, Any]:
        split = self._split
        split.channel.command(STATE)
        gathered: list[Any] = [None] * split.channel.size
        dist.gather_object(split.inner.equilibrium.warm_start_state(), gathered, dst=0)
        _exchange(False)
        if not any(gathered):
            return {}
        return {"world_size": split.channel.size,
                "blocks": [list(b) for b in split.channel.blocks], "ranks": gathered}

    def restore_warm_start_state(self, state: dict[str, Any], device: Any = None) -> None:
        split = self._split
        if state:
            check_state(state, split.channel.size)
        split.channel.command(RESTORE)
        parts = list(state["ranks"]) if state else [{}] * split.channel.size
        received: list[Any] = [None]
        dist.scatter_object_list(received, parts, src=0)
        _exchange(False)
        split.inner.equilibrium.restore_warm_start_state(received[0], device)


def check_state(state: dict[str, Any], n_ranks: int) -> None:
    saved = int(state.get("world_size", 1))
    if saved != n_ranks:
        raise FitConfigError(f"cannot resume: the checkpoint's warm starts come from {saved} "
                             f"process(es), this run has {n_ranks}; resume with torchrun "
                             f"--nproc_per_node={saved}")


class FrameSplit:
    """A rigged body's ``quasistatic`` whose frames are split over the ranks.

    On rank 0 (the problem the fit uses) a call simulates every frame: it broadcasts the
    command, simulates its own block and gathers the others. :meth:`local` (every rank,
    inside a command) makes calls simulate this rank's block only.
    """

    def __init__(self, problem: Any, channel: _Channel) -> None:
        self.problem = problem
        self.inner = problem.quasistatic
        self.channel = channel
        start, stop = channel.blocks[channel.rank]
        self.frames = slice(start, stop)
        self.equilibrium = _SplitEquilibrium(self)
        self._local = False
        self._forward_jacobian = type(problem).forward_jacobian

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    @contextlib.contextmanager
    def local(self) -> Iterator[None]:
        self._local = True
        try:
            yield
        finally:
            self._local = False

    def _mine(self, value: Tensor | None) -> Tensor | None:
        if value is None:
            return None
        if value.shape[0] != self.problem.n_frames:
            raise RuntimeError(f"a distributed simulation takes all {self.problem.n_frames} "
                               f"frames, got {value.shape[0]}")
        return value[self.frames]

    def __call__(self, E: Tensor, positions: Tensor, x_init: Tensor | None = None) -> Tensor:
        if self._local:
            return self.inner(E, self._mine(positions), x_init=self._mine(x_init))
        self.channel.command(SIMULATE)
        self.channel.share(E, tuple(E.shape), E.dtype)
        with self.local():
            return self.channel.collect(lambda: self(E, positions, x_init))

    def jacobian(self, E: Tensor, positions: Tensor, directions: Tensor,
                 x_init: Tensor | None = None, observe: Tensor | None = None) -> Tensor:
        if not self._local:
            raise NotImplementedError("a distributed rigged body gives its Jacobian through "
                                      "forward_jacobian only")
        return self.inner.jacobian(E, self._mine(positions), directions,
                                   x_init=self._mine(x_init), observe=observe)

    def local_forward_jacobian(self, theta: Tensor) -> Tensor:
        """This rank's rows of ``d forward / d theta``, ``(F_rank, n_obs 3, n)``."""
        with self.local():
            J = self._forward_jacobian(self.problem, theta)
        return J.reshape(self.frames.stop - self.frames.start, -1, J.shape[-1])

    def forward_jacobian(self, theta: Tensor) -> Tensor:
        """Rank 0: every frame's rows, ``(F n_obs 3, n)``, as one process gives them."""
        self.channel.command(JACOBIAN)
        self.channel.share(theta, tuple(theta.shape), theta.dtype)
        J = self.channel.collect(lambda: self.local_forward_jacobian(theta))
        assert J is not None
        return J.reshape(-1, J.shape[-1])


def split_frames(problem: Any) -> FrameSplit:
    """Replace ``problem.quasistatic`` by its frame split (every rank, same problem). Every
    frame is simulated by its rank: frames that repeat a pose are not shared across the
    split (``repeated_poses`` off), so the split sees all ``n_frames``."""
    problem.repeated_poses = None
    blocks = partition(int(problem.n_frames), dist.get_world_size())
    split = FrameSplit(problem, _Channel(blocks))
    problem.quasistatic = split
    if split.channel.rank == 0:
        problem.forward_jacobian = split.forward_jacobian
    return split


def lead(problem: Any, config: dict[str, Any], multirun: bool = False) -> None:
    """Rank 0, after the settings are read: refuse what does not run distributed (one
    line), hand the settings to the workers and split the frames."""
    global _SHARED
    start_group()
    if multirun:
        raise FitConfigError("a sweep (-m) does not run under torchrun; launch one torchrun "
                             "per job")
    check_supported(problem, config, dist.get_world_size())
    dist.broadcast_object_list([config], src=0)
    _SHARED = True
    split_frames(problem)


def stop() -> None:
    """Rank 0 at the end of the run, whatever the end (a refusal, a failure): the workers
    leave :func:`serve`."""
    global _SHARED
    try:
        start_group()
        if _SHARED and not _EXCHANGING:
            _Channel([(0, 0)]).command(STOP)
        else:
            dist.broadcast_object_list([None], src=0)
    except Exception:  # noqa: BLE001  (a worker already gone: torchrun reports it)
        pass
    _SHARED = False
    if dist.is_initialized():
        dist.destroy_process_group()


def serve(build: Callable[[dict[str, Any]], Any]) -> int:
    """A worker (rank > 0): build the problem from rank 0's settings and answer its commands
    until told to stop. Returns the exit status."""
    start_group()
    rank = dist.get_rank()
    logging.basicConfig(level=logging.WARNING, format=f"rank {rank}: %(message)s")
    warnings.simplefilter("ignore")     # rank 0 gives the problem's warnings once
    received: list[Any] = [None]
    dist.broadcast_object_list(received, src=0)
    config = received[0]
    if config is None:          # rank 0 refused the settings or stopped before the fit
        dist.destroy_process_group()
        return 0
    try:
        problem = build(config)
        split = split_frames(problem)
    except Exception as err:  # noqa: BLE001
        print(f"error: rank {rank}: building the problem failed: {err}", file=sys.stderr,
              flush=True)
        return 1
    channel = split.channel
    blocks: list[contextlib.ExitStack] = []
    while True:
        try:
            code = channel.command(0)[0]
        except Exception as err:  # noqa: BLE001  (rank 0 gone)
            print(f"error: rank {rank}: rank 0 stopped answering ({str(err).splitlines()[0]})",
                  file=sys.stderr, flush=True)
            return 1
        if code == STOP:
            dist.destroy_process_group()
            return 0
        try:
            _answer(code, split, blocks)
        except Exception as err:  # noqa: BLE001
            print(f"error: rank {rank}: {str(err).splitlines()[0] if str(err) else err!r}",
                  file=sys.stderr, flush=True)
            return 1


def _answer(code: int, split: FrameSplit, blocks: list[contextlib.ExitStack]) -> None:
    problem, channel = split.problem, split.channel
    if code == SIMULATE:
        n_cells = int(problem.model.n_cells)
        E = channel.share(None, (n_cells,), problem.dtype)
        positions = problem.dirichlet_positions.to(E)
        starts = problem.start_positions.to(E)
        with split.local(), torch.no_grad():
            channel.collect(lambda: split(E, positions, starts))
    elif code == JACOBIAN:
        theta = channel.share(None, (int(problem.parameterization.n_params),), problem.dtype)
        channel.collect(lambda: split.local_forward_jacobian(theta))
    elif code == INDEPENDENT_ON:
        stack = contextlib.ExitStack()
        stack.enter_context(split.inner.equilibrium.independent())
        blocks.append(stack)
    elif code == INDEPENDENT_OFF:
        blocks.pop().close()
    elif code == STATE:
        dist.gather_object(split.inner.equilibrium.warm_start_state(), dst=0)
    elif code == RESTORE:
        received: list[Any] = [None]
        dist.scatter_object_list(received, None, src=0)
        split.inner.equilibrium.restore_warm_start_state(received[0], problem.device)
    else:
        raise RuntimeError(f"unknown command {code} from rank 0")
