"""Iteration records, results and the callback protocol shared by every solver.

A solver emits one :class:`IterationRecord` per outer iteration (iteration 0 is the
initial point) to every callback; the TensorBoard logger, the progress display, the
checkpoint writer and the metric evaluator of a run are such callbacks. Callbacks may
add entries to ``record.extra`` (problem metrics), which later callbacks see.
"""
from __future__ import annotations

import dataclasses
import enum
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


class StopReason(str, enum.Enum):
    """Why a solver run ended (``SolveResult.stop_reason``). A ``str`` enum: it equals,
    prints and JSON-dumps as its value (``result.json`` holds the value); ``torch.save``
    needs the value (``str(reason)``), as ``torch.load(weights_only=True)`` reads no enum.

    Converged (``SolveResult.converged`` true):

    * ``discrepancy``: ``||r|| <= tau delta`` (noise level ``delta`` known); split
      Bregman: the selected stage of the search in ``mu`` fits the data so.
    * ``tolerance``: the relative decrease of ``||r||``, ``||J^T r||`` or ``||r||`` itself
      fell below its tolerance, or Gauss-Newton's CGLS found no descent direction; split
      Bregman with a fixed weight: the fixed point.
    * ``resolution``: a trial point's misfit was bit-identical to the current one (the
      simulation cannot tell the step from the current point; Gauss-Newton and
      Levenberg-Marquardt).
    * ``plateau``: split Bregman's search in ``mu``: a weaker-TV stage fitted the data no
      closer than the spread of the noise's norm; the stage before it is the answer.

    Not converged:

    * ``max_iter``: the outer-iteration budget (split Bregman: also a stage's budget in a
      fixed-weight run, or the stages) is spent.
    * ``line_search``: Gauss-Newton's backtracking found no decrease along the step.
    * ``stalled``: Levenberg-Marquardt's damping exceeded ``damping_max`` times its start,
      or split Bregman rejected more than ``max_rejections`` outer steps in a row.
    * ``interrupted``: a callback returned ``True``.
    * ``validation``: a run's validation stopped it (no lower error on the frames held out
      of the fit for ``validation_patience`` iterations; :mod:`torchfit.run.validation`);
      the solver itself reports ``interrupted``.
    """

    discrepancy = "discrepancy"
    tolerance = "tolerance"
    resolution = "resolution"
    plateau = "plateau"
    max_iter = "max_iter"
    line_search = "line_search"
    stalled = "stalled"
    interrupted = "interrupted"
    validation = "validation"

    def __str__(self) -> str:
        return self.value

    __format__ = str.__format__


@dataclasses.dataclass
class SolveResult:
    """Outcome of a solver run: the parameters, whether and why it stopped
    (:class:`StopReason`), the records of this call and the whole run's totals.
    """

    theta: Tensor
    converged: bool
    stop_reason: StopReason
    iterations: int
    history: list[IterationRecord]
    wall_time: float
    factorizations: int
    solves: int

    def summary(self) -> dict[str, Any]:
        last = self.history[-1]
        return {"converged": self.converged, "stop_reason": str(self.stop_reason),
                "iterations": self.iterations, "wall_s": self.wall_time,
                "factorizations": self.factorizations, "solves": self.solves,
                "misfit": last.misfit, "objective": last.objective}


class Callback(Protocol):
    """What a solver calls with each iteration record (a run's observers are callbacks)."""

    def __call__(self, record: IterationRecord) -> bool | None:
        """Called once per outer iteration; return ``True`` to stop the solver."""


__all__ = ["Callback", "IterationRecord", "SolveResult", "StopReason"]
