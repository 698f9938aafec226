"""torchfit.run.distributed.split: the poses dealt to the ranks, and the split simulation that
implements the pose simulation interface the body's seam declares, member by member."""
from __future__ import annotations

import contextlib
import typing
from typing import Any, Iterator, Protocol

import pytest
import torch
import torch.distributed as dist

from helpers.repeating_animation import write_tube
from torchfit.problems import build_problem
from torchfit.problems.body.poses import FramePoses
from torchfit.run.distributed.channel import Channel
from torchfit.run.distributed.split import (FrameSplit, SplitEquilibrium, check_implements,
                                            partition, plug_split, protocol_members,
                                            seam_interface, unimplemented)


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


def test_the_split_has_every_member_of_the_pose_simulation_interface():
    # the interface the body's seam declares: a member added there is looked for here
    interface = seam_interface(FramePoses.plug)
    assert interface.__name__ == "PoseSimulation" and Protocol in interface.__mro__
    equilibrium = typing.get_type_hints(interface)["equilibrium"]
    assert Protocol in equilibrium.__mro__
    members = protocol_members(interface)
    assert {"__call__", "jacobian", "equilibrium"} <= members
    assert {"independent", "warm_start_state", "restore_warm_start_state"} <= \
        protocol_members(equilibrium)
    for name in members - {"equilibrium"}:      # methods, defined on the class itself
        assert name in vars(FrameSplit) and callable(vars(FrameSplit)[name]), name
    assert "equilibrium" in FrameSplit.__annotations__        # set by the constructor
    for name in protocol_members(equilibrium):
        assert name in vars(SplitEquilibrium) and callable(vars(SplitEquilibrium)[name]), name
    assert "__getattr__" not in vars(FrameSplit) and "__getattr__" not in vars(SplitEquilibrium)
    assert unimplemented(FrameSplit, interface) == []
    assert unimplemented(SplitEquilibrium, equilibrium) == []


class Simulation(Protocol):
    """A pose simulation interface with a member the split does not have."""

    equilibrium: Any

    def __call__(self, E: torch.Tensor) -> torch.Tensor:
        ...

    def jacobian(self, E: torch.Tensor) -> torch.Tensor:
        ...

    def reset(self) -> None:
        ...


class Seam:
    """A problem whose simulation's seam declares :class:`Simulation`: nothing may be plugged
    into it."""

    def __init__(self) -> None:
        self.plugged: list[Any] = []
        self.poses = self                       # the problem's simulation holds the seam

    def plug(self, simulation: Simulation, jacobian: Any = None) -> None:
        self.plugged.append(simulation)


def test_a_missing_member_stops_the_split_before_it_is_plugged():
    assert protocol_members(Simulation) == {"__call__", "jacobian", "equilibrium", "reset"}
    assert seam_interface(Seam().plug) is Simulation
    assert unimplemented(FrameSplit, Simulation) == ["reset"]
    with pytest.raises(TypeError, match="FrameSplit does not implement Simulation: it lacks "
                                        "reset"):
        check_implements(FrameSplit, Simulation)

    class Partial:
        def __call__(self, E: torch.Tensor) -> torch.Tensor:
            return E

    assert unimplemented(Partial, Simulation) == ["equilibrium", "jacobian", "reset"]
    problem = Seam()
    with pytest.raises(TypeError, match="lacks reset"):
        plug_split(problem, None)           # refused before any collective or plug
    assert problem.plugged == []


def same(a: Any, b: Any) -> bool:
    """Nested dicts, lists and tensors equal bit for bit."""
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b)
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and \
            all(same(x, y) for x, y in zip(a, b))
    return a == b


@contextlib.contextmanager
def one_rank_group(tmp_path) -> Iterator[None]:
    """A gloo group of this process alone: every command and exchange of the split runs,
    with rank 0 holding every pose."""
    dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'store'}", rank=0,
                            world_size=1)
    try:
        yield
    finally:
        dist.destroy_process_group()


def test_one_rank_split_simulates_as_the_problem_does(tmp_path):
    """Rank 0 alone through the commands: the tube's 8 frames are 5 poses; its positions
    bit for bit those of the problem's own simulation, the products of the rows kept on the
    rank equal the dense Jacobian's (``J^T J`` weighting a pose's rows by its frames), the
    warm-start state round trip and the dropped cache reach the rank's equilibrium."""
    settings = {"path": str(write_tube(tmp_path / "tube")), "tet_edge_length": 0.3,
                "grid": [2, 2, 2], "cache_dir": str(tmp_path / "cache")}
    alone, split_problem = build_problem("animation", settings), \
        build_problem("animation", settings)
    theta = alone.theta0 + 0.05 * torch.sin(torch.arange(alone.theta0.numel(),
                                                          dtype=alone.theta0.dtype))
    E = alone.parameterization(theta)
    with torch.no_grad():
        x = alone.simulate(E)
    J = alone.forward_jacobian(theta)
    with one_rank_group(tmp_path):
        own = split_problem.poses.quasistatic
        split = plug_split(split_problem, Channel(partition(5, 1)))
        assert split_problem.poses.quasistatic is split and split.own is own
        assert split.frames.tolist() == [0, 1, 2, 3, 4] and split.counts.tolist() == \
            [2, 2, 1, 2, 1]
        with torch.no_grad():
            assert torch.equal(split_problem.simulate(E), x)
        assert split.last_newton_iterations == own.last_newton_iterations
        assert len(split.last_newton_iterations) == 5
        rows = split_problem.forward_jacobian(theta)
        assert tuple(rows.shape) == tuple(J.shape)
        assert torch.equal(rows.full(), J)
        w = torch.linspace(-1.0, 1.0, J.shape[0], dtype=J.dtype)
        v = torch.linspace(0.5, 1.5, J.shape[1], dtype=J.dtype)
        # other shapes of the same products (per pose, weighted): equal to round-off
        scale = float(J.abs().max())
        assert torch.allclose(rows.T @ rows, J.T @ J, rtol=1e-12, atol=1e-14 * scale ** 2)
        assert torch.allclose(rows.T @ w, J.T @ w, rtol=1e-12, atol=1e-14 * scale)
        assert torch.allclose(rows @ v, J @ v, rtol=1e-12, atol=1e-14 * scale)
        state = split.equilibrium.warm_start_state()
        assert state["world_size"] == 1 and state["blocks"] == [[0, 1, 2, 3, 4]]
        assert state["ranks"][0]["solutions"]
        assert same(state["ranks"], [own.equilibrium.warm_start_state()])
        split.equilibrium.clear_cache()
        assert own.equilibrium.warm_start_state() == {}          # nothing to start from
        split.equilibrium.restore_warm_start_state(state)
        assert same(split.equilibrium.warm_start_state(), state)     # the same tensors back
        with split.equilibrium.independent(), torch.no_grad():
            assert torch.allclose(split_problem.simulate(E), x, rtol=0, atol=1e-9)
        assert not split.channel.exchanging
