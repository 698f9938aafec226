"""What a run evaluated at one point: the state every observer reads instead of simulating.

A run (:class:`torchfit.run.evaluator.Evaluator`) makes one :class:`Evaluation` per
recorded iteration, before any observer sees the record, and one at the end (the last
record's, when the run ended there); observers take it and never simulate again.
"""
from __future__ import annotations

import dataclasses
from typing import Any

from torch import Tensor

from ..records import IterationRecord


@dataclasses.dataclass(frozen=True)
class Evaluation:
    """The problem at ``theta``.

    Attributes:
        theta: ``(n_params,)`` the parameters (detached).
        field: ``(n_field,)`` the physical field, ``problem.field(theta)``.
        state: ``(F, n_nodes, dim)`` every node of every frame,
            ``problem.simulate(problem.simulation_input(theta))`` (no graph).
        metrics: ``problem.metrics(theta, state)``: the metrics of docs/problems.md.
        record: the iteration record evaluated (``None``: a point that is not a record's,
            such as a report's baseline).
        validation: the metrics of the frames held out of the fit at ``theta`` (the run's
            validation problem, :mod:`torchfit.run.validation`), ``None`` without them.
        validation_errors: ``(F_val,)`` the mean surface error (m) of every validation
            frame at ``theta`` (their ``frame_errors``' ``surface_err_mean``, for the
            per-frame plots), ``None`` without validation frames or per-frame errors.
    """

    theta: Tensor
    field: Tensor
    state: Tensor
    metrics: dict[str, float]
    record: IterationRecord | None = None
    validation: dict[str, float] | None = None
    validation_errors: Any = None
