"""Iteration records, results and the callback protocol shared by every solver.

A solver emits one :class:`IterationRecord` per outer iteration (iteration 0 is the
initial point) to every callback; the TensorBoard logger, the progress display, the
checkpoint writer and the metric evaluator of a run are such callbacks. Callbacks may
add entries to ``record.extra`` (problem metrics), which later callbacks see.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Protocol

from torch import Tensor


@dataclasses.dataclass
class IterationRecord:
    """State after one outer iteration.

    Attributes:
        iteration: outer iteration (0 = initial point).
        theta: ``(n,)`` current parameters (detached; do not modify).
        objective: the value the solver minimises (``0.5 ||r||^2`` for least squares).
        misfit: ``||r||_2``.
        step_norm: ``||theta_k - theta_{k-1}||_2`` (0 for a rejected step).
        cg_iterations: inner CG/CGLS iterations of this outer iteration.
        damping: Levenberg-Marquardt damping used for this iteration's step (``nan``
            for other solvers; at iteration 0 the initial damping).
        accepted: whether the step was taken.
        wall_time: seconds since the solver started.
        factorizations, solves: counters since the solver started.
        extra: solver- or callback-specific scalars (metrics, TV terms, ...).
    """

    iteration: int
    theta: Tensor
    objective: float
    misfit: float
    step_norm: float = 0.0
    cg_iterations: int = 0
    damping: float = float("nan")
    accepted: bool = True
    wall_time: float = 0.0
    factorizations: int = 0
    solves: int = 0
    extra: dict[str, float] = dataclasses.field(default_factory=dict)

    def scalars(self) -> dict[str, float]:
        """Every scalar of the record (for loggers), ``extra`` included."""
        out = {k: float(v) for k, v in dataclasses.asdict(self).items()
               if k not in ("theta", "extra", "iteration")}
        out.update({k: float(v) for k, v in self.extra.items()})
        return out

    def row(self, step_offset: int = 0) -> dict[str, float]:
        """``{'iteration': ..., **scalars()}``: one row of ``result.json``'s history."""
        return {"iteration": self.iteration + step_offset, **self.scalars()}


@dataclasses.dataclass
class SolveResult:
    """Outcome of a solver run.

    ``stop_reason`` is one of ``discrepancy`` (``||r|| <= tau delta``), ``tolerance``
    (relative decrease or gradient below tolerance, or a split Bregman fixed point),
    ``max_iter``, ``line_search`` (no decrease possible along the step), ``stalled``
    (damping exhausted, or split Bregman rejected too many outer steps in a row), or
    ``interrupted`` (a callback asked to stop).
    """

    theta: Tensor
    converged: bool
    stop_reason: str
    iterations: int
    history: list[IterationRecord]
    wall_time: float
    factorizations: int
    solves: int

    def summary(self) -> dict[str, Any]:
        last = self.history[-1]
        return {"converged": self.converged, "stop_reason": self.stop_reason,
                "iterations": self.iterations, "wall_s": self.wall_time,
                "factorizations": self.factorizations, "solves": self.solves,
                "misfit": last.misfit, "objective": last.objective}


class Callback(Protocol):
    def __call__(self, record: IterationRecord) -> bool | None:
        """Called once per outer iteration; return ``True`` to stop the solver."""
