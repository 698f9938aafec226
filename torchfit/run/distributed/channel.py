"""The collectives of a distributed fit (:mod:`.session`): rank 0 commands, every rank answers.

A command is a broadcast header of four int64 (the code and up to three values). An answer
is this rank's part, computed under :meth:`Channel.run`, which tells every rank how each
part went (a :class:`~torchfit.errors.SimulationError` anywhere is raised on rank 0 as a
failed simulation; another error ends the rank that had it) and adds the workers'
factorisation and solve counts to rank 0's; :meth:`Channel.collect` then gathers frame
blocks to rank 0 in frame order, :meth:`Channel.total` sums equal-shaped parts there in
rank order, :meth:`Channel.gather_object` and :meth:`Channel.scatter_object` move the
warm-start state. :attr:`Channel.exchanging` says whether rank 0 is inside an exchange
(stopped there, it must not send the workers a stop: they wait in the same exchange).
"""
from __future__ import annotations

from typing import Any, Callable

import torch
import torch.distributed as dist
from torch import Tensor

from ...errors import SimulationError
from ...linalg import SolveCounters, counting, credit

#: the commands: simulate / Jacobian / cold block on, off / warm-start state / restore / stop
#: / drop the cached solutions
SIMULATE, JACOBIAN, INDEPENDENT_ON, INDEPENDENT_OFF, STATE, RESTORE, STOP, CLEAR = range(8)
#: products with a Jacobian kept on the ranks (:mod:`.rows`)
MATVEC, RMATVEC, GRAM, FULL = 20, 21, 22, 23
ROW_COMMANDS = (MATVEC, RMATVEC, GRAM, FULL)
#: a simulation autograd differentiates, its backward and jvp (:mod:`.graph`)
SIMULATE_GRAPH, GRAPH_VJP, GRAPH_JVP = 30, 31, 32
GRAPH_COMMANDS = (SIMULATE_GRAPH, GRAPH_VJP, GRAPH_JVP)
#: codes whose answer is an exchange (every rank computes, rank 0 receives)
COMMANDS_WITH_EXCHANGE = (SIMULATE, JACOBIAN, STATE, RESTORE) + ROW_COMMANDS + GRAPH_COMMANDS
_OK, _SIMULATION_FAILED, _FAILED = 0, 1, 2


class Channel:
    """The collectives of the protocol (rank 0 commands, every rank answers)."""

    def __init__(self, blocks: list[list[int]]) -> None:
        """``blocks``: per rank, the indices of its frames (poses) in the whole."""
        self.rank, self.size = dist.get_rank(), dist.get_world_size()
        self.blocks = blocks
        self.longest = max(len(block) for block in blocks)
        #: rank 0's: a command with an answer was sent and the answer is not all in yet
        self.exchanging = False

    def command(self, code: int, *values: int) -> list[int]:
        header = torch.zeros(4, dtype=torch.int64)
        if self.rank == 0 and code in COMMANDS_WITH_EXCHANGE:
            self.exchanging = True
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

    def run(self, compute: Callable[[], Tensor]) -> Tensor | None:
        """Run ``compute`` (this rank's part) and tell every rank how it went. A
        :class:`SimulationError` on any rank is raised on rank 0 (the workers go on
        serving); another error ends that worker after rank 0 has been told. Returns the
        local result, or ``None`` on a worker where some rank failed."""
        local: Tensor | None = None
        error: BaseException | None = None
        status = _OK
        try:
            with counting() as spent:
                local = compute()
        except SimulationError as err:
            error, status = err, _SIMULATION_FAILED
        except Exception as err:  # noqa: BLE001  (reported to rank 0, then raised)
            error, status = err, _FAILED
        mine = torch.tensor([status, spent.factorizations, spent.solves, spent.rhs_columns,
                             spent.analyses], dtype=torch.int64)
        everyone = [torch.zeros_like(mine) for _ in range(self.size)]
        dist.all_gather(everyone, mine)
        if self.rank == 0:
            self.exchanging = False
            for row in everyone[1:]:        # the workers' work, in rank 0's scopes
                credit(SolveCounters(int(row[1]), int(row[2]), int(row[3]), int(row[4])))
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
        return local

    def collect(self, compute: Callable[[], Tensor]) -> Tensor | None:
        """:meth:`run` ``compute`` (this rank's frames, frame-major first axis), then on rank 0
        every rank's frames put in their places, in frame order (``None`` elsewhere)."""
        local = self.run(compute)
        if local is None:
            return None
        padded = local.new_zeros((self.longest,) + tuple(local.shape[1:]))
        padded[:local.shape[0]] = local.detach()
        if self.rank != 0:
            dist.gather(padded.cpu(), dst=0)
            return None
        parts = [torch.empty_like(padded.cpu()) for _ in range(self.size)]
        self.exchanging = True
        dist.gather(padded.cpu(), parts, dst=0)
        self.exchanging = False
        out = local.new_empty((sum(len(b) for b in self.blocks),) + tuple(local.shape[1:]))
        for r, block in enumerate(self.blocks):
            out[torch.as_tensor(block, dtype=torch.int64, device=out.device)] = \
                local if r == 0 else parts[r][:len(block)].to(local)
        return out

    def total(self, compute: Callable[[], Tensor]) -> Tensor | None:
        """:meth:`run` ``compute`` (the same shape on every rank), then on rank 0 the sum of
        every rank's result, added in rank order (a fixed order: bit-reproducible for a
        given number of processes); ``None`` elsewhere."""
        local = self.run(compute)
        if local is None:
            return None
        local = local.detach().cpu().contiguous()
        if self.rank != 0:
            dist.gather(local, dst=0)
            return None
        parts = [torch.empty_like(local) for _ in range(self.size)]
        self.exchanging = True
        dist.gather(local, parts, dst=0)
        self.exchanging = False
        result = parts[0].clone()
        for part in parts[1:]:
            result += part
        return result

    def gather_object(self, value: Any) -> list[Any] | None:
        """Every rank's ``value`` (picklable) on rank 0, in rank order, which ends rank 0's
        exchange; ``None`` elsewhere."""
        if self.rank != 0:
            dist.gather_object(value, dst=0)
            return None
        gathered: list[Any] = [None] * self.size
        dist.gather_object(value, gathered, dst=0)
        self.exchanging = False
        return gathered

    def scatter_object(self, parts: list[Any] | None) -> Any:
        """Rank 0's ``parts[r]`` (one picklable value per rank) on rank ``r``, which ends
        rank 0's exchange (a worker passes ``None``)."""
        received: list[Any] = [None]
        dist.scatter_object_list(received, parts if self.rank == 0 else None, src=0)
        if self.rank == 0:
            self.exchanging = False
        return received[0]
