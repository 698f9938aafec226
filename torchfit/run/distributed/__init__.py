"""One fit over several processes (``torchrun``): a rigged body's poses split over ranks.

Every process makes a :class:`DistributedSession` (:mod:`.session`): rank 0 leads and runs
the fit, every other rank builds the same problem and serves the simulations of its poses.
The modules:

- :mod:`.environment`: the rank, the number of processes and the process group, from
  torchrun's environment;
- :mod:`.refusals`: what a distributed fit refuses before it starts, each in one line;
- :mod:`.split`: the partition of the poses and the split pose simulation (:class:`~.split.
  FrameSplit`, plugged into the problem), rank 0's commands and a worker's answers;
- :mod:`.channel`: the collectives (rank 0 commands, every rank answers);
- :mod:`.rows`: the Jacobian's rows kept on their ranks, and the products the dense path
  needs;
- :mod:`.graph`: the matrix-free path, a distributed simulation autograd differentiates;
- :mod:`.liveness`: whether the peers still run, a lost rank told from other failures;
- :mod:`.session`: one process's part, the leader's and each worker's lifecycle.
"""
from .environment import launched, rank, start_group, world_size
from .liveness import communication_failure
from .refusals import check_resume
from .session import DistributedSession

__all__ = ["DistributedSession", "check_resume", "communication_failure", "launched", "rank",
           "start_group", "world_size"]
