"""Where this process stands under ``torchrun``: its rank, the number of processes, the group.

torchrun tells each process its place through the environment (``RANK``, ``WORLD_SIZE``);
outside torchrun there is one process, rank 0. The process group is gloo (the frames are
simulated on the CPU); its collectives time out after ``TORCHFIT_DISTRIBUTED_TIMEOUT``
seconds (default 1800: a worker waits while rank 0 writes pictures or simulates the model
comparison alone).
"""
from __future__ import annotations

import datetime
import os

import torch.distributed as dist


def rank() -> int:
    """This process's rank under torchrun (0 outside it)."""
    return int(os.environ.get("RANK", "0"))


def world_size() -> int:
    """The number of processes torchrun started (1 outside torchrun)."""
    return int(os.environ.get("WORLD_SIZE", "1"))


def launched() -> bool:
    """Whether this process is one of several started by torchrun."""
    return world_size() > 1


def timeout_seconds() -> float:
    """How long a collective waits for its peers (``TORCHFIT_DISTRIBUTED_TIMEOUT``)."""
    return float(os.environ.get("TORCHFIT_DISTRIBUTED_TIMEOUT", "1800"))


def start_group() -> None:
    """The process group (gloo: frames on the CPU) from torchrun's environment; nothing
    where this process has one already."""
    if not dist.is_initialized():
        dist.init_process_group("gloo", timeout=datetime.timedelta(seconds=timeout_seconds()))
