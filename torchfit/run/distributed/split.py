"""A rigged body's pose simulation split over the ranks: the partition and the split simulation.

Every rank builds the same problem; the distinct poses it simulates
(``problems/body/repeated_poses.py``: the arm's 48 frames are 23 poses; every frame where
none repeats) are dealt to the ranks by :func:`partition`, and each rank simulates only its
share: its Newton solves, factorisations and warm starts stay on it. :class:`FrameSplit`
is the problem's pose simulation from then on (:func:`plug_split`, the one call of the
body's simulation's seam ``problem.poses.plug(simulation, jacobian)``). It defines every member of the pose
simulation interface that seam declares (``PoseSimulation``; its warm starts,
:class:`SplitEquilibrium`, every member of ``PoseEquilibrium``) as a method of its own,
nothing forwarded; :func:`plug_split` checks them against the seam's declaration before it
plugs (:func:`check_implements`), so a missing member stops every rank at the split, not a
worker in the middle of a fit.

On rank 0 (the problem the fit uses) a call is a command to every rank (:mod:`.channel`):
each computes its poses and the positions are gathered to rank 0 in pose order; the
Jacobian's rows stay where they were computed (:mod:`.rows`, :meth:`FrameSplit.
forward_jacobian`), and with many parameters the simulation is an autograd node whose
products run on every rank (:mod:`.graph`). A worker answers each command with the same
object (:meth:`FrameSplit.answer`), inside :meth:`FrameSplit.local`, where a call
simulates this rank's poses only.
"""
from __future__ import annotations

import contextlib
import typing
from typing import Any, Callable, Iterator

import torch
from torch import Tensor

from . import graph as distributed_graph
from .channel import (CLEAR, FULL, GRAPH_COMMANDS, INDEPENDENT_OFF, INDEPENDENT_ON, JACOBIAN,
                      MATVEC, RESTORE, RMATVEC, ROW_COMMANDS, SIMULATE, STATE, Channel)
from .refusals import check_state
from .rows import DistributedRows, RowStore, local_product
from ...problems import PosedProblem


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


def protocol_members(protocol: type) -> set[str]:
    """The members a protocol class declares: its annotated attributes and its methods
    (``__call__`` the one special method counted)."""
    names = set(vars(protocol).get("__annotations__", {}))
    names |= {name for name, value in vars(protocol).items()
              if callable(value) or isinstance(value, property)}
    return {name for name in names if not name.startswith("_") or name == "__call__"}


def unimplemented(cls: type, protocol: type) -> list[str]:
    """The members of ``protocol`` that ``cls`` neither defines nor declares (an annotated
    attribute set by its constructor counts as declared), sorted."""
    declared = {name for klass in cls.__mro__ for name in vars(klass).get("__annotations__", {})}
    return sorted(name for name in protocol_members(protocol)
                  if name not in declared and not hasattr(cls, name))


def check_implements(cls: type, protocol: type) -> None:
    """``TypeError`` naming the members of ``protocol`` that ``cls`` lacks
    (:func:`unimplemented`); nothing where it has them all."""
    missing = unimplemented(cls, protocol)
    if missing:
        raise TypeError(f"{cls.__name__} does not implement {protocol.__name__}: it lacks "
                        f"{', '.join(missing)}")


def seam_interface(plug: Callable[..., Any]) -> type:
    """The pose simulation interface a problem's seam declares: the class its ``plug``
    annotates ``simulation`` with (a rigged body's: the ``PoseSimulation`` protocol)."""
    return typing.get_type_hints(plug)["simulation"]


class SplitEquilibrium:
    """The warm starts of a split simulation as rank 0's problem sees them: a cold block,
    the warm-start state, its restore and dropping the cached solutions reach every rank
    (a command each); ``own`` is this rank's equilibrium."""

    def __init__(self, channel: Channel, own: Any) -> None:
        self.channel = channel
        self.own = own

    @contextlib.contextmanager
    def independent(self) -> Iterator[None]:
        """Cold starts on every rank that seed no warm start (between two commands)."""
        self.channel.command(INDEPENDENT_ON)
        try:
            with self.own.independent():
                yield
        finally:
            self.channel.command(INDEPENDENT_OFF)

    def warm_start_state(self) -> dict[str, Any]:
        """Every rank's warm starts, ``{"world_size", "blocks", "ranks"}`` (``{}`` where no
        rank has any: a linear model)."""
        self.channel.command(STATE)
        gathered = self.channel.gather_object(self.own.warm_start_state())
        assert gathered is not None
        if not any(gathered):
            return {}
        return {"world_size": self.channel.size,
                "blocks": [list(b) for b in self.channel.blocks], "ranks": gathered}

    def restore_warm_start_state(self, state: dict[str, Any], device: Any = None) -> None:
        """Each rank's part of ``state`` (:meth:`warm_start_state`) restored on it; state
        saved by another number of ranks, or with the poses shared out otherwise, is
        refused (:func:`.refusals.check_state`)."""
        if state:
            check_state(state, self.channel.blocks)
        self.channel.command(RESTORE)
        parts = list(state["ranks"]) if state else [{}] * self.channel.size
        self.own.restore_warm_start_state(self.channel.scatter_object(parts), device)

    def clear_cache(self) -> None:
        """Drop every rank's cached solutions (the next simulation is cold everywhere)."""
        self.channel.command(CLEAR)
        self.own.clear_cache()


class FrameSplit:
    """A rigged body's pose simulation whose poses are split over the ranks.

    On rank 0 (the problem the fit uses) a call simulates every pose: it broadcasts the
    command, simulates its own poses and gathers the others. :meth:`local` (every rank,
    inside a command) makes calls simulate this rank's poses only; :meth:`answer` is a
    worker's side of each command.
    """

    #: the warm starts, every rank's (:class:`SplitEquilibrium`)
    equilibrium: SplitEquilibrium

    def __init__(self, problem: Any, channel: Channel) -> None:
        """``problem``: this rank's, before the split is plugged in (its
        ``poses.quasistatic`` is this process's own simulation); ``channel``: the collectives, with every rank's
        poses (:func:`partition`)."""
        self.problem = problem
        #: this rank's own simulation of its poses
        self.own = problem.poses.quasistatic
        self.channel = channel
        # this rank's simulated poses (indices into them, ascending)
        self.frames = torch.as_tensor(channel.blocks[channel.rank], dtype=torch.int64)
        self.equilibrium = SplitEquilibrium(channel, self.own.equilibrium)
        self._local = False
        self.rows = RowStore()
        self.graphs = distributed_graph.GraphStore()
        # rank 0's: the solvers take J v, J^T w by autograd (no dense J), so a simulation
        # with a graph is an autograd node (:mod:`.graph`); else the graph is cut
        self.matrix_free = False
        # a worker's: the cold blocks rank 0 opened (INDEPENDENT_ON), innermost last
        self._cold_blocks: list[contextlib.ExitStack] = []
        poses = problem.poses.simulated_poses()
        n_frames = int(problem.n_frames)
        self.poses = torch.arange(n_frames) if isinstance(poses, slice) else poses.cpu()
        repeated = problem.poses.repeated_poses
        self.pose_of_frame = torch.arange(n_frames) if repeated is None else repeated[1].cpu()
        # how many frames each of this rank's poses stands for (J^T J weights its rows)
        self.counts = torch.bincount(self.pose_of_frame, minlength=len(self.poses))[self.frames]

    # -- the pose simulation interface ---------------------------------------------------
    def __call__(self, E: Tensor, positions: Tensor, x_init: Tensor | None = None) -> Tensor:
        """Positions ``(P, n, 3)`` of every simulated pose (rank 0; :meth:`local`: this
        rank's poses); ``positions`` and ``x_init`` are every pose's."""
        if self._local:
            return self.own(E, self._mine(positions), x_init=self._mine(x_init))
        if self.matrix_free and distributed_graph.needs_graph(E):   # products by autograd
            keep = torch.is_grad_enabled() and E.requires_grad
            return distributed_graph.DistributedSimulation.apply(E, self, keep)
        self.channel.command(SIMULATE)
        self.channel.share(E, tuple(E.shape), E.dtype)
        with self.local():
            return self.channel.collect(lambda: self(E, positions, x_init))

    def jacobian(self, E: Tensor, positions: Tensor, directions: Tensor,
                 x_init: Tensor | None = None, observe: Tensor | None = None) -> Tensor:
        """Inside :meth:`local` only: this rank's poses' derivatives ``(P_rank, rows, k)``
        along ``directions`` (rank 0's problem takes its Jacobian from
        :meth:`forward_jacobian`, whose rows stay on the ranks)."""
        if not self._local:
            raise NotImplementedError("a distributed rigged body gives its Jacobian through "
                                      "forward_jacobian only")
        return self.own.jacobian(E, self._mine(positions), directions,
                                 x_init=self._mine(x_init), observe=observe)

    @property
    def last_newton_iterations(self) -> list[int]:
        """Newton iterations of this rank's poses in its last simulation."""
        return self.own.last_newton_iterations

    # -- this rank's poses ---------------------------------------------------------------
    @contextlib.contextmanager
    def local(self) -> Iterator[None]:
        """Calls inside simulate this rank's poses only (its part of a command)."""
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
        poses = self.problem.poses.simulated_poses()
        return (self.problem.dirichlet_positions[poses].to(like),
                self.problem.start_positions[poses].to(like))

    # -- the Jacobian's rows, kept on their ranks ----------------------------------------
    def store_jacobian(self, theta: Tensor, ident: int) -> Tensor:
        """Every rank: compute and keep the rows of this rank's poses
        (``(P_rank n_obs 3, n)``) as Jacobian ``ident`` (:class:`.rows.RowStore`);
        returns their shape ``(2,)`` (int64)."""
        with self.local():
            rows = self.problem.poses.pose_jacobian(theta, self.problem.parameterization,
                                                    self.problem.observation.matrix)
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

    # -- a worker's side of every command ------------------------------------------------
    def answer(self, header: list[int]) -> None:
        """A worker: this rank's part of rank 0's command ``header`` (the code and its
        values, :meth:`.channel.Channel.command`); ``RuntimeError`` for a code it does not
        know."""
        problem, channel = self.problem, self.channel
        code = header[0]
        if code == SIMULATE:
            n_cells = int(problem.model.n_cells)
            E = channel.share(None, (n_cells,), problem.dtype)
            positions, starts = self.pose_inputs(E)
            with self.local(), torch.no_grad():
                channel.collect(lambda: self(E, positions, starts))
        elif code == JACOBIAN:
            theta = channel.share(None, (int(problem.parameterization.n_params),),
                                  problem.dtype)
            channel.run(lambda: self.store_jacobian(theta, header[1]))
        elif code in GRAPH_COMMANDS:
            distributed_graph.answer(header, self)
        elif code in ROW_COMMANDS:
            _, ident, columns, length = header
            operand = None if columns == 0 else channel.share(
                None, (length,) if columns == 1 else (length, columns - 1), problem.dtype)
            self.answer_rows(code, ident, operand)
        elif code == INDEPENDENT_ON:
            stack = contextlib.ExitStack()
            stack.enter_context(self.own.equilibrium.independent())
            self._cold_blocks.append(stack)
        elif code == INDEPENDENT_OFF:
            self._cold_blocks.pop().close()
        elif code == STATE:
            channel.gather_object(self.own.equilibrium.warm_start_state())
        elif code == RESTORE:
            self.own.equilibrium.restore_warm_start_state(channel.scatter_object(None),
                                                          problem.device)
        elif code == CLEAR:
            self.own.equilibrium.clear_cache()
        else:
            raise RuntimeError(f"unknown command {code} from rank 0")


def plug_split(problem: PosedProblem, channel: Channel) -> FrameSplit:
    """Plug the split of the problem's pose simulation into it (every rank, same problem,
    ``channel`` with :func:`partition`'s blocks of its poses): the one call of the body's
    simulation's seam (:meth:`~torchfit.problems.body.poses.FramePoses.plug`). Rank 0's
    Jacobian rows stay on their ranks (:meth:`FrameSplit.forward_jacobian`). ``TypeError`` before anything is
    plugged where the split lacks a member of the interface the seam declares, or its
    equilibrium one of the interface's ``equilibrium``."""
    interface = seam_interface(problem.poses.plug)
    check_implements(FrameSplit, interface)
    check_implements(SplitEquilibrium, typing.get_type_hints(interface)["equilibrium"])
    split = FrameSplit(problem, channel)
    problem.poses.plug(split, split.forward_jacobian if channel.rank == 0 else None)
    return split
