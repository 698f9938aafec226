"""One fit over several processes (``torchrun``): the frames of a rigged body split over ranks.

Launched under ``torchrun`` (``WORLD_SIZE > 1``), every process builds the same problem from
the same settings (mesh, rig, data: cheap and identical), then the distinct poses it
simulates (``problems/body/repeated_poses.py``: the arm's 48 frames are 23 poses; every frame where none
repeats) are split by a static balanced partition (:func:`partition`: every ``W``-th pose,
the first ``P mod W`` ranks one more) and each rank simulates only its share:
its Newton solves, factorisations and warm starts stay on it (:class:`FrameSplit`, plugged
into the problem through the seam it declares: ``problem.plug(split, jacobian)``), and a pose that several frames repeat is simulated once in
the whole job.

Leader and workers: rank 0 runs the whole fit (:func:`torchfit.fit`, the solver, every
output: it alone writes the run directory); ranks 1.. only serve (:func:`serve`). Each
simulation the problem asks for on rank 0 (``simulate``, ``forward_jacobian``, a cold
``independent`` block, the warm-start state for a checkpoint or a resume) is broadcast as
a command (the collectives: :mod:`.channel`), every rank computes its frames,
and the positions are gathered to rank 0 in frame order. The Jacobian's rows stay where
they were computed (:mod:`.rows`): rank 0's ``forward_jacobian`` returns a
handle on which the dense path's products run on every rank (``J^T J`` and ``J^T w``
summed in rank order on rank 0, ``J x`` gathered), so no rank holds more than its own
frames' rows (the arm: 110 MB per rank of 2 instead of 220 MB gathered on rank 0). The
iterates are those of one process to round-off (the partial sums; measured:
docs/notes/distributed.md), and bit-reproducible for a given number of processes. What
rank 0 alone runs (pictures, the model comparison's other materials) is unchanged and may
simulate any time: a worker is idle until the next command. Counters of factorisations
and solves of the other ranks are added to rank 0's (the result's totals are the whole
job's).

Checkpoints: rank 0's ``checkpoint.pt`` holds every rank's warm-start state (gathered,
``{"world_size", "blocks", "ranks"}``), scattered back on a resume; a resume must use the
same number of processes (:func:`check_resume`). A worker that dies ends the job: rank 0
tells a lost rank (:func:`stopped_answering`: a broken connection, a collective's timeout, or
a worker process of this host gone when torchrun sends rank 0 its SIGTERM) from other
failures, and ``resume=true`` continues from the last checkpoint. Collectives time out after
``TORCHFIT_DISTRIBUTED_TIMEOUT`` seconds (default 1800: a worker waits while rank 0 writes
pictures or simulates the model comparison alone).

Supported: quasistatic rigged bodies (``problem=arm3d``, ``arm3d_short``, ``animation``)
with Gauss-Newton or Levenberg-Marquardt, on the dense Jacobian (:mod:`.rows`)
or matrix-free (``n_params`` above ``solver.dense_jacobian_max_params``: ``J v`` and
``J^T w`` by autograd through :mod:`.graph`); the rest is refused
(:func:`check_supported`).
"""
from __future__ import annotations

import contextlib
import datetime
import logging
import os
import re
import signal
import socket
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Iterator

import torch
import torch.distributed as dist
from torch import Tensor

from . import graph as distributed_graph
from .channel import (FULL, GRAPH_COMMANDS, INDEPENDENT_OFF, INDEPENDENT_ON,
                                  JACOBIAN, MATVEC, RESTORE, RMATVEC, ROW_COMMANDS, SIMULATE,
                                  STATE, STOP, Channel, exchange, exchanging)
from .rows import DistributedRows, RowStore, local_product
from ...problems import MotionProblem, PosedProblem
from ..options import FitConfigError

#: solvers that run distributed (dense Jacobian or matrix-free)
SOLVERS = ("levenberg_marquardt", "gauss_newton")
_SHARED = False     # rank 0 has handed the settings to the workers (they serve commands)
#: rank 0's: every rank's process ``(host, pid, start time)`` (:func:`identity`), from lead
_PEERS: tuple[Any, ...] = ()
#: what a collective raises when a peer's connection broke or it never answered (gloo)
_LOST = re.compile(r"connection (reset|closed|refused)|closed by peer|broken pipe|timed out|"
                   r"timeout|socket closed|end of file|ECONNRESET|EPIPE", re.IGNORECASE)


def rank() -> int:
    """This process's rank under torchrun (0 outside it)."""
    return int(os.environ.get("RANK", "0"))


def world_size() -> int:
    """The number of processes torchrun started (1 outside torchrun)."""
    return int(os.environ.get("WORLD_SIZE", "1"))


def launched() -> bool:
    """Whether this process is one of several started by torchrun."""
    return world_size() > 1


def partition(n_poses: int, n_ranks: int) -> list[list[int]]:
    """The poses of each rank: every ``n_ranks``-th from its rank (rank ``r``: ``r, r + R,
    ...``); sizes differ by at most one (the first ``n_poses mod n_ranks`` ranks one more); a
    rank may get none.

    Interleaved, not contiguous: neighbouring poses of an animation cost alike (the arm's
    folded poses near full bend lie together), so contiguous blocks gave rank 0 of 2 the
    arm's whole bend: 144 of the cold simulation's 185 Newton iterations at 10k tetrahedra
    and 331 of 373 at 36k (docs/notes/distributed.md)."""
    if n_ranks < 1 or n_poses < 0:
        raise ValueError(f"cannot split {n_poses} poses over {n_ranks} ranks")
    return [list(range(rank, n_poses, n_ranks)) for rank in range(n_ranks)]


def timeout_seconds() -> float:
    return float(os.environ.get("TORCHFIT_DISTRIBUTED_TIMEOUT", "1800"))


def start_group() -> None:
    """The process group (gloo: frames on the CPU) from torchrun's environment."""
    if not dist.is_initialized():
        dist.init_process_group("gloo", timeout=datetime.timedelta(seconds=timeout_seconds()))


def check_supported(problem: Any, config: dict[str, Any], n_ranks: int) -> None:
    """:class:`~.options.FitConfigError` (one line) for what does not run distributed yet."""
    solver = str(config.get("solver", {}).get("name"))
    name = problem.name
    supported = isinstance(problem, PosedProblem) and not isinstance(problem, MotionProblem) \
        and solver in SOLVERS
    if not supported:
        raise FitConfigError(f"problem {name} / solver {solver} does not run distributed yet "
                             f"(torchrun runs a quasistatic rigged body with "
                             f"{' or '.join(SOLVERS)}); run it as one process")
    poses = problem.simulated_poses()
    units = int(problem.n_frames) if isinstance(poses, slice) else len(poses)
    if units < n_ranks:
        raise FitConfigError(f"problem {name} simulates {units} distinct pose(s) "
                             f"({problem.n_frames} frames), fewer than the {n_ranks} "
                             f"processes; start at most --nproc_per_node={units}")
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
        exchange(False)
        if not any(gathered):
            return {}
        return {"world_size": split.channel.size,
                "blocks": [list(b) for b in split.channel.blocks], "ranks": gathered}

    def restore_warm_start_state(self, state: dict[str, Any], device: Any = None) -> None:
        split = self._split
        if state:
            check_state(state, split.channel.blocks)
        split.channel.command(RESTORE)
        parts = list(state["ranks"]) if state else [{}] * split.channel.size
        received: list[Any] = [None]
        dist.scatter_object_list(received, parts, src=0)
        exchange(False)
        split.inner.equilibrium.restore_warm_start_state(received[0], device)


def check_state(state: dict[str, Any], blocks: list[list[int]]) -> None:
    """Refuse warm starts saved by another number of processes, or by the same number with
    the poses shared out otherwise (a checkpoint written before the interleaved
    :func:`partition`: each rank would start its poses from another pose's equilibrium)."""
    saved = int(state.get("world_size", 1))
    if saved != len(blocks):
        raise FitConfigError(f"cannot resume: the checkpoint's warm starts come from {saved} "
                             f"process(es), this run has {len(blocks)}; resume with torchrun "
                             f"--nproc_per_node={saved}")
    if [list(b) for b in state.get("blocks", [])] != [list(b) for b in blocks]:
        raise FitConfigError("cannot resume: the checkpoint's warm starts were saved with the "
                             "poses shared over the ranks in another way (an earlier torchfit "
                             "split them in contiguous blocks); start the fit again")


class FrameSplit:
    """A rigged body's ``quasistatic`` whose frames are split over the ranks.

    On rank 0 (the problem the fit uses) a call simulates every frame: it broadcasts the
    command, simulates its own poses and gathers the others. :meth:`local` (every rank,
    inside a command) makes calls simulate this rank's poses only.
    """

    def __init__(self, problem: Any, channel: Channel) -> None:
        self.problem = problem
        self.inner = problem.quasistatic
        self.channel = channel
        # this rank's simulated poses (indices into them, ascending)
        self.frames = torch.as_tensor(channel.blocks[channel.rank], dtype=torch.int64)
        self.equilibrium = _SplitEquilibrium(self)
        self._local = False
        self.rows = RowStore()
        self.graphs = distributed_graph.GraphStore()
        # rank 0's: the solvers take J v, J^T w by autograd (no dense J), so a simulation
        # with a graph is an autograd node (:mod:`.graph`); else the graph is cut
        self.matrix_free = False
        poses = problem.simulated_poses()
        n_frames = int(problem.n_frames)
        self.poses = torch.arange(n_frames) if isinstance(poses, slice) else poses.cpu()
        self.pose_of_frame = torch.arange(n_frames) if problem.repeated_poses is None \
            else problem.repeated_poses[1].cpu()
        # how many frames each of this rank's poses stands for (J^T J weights its rows)
        self.counts = torch.bincount(self.pose_of_frame, minlength=len(self.poses))[self.frames]

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
        if value.shape[0] != len(self.poses):
            raise RuntimeError(f"a distributed simulation takes all {len(self.poses)} "
                               f"simulated poses, got {value.shape[0]}")
        return value[self.frames]

    def pose_inputs(self, like: Tensor) -> tuple[Tensor, Tensor]:
        """The drive and start positions of every simulated pose (what rank 0 passes)."""
        poses = self.problem.simulated_poses()
        return (self.problem.dirichlet_positions[poses].to(like),
                self.problem.start_positions[poses].to(like))

    def __call__(self, E: Tensor, positions: Tensor, x_init: Tensor | None = None) -> Tensor:
        if self._local:
            return self.inner(E, self._mine(positions), x_init=self._mine(x_init))
        if self.matrix_free and distributed_graph.needs_graph(E):   # products by autograd
            keep = torch.is_grad_enabled() and E.requires_grad
            return distributed_graph.DistributedSimulation.apply(E, self, keep)
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

    def store_jacobian(self, theta: Tensor, ident: int) -> Tensor:
        """Every rank: compute and keep the rows of this rank's poses
        (``(P_rank n_obs 3, n)``) as Jacobian ``ident`` (:class:`.rows.RowStore`);
        returns their shape ``(2,)`` (int64)."""
        with self.local():
            rows = self.problem.pose_jacobian(theta)
        rows = rows.reshape(-1, rows.shape[-1])
        self.rows.add(rows, ident)
        return torch.tensor(rows.shape, dtype=torch.int64)

    def forward_jacobian(self, theta: Tensor) -> DistributedRows:
        """Rank 0: every frame's rows, ``(F n_obs 3, n)``, kept where they were computed
        (:class:`.rows.DistributedRows`: the products the dense path needs)."""
        ident = self.rows.next_id
        self.channel.command(JACOBIAN, ident)
        self.channel.share(theta, tuple(theta.shape), theta.dtype)
        shape = self.channel.run(lambda: self.store_jacobian(theta, ident))
        assert shape is not None
        return DistributedRows(ident, (int(self.problem.data.numel()), int(shape[1])),
                               self.problem.dtype, torch.device("cpu"), self.row_product)

    def per_frame(self) -> int:
        """Rows of one frame (and of one pose): ``n_obs 3``."""
        return int(self.problem.data.numel()) // int(self.problem.n_frames)

    def row_product(self, code: int, ident: int, operand: Tensor | None) -> Tensor:
        """Rank 0: the product ``code`` of Jacobian ``ident`` with ``operand`` on every rank,
        reduced (module :mod:`.rows`). The frames of a repeated pose share its
        rows: ``w`` is summed per pose before ``J^T w``, ``J x`` expanded to every frame."""
        if code == RMATVEC:
            assert operand is not None
            by_frame = operand.reshape((len(self.pose_of_frame), self.per_frame())
                                       + tuple(operand.shape[1:]))
            by_pose = by_frame.new_zeros((len(self.poses),) + tuple(by_frame.shape[1:]))
            by_pose.index_add_(0, self.pose_of_frame.to(by_frame.device), by_frame)
            operand = by_pose.reshape((-1,) + tuple(operand.shape[1:]))
        columns = 0 if operand is None else (1 if operand.dim() == 1 else 1 + operand.shape[1])
        length = 0 if operand is None else operand.shape[0]
        self.channel.command(code, ident, columns, length)
        if operand is not None:
            operand = self.channel.share(operand, tuple(operand.shape), self.problem.dtype)
        out = self.answer_rows(code, ident, operand)
        assert out is not None
        if code in (MATVEC, FULL):          # (P, n_obs 3, ...) -> every frame's rows
            out = out[self.pose_of_frame.to(out.device)]
            out = out.reshape((-1,) + tuple(out.shape[2:]))
        return out

    def answer_rows(self, code: int, ident: int, operand: Tensor | None) -> Tensor | None:
        """Every rank: this rank's part of a row product, gathered by pose (``J x``, the
        rows) or summed (``J^T w``, ``J^T J``: each pose's rows weighted by its frames) on
        rank 0."""
        rows = self.rows.get(ident)
        per_frame = self.per_frame()
        mine = (self.frames[:, None] * per_frame + torch.arange(per_frame)).reshape(-1)
        weights = None if bool((self.counts == 1).all()) else \
            self.counts.to(rows).repeat_interleave(per_frame)

        def part() -> Tensor:
            out = local_product(code, rows, operand, mine, weights)
            if code in (MATVEC, FULL):      # pose-major, for the gather in pose order
                return out.reshape((len(self.frames), per_frame)
                                   + tuple(out.shape[1:]))
            return out

        if code in (MATVEC, FULL):
            return self.channel.collect(part)
        return self.channel.total(part)


def split_frames(problem: PosedProblem) -> FrameSplit:
    """Plug the split of the problem's pose simulation into it (every rank, same problem;
    :meth:`~torchfit.problems.PosedProblem.plug`): the distinct poses the problem simulates
    (every frame where none repeats) are partitioned over the ranks, so a pose that several
    frames repeat is simulated once in the whole job; rank 0's Jacobian rows stay on their
    ranks (:meth:`FrameSplit.forward_jacobian`)."""
    poses = problem.simulated_poses()
    count = int(problem.n_frames) if isinstance(poses, slice) else len(poses)
    blocks = partition(count, dist.get_world_size())
    split = FrameSplit(problem, Channel(blocks))
    problem.plug(split, split.forward_jacobian if split.channel.rank == 0 else None)
    return split


def lead(problem: Any, config: dict[str, Any], multirun: bool = False) -> None:
    """Rank 0, after the settings are read: refuse what does not run distributed (one
    line), hand the settings to the workers and split the frames."""
    global _SHARED, _PEERS
    start_group()
    if multirun:
        raise FitConfigError("a sweep (-m) does not run under torchrun; launch one torchrun "
                             "per job")
    check_supported(problem, config, dist.get_world_size())
    dist.broadcast_object_list([config], src=0)
    _SHARED = True
    peers: list[Any] = [None] * dist.get_world_size()
    dist.gather_object(identity(), peers, dst=0)        # to tell a rank that died
    _PEERS = tuple(peers)
    digests: list[Any] = [None] * dist.get_world_size()
    dist.gather_object(problem.input_digests(), digests, dst=0)
    check_same_inputs(problem.input_digests(), digests)
    split = split_frames(problem)
    solver = config.get("solver", {})
    split.matrix_free = not 0 < int(problem.parameterization.n_params) <= \
        int(solver.get("dense_jacobian_max_params", 0))


def identity() -> tuple[str, int, str]:
    """This process: ``(host, pid, start time)`` (the start time in clock ticks after boot,
    from ``/proc``; ``''`` where there is none), so that a reused pid is not taken for it."""
    return socket.gethostname(), os.getpid(), _start_time(os.getpid()) or ""


def _start_time(pid: int) -> str | None:
    """The start time of process ``pid`` (``/proc/<pid>/stat`` field 22), ``None`` if it is
    gone or a zombie (killed, not yet reaped by torchrun)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2:].split()      # after the command name
    return None if fields[0] in ("Z", "X") else fields[19]


def _gone(peer: Any) -> bool:
    """Whether a rank's process (:func:`identity`) is known to be gone: only a process of
    this host can be looked at; one elsewhere counts as running."""
    host, pid, started = peer
    if host != socket.gethostname():
        return False
    if not Path("/proc/self/stat").exists():       # no /proc: the pid alone
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        except OSError:
            pass
        return False
    now = _start_time(pid)
    return now is None or bool(started) and now != started


def communication_failure(error: BaseException) -> bool:
    """Whether ``error`` (or what it was raised from) is a collective that lost its peer: a
    connection reset or closed, a broken pipe, a timeout (gloo raises ``RuntimeError`` or
    ``torch.distributed.DistError`` with these words)."""
    while error is not None:
        if isinstance(error, RuntimeError) and _LOST.search(str(error)):
            return True
        error = error.__cause__ or error.__context__
    return False


def stopped_answering(error: BaseException | None, wait: float = 1.0) -> str | None:
    """Rank 0: ``"rank k of W"`` (or ``"a rank of W"`` where it cannot tell which) when the
    run ended because a worker stopped answering, else ``None``.

    ``error`` is what the fit raised: a :func:`communication_failure` is a lost rank (the
    rank whose process of this host is gone, waiting up to ``wait`` s for the kernel to
    mark it; with 2 ranks it is rank 1). ``None`` stands for torchrun's SIGTERM: it is a
    lost rank only where a worker's process of this host is already gone (torchrun stops
    rank 0 once another rank died; a job cancelled as a whole signals every rank, and the
    workers outlive rank 0: :func:`serve` ignores SIGTERM)."""
    size = world_size()
    if size < 2 or rank() != 0:
        return None
    peers = list(enumerate(_PEERS))[1:]
    lost = error is not None and communication_failure(error)
    if error is not None and not lost:
        return None
    deadline = time.monotonic() + (wait if lost else 0.0)
    while True:
        gone = [r for r, peer in peers if peer is not None and _gone(peer)]
        if gone:
            return f"rank {gone[0]} of {size}"
        if time.monotonic() >= deadline:
            break
        time.sleep(0.05)
    if not lost:
        return None
    return f"rank 1 of {size}" if size == 2 else f"a rank of {size}"


def check_same_inputs(mine: dict[str, str], ranks: list[Any]) -> None:
    """Every rank built its problem on the same inputs (the tet mesh, the animation: their
    digests) as rank 0, or one line naming the first rank and input that differ (a worker
    on another node whose cache entry is missing tetrahedralises the surface again, and
    pytetwild's mesh differs from run to run)."""
    for rank, theirs in enumerate(ranks):
        if theirs is None or theirs == mine:
            continue
        differs = sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))
        raise FitConfigError(f"rank {rank} built its problem on another {', '.join(differs)} "
                             "than rank 0; give every rank the same inputs (problem.cache_dir "
                             "on a disk every node reads, or resume where the run directory's "
                             "mesh.npz is readable by every rank)")


def abandon() -> None:
    """Rank 0, once a rank stopped answering: :func:`stop` sends nothing and leaves the
    group as it is (a collective with a lost peer fails or waits; torchrun ends the others,
    which leave quietly after its SIGTERM)."""
    global _ABANDONED
    _ABANDONED = True


_ABANDONED = False


def stop() -> None:
    """Rank 0 at the end of the run, whatever the end (a refusal, a failure): the workers
    leave :func:`serve`."""
    global _SHARED
    if _ABANDONED:
        return
    try:
        start_group()
        if not _SHARED:                 # the workers wait for the settings
            dist.broadcast_object_list([None], src=0)
        elif not exchanging():          # they wait for a command (in an exchange: nothing
            Channel([[]]).command(STOP)     # they would understand; they leave once rank 0
                                            # has gone, after SIGTERM quietly)
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
    for name in ("torchfit.mesh", "torchfit.problems"):    # (they are log records)
        logging.getLogger(name).setLevel(logging.ERROR)
    received: list[Any] = [None]
    dist.broadcast_object_list(received, src=0)
    config = received[0]
    if config is None:          # rank 0 refused the settings or stopped before the fit
        dist.destroy_process_group()
        return 0
    # a cancelled job signals every rank: the workers outlive rank 0, which tells this from
    # a worker that died (:func:`stopped_answering`), says so and stops them
    signal.signal(signal.SIGTERM, _note_terminated)
    try:
        dist.gather_object(identity(), dst=0)
        try:
            problem = build(config)
        except Exception as err:  # noqa: BLE001
            if _TERMINATED:
                return 143
            print(f"error: rank {rank}: building the problem failed: {err}", file=sys.stderr,
                  flush=True)
            return 1
        dist.gather_object(problem.input_digests(), dst=0)       # rank 0 compares them
        split = split_frames(problem)
    except Exception:  # noqa: BLE001  (rank 0 gone after SIGTERM: it said so)
        if _TERMINATED:
            return 143
        raise
    channel = split.channel
    blocks: list[contextlib.ExitStack] = []
    while True:
        try:
            header = channel.command(0)
            code = header[0]
        except Exception as err:  # noqa: BLE001  (rank 0 gone)
            if _TERMINATED:     # the job was cancelled: rank 0 said so
                return 143
            print(f"error: rank {rank}: rank 0 stopped answering ({str(err).splitlines()[0]})",
                  file=sys.stderr, flush=True)
            return 1
        if code == STOP:
            dist.destroy_process_group()
            return 0
        try:
            _answer(header, split, blocks)
        except Exception as err:  # noqa: BLE001
            if _TERMINATED:
                return 143
            print(f"error: rank {rank}: {str(err).splitlines()[0] if str(err) else err!r}",
                  file=sys.stderr, flush=True)
            return 1


_TERMINATED = False     # a worker's: SIGTERM came (the whole job is being stopped)


def _note_terminated(signum: int, frame: Any) -> None:
    global _TERMINATED
    _TERMINATED = True


def _answer(header: list[int], split: FrameSplit, blocks: list[contextlib.ExitStack]) -> None:
    problem, channel = split.problem, split.channel
    code = header[0]
    if code == SIMULATE:
        n_cells = int(problem.model.n_cells)
        E = channel.share(None, (n_cells,), problem.dtype)
        positions, starts = split.pose_inputs(E)
        with split.local(), torch.no_grad():
            channel.collect(lambda: split(E, positions, starts))
    elif code == JACOBIAN:
        theta = channel.share(None, (int(problem.parameterization.n_params),), problem.dtype)
        channel.run(lambda: split.store_jacobian(theta, header[1]))
    elif code in GRAPH_COMMANDS:
        distributed_graph.answer(header, split)
    elif code in ROW_COMMANDS:
        _, ident, columns, length = header
        operand = None if columns == 0 else channel.share(
            None, (length,) if columns == 1 else (length, columns - 1), problem.dtype)
        split.answer_rows(code, ident, operand)
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
