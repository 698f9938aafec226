"""A distributed simulation autograd can differentiate: each rank keeps its poses' graph.

The matrix-free path of a distributed fit (``n_params`` above
``solver.dense_jacobian_max_params``, :mod:`.split`): the solvers take ``J v`` and
``J^T w`` from autograd through ``problem.forward`` (:class:`~torchfit.residual.Linearization`),
so rank 0's simulation must be an autograd node. :class:`DistributedSimulation` is that
node; each rank's own frames are simulated with a graph from a leaf copy of the modulus
``E`` (the implicit-function adjoint of :class:`~torchfit.physics.Equilibrium`), kept on
the rank by id while rank 0's autograd node lives (:class:`GraphStore`):

- forward: every rank simulates its poses (Newton, or the equilibrium cache), the positions
  are gathered to rank 0 in pose order (as without a graph);
- backward (``J^T w``): ``dL/dx`` ``(P, n, d)`` is broadcast, every rank back-propagates
  its rows through its graph (one adjoint solve per pose) and the ``(n_cells,)`` gradients
  are summed on rank 0 in rank order;
- jvp (``J v``): ``E`` and ``dE`` are broadcast, every rank pushes ``dE`` through its
  equilibrium (one solve per pose with the cached solution's factor) and the tangents are
  gathered.

Traffic per product: one broadcast and one reduction of ``n_cells`` doubles for ``J^T w``
(plus ``dL/dx``), one broadcast of ``n_cells`` and a gather of positions for ``J v``.
"""
from __future__ import annotations

import weakref
from typing import Any

import torch
import torch.autograd.forward_ad as fwAD
from torch import Tensor

from .channel import GRAPH_JVP, GRAPH_VJP, SIMULATE_GRAPH


class GraphStore:
    """This rank's kept graphs ``(E_leaf, x)`` by id (rank 0's number). A graph is dropped
    when rank 0's autograd node of it is gone: its finalizer queues the id
    (:attr:`released`, rank 0), and the next simulation command carries the queue to
    every rank (no collective from a finalizer)."""

    def __init__(self) -> None:
        self.graphs: dict[int, tuple[Tensor, Tensor]] = {}
        self.next_id = 0
        self.released: list[int] = []

    def add(self, ident: int, leaf: Tensor, x: Tensor) -> None:
        self.next_id = max(self.next_id, ident + 1)
        self.graphs[ident] = (leaf, x)

    def drop(self, idents: list[int]) -> None:
        for ident in idents:
            self.graphs.pop(int(ident), None)

    def take_released(self) -> list[int]:
        released, self.released = self.released, []
        return released

    def get(self, ident: int) -> tuple[Tensor, Tensor]:
        if ident not in self.graphs:
            raise RuntimeError(f"the distributed simulation {ident} is no longer kept")
        return self.graphs[ident]


def needs_graph(E: Tensor) -> bool:
    """Whether a simulation at ``E`` must be differentiable (reverse or forward mode)."""
    return (torch.is_grad_enabled() and E.requires_grad) or \
        fwAD.unpack_dual(E).tangent is not None


def simulate_part(split: Any, ident: int, E: Tensor, keep: bool) -> Tensor:
    """Every rank: simulate this rank's poses; with ``keep``, at a leaf copy of ``E`` with
    a graph kept as ``ident`` (a reverse-mode linearisation); returns the positions
    (detached) for the gather."""
    positions, starts = split.pose_inputs(E)
    if not keep:        # forward mode: the jvp needs the point, not a graph
        with split.local(), torch.no_grad():
            return split(E, positions, starts)
    with split.local(), torch.enable_grad():
        leaf = E.detach().requires_grad_(True)
        x = split(leaf, positions, starts)
    split.graphs.add(ident, leaf, x)
    return x.detach()


def vjp_part(split: Any, ident: int, grad_x: Tensor) -> Tensor:
    """Every rank: ``(dx_rank/dE)^T grad_x[rank's poses]`` ``(n_cells,)``."""
    leaf, x = split.graphs.get(ident)
    (grad,) = torch.autograd.grad(x, leaf, grad_x[split.frames].to(x), retain_graph=True,
                                  allow_unused=True)
    return torch.zeros_like(leaf) if grad is None else grad.detach()


def jvp_part(split: Any, E: Tensor, d_E: Tensor) -> Tensor:
    """Every rank: ``(dx_rank/dE) d_E`` ``(P_rank, n, d)`` at ``E`` by the equilibrium's
    explicit products (one solve per pose with the cached solution's factor; no nested
    forward-mode AD, which rank 0's own jvp is inside of)."""
    positions, starts = split.pose_inputs(E)
    with split.local(), torch.no_grad():
        dx = split.jacobian(E.detach(), positions, d_E.to(E)[:, None], x_init=starts)
    return dx[..., 0]


class DistributedSimulation(torch.autograd.Function):
    """Rank 0: the positions of every simulated pose ``(P, n, d)`` at ``E``, with the
    distributed backward and jvp (module docstring). ``keep``: the ranks keep their graphs
    for a backward (reverse mode; forward mode keeps none)."""

    @staticmethod
    def forward(E: Tensor, split: Any, keep: bool) -> Tensor:  # type: ignore[override]
        ident = split.graphs.next_id if keep else -1
        released = split.graphs.take_released()
        split.channel.command(SIMULATE_GRAPH, ident, int(keep), len(released))
        split.channel.share(E, tuple(E.shape), E.dtype)
        if released:
            split.channel.share(torch.tensor(released, dtype=torch.float64), (len(released),),
                                torch.float64)
            split.graphs.drop(released)
        x = split.channel.collect(lambda: simulate_part(split, ident, E, keep))
        assert x is not None
        return x

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple, output: Tensor) -> None:
        E, split, keep = inputs
        ctx.split = split
        ctx.E = E.detach()
        ctx.ident = split.graphs.next_id - 1 if keep else -1
        ctx.set_materialize_grads(False)
        if keep:        # the graph is released with this node (module docstring)
            weakref.finalize(ctx, split.graphs.released.append, ctx.ident)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad_x: Tensor | None) -> tuple:  # type: ignore[override]
        if grad_x is None:
            return None, None, None
        split = ctx.split
        split.channel.command(GRAPH_VJP, ctx.ident)
        grad_x = split.channel.share(grad_x, tuple(grad_x.shape), grad_x.dtype)
        grad = split.channel.total(lambda: vjp_part(split, ctx.ident, grad_x))
        return grad, None, None

    @staticmethod
    def jvp(ctx: Any, d_E: Tensor | None, *_: Any) -> Tensor:  # type: ignore[override]
        split = ctx.split
        split.channel.command(GRAPH_JVP)
        E = split.channel.share(ctx.E, tuple(ctx.E.shape), ctx.E.dtype)
        d_E = split.channel.share(torch.zeros_like(E) if d_E is None else d_E,
                                  tuple(E.shape), E.dtype)
        tangent = split.channel.collect(lambda: jvp_part(split, E, d_E))
        assert tangent is not None
        return tangent


def answer(header: list[int], split: Any) -> None:
    """A worker's part of a graph command from rank 0."""
    problem, channel = split.problem, split.channel
    code, ident = header[0], header[1]
    n_cells = int(problem.model.n_cells)
    if code == SIMULATE_GRAPH:
        E = channel.share(None, (n_cells,), problem.dtype)
        if header[3]:
            released = channel.share(None, (header[3],), torch.float64)
            split.graphs.drop([int(i) for i in released.tolist()])
        channel.collect(lambda: simulate_part(split, ident, E, bool(header[2])))
    elif code == GRAPH_VJP:
        shape = (len(split.poses), int(problem.model.n_vertices), int(problem.model.dim))
        grad_x = channel.share(None, shape, problem.dtype)
        channel.total(lambda: vjp_part(split, ident, grad_x))
    elif code == GRAPH_JVP:
        E = channel.share(None, (n_cells,), problem.dtype)
        d_E = channel.share(None, (n_cells,), problem.dtype)
        channel.collect(lambda: jvp_part(split, E, d_E))
    else:
        raise RuntimeError(f"unknown graph command {code}")
