"""One process's part in a distributed fit: the leader's and each worker's lifecycle.

Launched under ``torchrun`` (``WORLD_SIZE > 1``), every process makes a
:class:`DistributedSession` and builds the same problem from the same settings (mesh, rig,
data: cheap and identical). Rank 0 leads (:meth:`DistributedSession.lead`): it runs the
whole fit (:func:`torchfit.fit`, the solver, every output: it alone writes the run
directory); ranks 1.. only serve (:meth:`DistributedSession.serve`): the problem's poses
are split over the ranks (:mod:`.split`), and each simulation the problem asks for on rank
0 (``simulate``, ``forward_jacobian``, a cold ``independent`` block, the warm-start state
for a checkpoint or a resume) is a command every rank answers (:mod:`.channel`) with its
poses. The iterates are those of one process to round-off (the partial sums; measured:
docs/notes/distributed.md), and bit-reproducible for a given number of processes. What rank
0 alone runs (pictures, the model comparison's other materials) may simulate any time: a
worker is idle until the next command. Counters of factorisations and solves of the other
ranks are added to rank 0's (the result's totals are the whole job's).

The session holds what the run is in: the peers' processes (rank 0's, to tell a rank that
died: :mod:`.liveness`), whether rank 0 has handed the settings to the workers, whether it
abandoned them (a rank stopped answering), whether a worker was sent SIGTERM, and the
channel once the poses are split. Outside torchrun the session is inert (one process:
:meth:`~DistributedSession.stopped_answering` says ``None``, :meth:`~DistributedSession.
stop` does nothing).

Checkpoints: rank 0's ``checkpoint.pt`` holds every rank's warm-start state (gathered,
``{"world_size", "blocks", "ranks"}``), scattered back on a resume; a resume must use the
same number of processes (:func:`.refusals.check_resume`). A worker that dies ends the job:
rank 0 tells a lost rank from other failures (:meth:`~DistributedSession.
stopped_answering`), and ``resume=true`` continues from the last checkpoint.

Supported: quasistatic rigged bodies (``problem=arm3d``, ``arm3d_short``, ``animation``)
with Gauss-Newton or Levenberg-Marquardt, on the dense Jacobian (:mod:`.rows`) or
matrix-free (``n_params`` above ``solver.dense_jacobian_max_params``: ``J v`` and ``J^T w``
by autograd through :mod:`.graph`); the rest is refused in one line (:mod:`.refusals`).
"""
from __future__ import annotations

import logging
import signal
import sys
import warnings
from pathlib import Path
from typing import Any, Callable

import torch.distributed as dist

from . import environment
from .channel import STOP, Channel
from .liveness import communication_failure, identity, lost_rank
from .refusals import check_same_inputs, check_single_job, check_supported
from .split import FrameSplit, partition, plug_split

#: a worker's exit status once SIGTERM came (the job is being stopped as a whole)
TERMINATED_STATUS = 143
#: a worker's exit status once rank 0 stopped answering (rank 0's for a lost worker: 3)
LEADER_LOST_STATUS = 3


class DistributedSession:
    """This process's part in a distributed fit, made by every process of the job.

    Rank 0 leads (:meth:`lead`), stops the workers at the end (:meth:`stop`) and, once a
    rank is lost, abandons them (:meth:`abandon`); each worker serves (:meth:`serve`). The
    lifecycle and what the session holds: the module docstring. ``rank`` and ``size``
    default to torchrun's environment (:mod:`.environment`)."""

    def __init__(self, rank: int | None = None, size: int | None = None) -> None:
        self.rank = environment.rank() if rank is None else int(rank)
        self.size = environment.world_size() if size is None else int(size)
        #: rank 0's: every rank's process ``(host, pid, start time)``, in rank order
        #: (:func:`.liveness.identity`), gathered when it leads
        self.peers: tuple[Any, ...] = ()
        #: rank 0's: the settings went to the workers (they wait for commands, not for them)
        self.shared = False
        #: rank 0's: a rank stopped answering, so :meth:`stop` sends nothing
        self.abandoned = False
        #: a worker's: SIGTERM came (the whole job is being stopped; rank 0 says so)
        self.terminated = False
        #: the collectives, once the poses are split (every rank)
        self.channel: Channel | None = None
        #: the problem's split pose simulation, once plugged in (every rank)
        self.split: FrameSplit | None = None

    @property
    def launched(self) -> bool:
        """Whether this process is one of several (under torchrun)."""
        return self.size > 1

    # -- the leader ------------------------------------------------------------------------
    def lead(self, problem: Any, config: dict[str, Any], multirun: bool = False) -> None:
        """Rank 0, after the settings are read: refuse what does not run distributed (one
        line, :mod:`.refusals`), hand the settings to the workers, learn their processes,
        check that they built on the same inputs, and split the poses."""
        environment.start_group()
        check_single_job(multirun)
        check_supported(problem, config, dist.get_world_size())
        dist.broadcast_object_list([config], src=0)
        self.shared = True
        peers: list[Any] = [None] * dist.get_world_size()
        dist.gather_object(identity(), peers, dst=0)        # to tell a rank that died
        self.peers = tuple(peers)
        digests: list[Any] = [None] * dist.get_world_size()
        dist.gather_object(problem.input_digests(), digests, dst=0)
        check_same_inputs(problem.input_digests(), digests)
        split = self._split(problem)
        solver = config.get("solver", {})
        split.matrix_free = not 0 < int(problem.parameterization.n_params) <= \
            int(solver.get("dense_jacobian_max_params", 0))

    def stopped_answering(self, error: BaseException | None, wait: float = 1.0) -> str | None:
        """Rank 0: ``"rank k of W"`` (or ``"a rank of W"``) when the run ended because a
        worker stopped answering, else ``None`` (:func:`.liveness.lost_rank`: ``error`` is
        what the fit raised, ``None`` torchrun's SIGTERM); ``None`` on a worker and outside
        torchrun."""
        if self.size < 2 or self.rank != 0:
            return None
        return lost_rank(self.peers, self.size, error, wait)

    def abandon(self) -> None:
        """Rank 0, once a rank stopped answering: :meth:`stop` sends nothing and leaves the
        group as it is (a collective with a lost peer fails or waits; torchrun ends the
        others, which leave quietly after its SIGTERM)."""
        self.abandoned = True

    def stop(self) -> None:
        """Rank 0 at the end of the run, whatever the end (a refusal, a failure): the workers
        leave :meth:`serve`. Nothing outside torchrun or once abandoned."""
        if not self.launched or self.abandoned:
            return
        try:
            environment.start_group()
            if not self.shared:             # the workers wait for the settings
                dist.broadcast_object_list([None], src=0)
            elif self.channel is None:      # they wait for their first command
                Channel([[] for _ in range(dist.get_world_size())]).command(STOP)
            elif not self.channel.exchanging:   # they wait for a command (in an exchange:
                self.channel.command(STOP)      # nothing they would understand; they leave
                                                # once rank 0 has gone, after SIGTERM quietly)
        except Exception:  # noqa: BLE001  (a worker already gone: torchrun reports it)
            pass
        self.shared = False
        if dist.is_initialized():
            dist.destroy_process_group()

    # -- a worker --------------------------------------------------------------------------
    def serve(self, build: Callable[[dict[str, Any]], Any],
              resume_command: Callable[[Path], str] | None = None) -> int:
        """A worker (rank > 0): build the problem from rank 0's settings and answer its
        commands until told to stop. Returns the exit status: 0 (stopped, or rank 0
        refused the settings), 1 (this rank failed; one ``error:`` line),
        :data:`LEADER_LOST_STATUS` (rank 0 stopped answering: one ``error:`` line that says
        nothing is lost and, given ``resume_command`` (the run directory -> the command that
        continues it), how to continue), 143 (SIGTERM: the job was cancelled)."""
        environment.start_group()
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
        # a cancelled job signals every rank: the workers outlive rank 0, which tells this
        # from a worker that died (:meth:`stopped_answering`), says so and stops them
        signal.signal(signal.SIGTERM, self._note_terminated)
        try:
            dist.gather_object(identity(), dst=0)
            try:
                problem = build(config)
            except Exception as err:  # noqa: BLE001
                if self.terminated:
                    return TERMINATED_STATUS
                print(f"error: rank {rank}: building the problem failed: {err}",
                      file=sys.stderr, flush=True)
                return 1
            dist.gather_object(problem.input_digests(), dst=0)       # rank 0 compares them
            split = self._split(problem)
        except Exception:  # noqa: BLE001  (rank 0 gone after SIGTERM: it said so)
            if self.terminated:
                return TERMINATED_STATUS
            raise
        channel = split.channel
        while True:
            waiting = True
            try:
                header = channel.command(0)
                if header[0] == STOP:
                    dist.destroy_process_group()
                    return 0
                waiting = False
                split.answer(header)
            except Exception as err:  # noqa: BLE001  (rank 0 gone, or this rank failed)
                return self._worker_failed(rank, err, waiting, config, resume_command)

    def _worker_failed(self, rank: int, error: Exception, waiting: bool, config: dict[str, Any],
                       resume_command: Callable[[Path], str] | None) -> int:
        """A worker's one line and exit status for ``error`` (:meth:`serve`): quiet after the
        job's SIGTERM (rank 0 said it); rank 0 gone (``waiting`` for its command, or a
        collective inside an answer that lost its peer): that, and the resume command; else
        this rank's own failure. gloo's message (a socket reset, a timeout) says nothing a
        TD can use."""
        if self.terminated:
            return TERMINATED_STATUS
        if waiting or communication_failure(error):
            run_dir = config.get("run_dir")
            resume = f"; nothing of the run is lost: continue with: " \
                f"{resume_command(Path(run_dir))}" if resume_command and run_dir else ""
            print(f"error: rank {rank}: rank 0 stopped answering (killed, or its machine went "
                  f"away){resume}", file=sys.stderr, flush=True)
            return LEADER_LOST_STATUS
        print(f"error: rank {rank}: {str(error).splitlines()[0] if str(error) else error!r}",
              file=sys.stderr, flush=True)
        return 1

    def _note_terminated(self, signum: int, frame: Any) -> None:
        self.terminated = True

    # -- every rank ------------------------------------------------------------------------
    def _split(self, problem: Any) -> FrameSplit:
        """The problem's distinct poses partitioned over the ranks (every rank, the same
        problem), the channel with that partition, and the split plugged into the problem."""
        poses = problem.poses.simulated_poses()
        count = int(problem.n_frames) if isinstance(poses, slice) else len(poses)
        self.channel = Channel(partition(count, dist.get_world_size()))
        self.split = plug_split(problem, self.channel)
        return self.split
