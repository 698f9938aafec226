"""Structured (validated) configs of the Hydra apps, registered with Hydra's ConfigStore.

Schemas live in the ``schema/`` group so that the user-facing groups ``problem/`` and
``solver/`` list only real choices. The YAML files under ``conf/`` extend them; a
misspelt or mistyped override fails at composition time, before any run directory
exists.
"""
from __future__ import annotations

import dataclasses
import enum
from typing import Any, List, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

from .problems import PROBLEMS
from .solvers import SOLVERS


@dataclasses.dataclass
class FitConfig:
    """Top level of ``experiments/fit.py``."""

    problem: Any = MISSING
    solver: Any = MISSING
    resume: bool = False        # continue from the last checkpoint in the run directory
    # Start from an earlier run's fitted parameters (its directory or params.pt) instead of
    # the problem's initial guess: e.g. the frames whose equilibrium is unique first, then
    # all frames; or a coarser mesh first. The parameterisation must be the same.
    init: Optional[str] = None
    # Fit the frames far from a fold first (no tetrahedron below continuation_min_volume of
    # its rest volume at the start), then all frames from there: two runs in one, the first
    # in <run>/unique_frames (torchfit.continuation). Bodies fitted to an animation only.
    continuation: bool = False
    continuation_min_volume: float = 0.25
    progress: bool = True       # one line per outer iteration on the terminal
    log_every: int = 1          # TensorBoard scalars every n iterations (the last always)
    threads: int = 0            # torch and BLAS CPU threads per job (0: default); 1 in joblib sweeps
    # 2-D fields (poisson2d, membrane2d): the field and error images after these iterations
    # (snapshots.png, the seed's figure), every snapshot_every iterations and at the last
    # one in TensorBoard (snapshot_every=0: only those).
    snapshot_iterations: List[int] = dataclasses.field(default_factory=lambda: [1, 5, 10, 40])
    snapshot_every: int = 10
    sheet_frame: Optional[int] = None   # frame whose deformed mesh is drawn (None: the problem's)
    # What the task function returns, i.e. what a sweeper such as Optuna minimises: a key of
    # result.json (a metric of PROBLEMS.md, or iterations, wall_s, factorizations, solves).
    objective_metric: str = "misfit"


class VerifyPoint(str, enum.Enum):
    """Where ``experiments/verify.py`` checks the derivatives."""

    initial = "initial"
    truth = "truth"


@dataclasses.dataclass
class VerifyConfig:
    """Top level of ``experiments/verify.py``."""

    problem: Any = MISSING
    seed: int = 0               # of the random point offset and directions
    at: VerifyPoint = VerifyPoint.initial   # where to verify: initial | truth
    perturbation: float = 0.1   # random offset of theta from that point (relative)
    taylor_tol: float = 0.05    # |rate - 2| allowed
    dot_tol: float = 1e-10      # relative |<Jv, w> - <v, J^T w>|
    fd_tol: Optional[float] = None   # relative |Jv - central FD|; null: max(1e-6, 100 a^(2/3))
                                     # with a the simulation's accuracy (Newton's rtol)
    solver: Any = None          # unused; a problem's default solver (membrane2d) may fill it
    threads: int = 0            # torch and BLAS CPU threads (0: default), as in fit


def register_configs() -> None:
    """Register every schema (idempotent)."""
    cs = ConfigStore.instance()
    cs.store(name="fit_schema", node=FitConfig)
    cs.store(name="verify_schema", node=VerifyConfig)
    for name, entry in PROBLEMS.items():
        cs.store(group="schema/problem", name=name, node=entry.config_class)
    for name, entry in SOLVERS.items():
        cs.store(group="schema/solver", name=name, node=entry.config_class)
