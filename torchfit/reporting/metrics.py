"""The metrics of PROBLEMS.md at every iteration, as a callback.

:class:`MetricsCallback` evaluates ``problem.metrics(record.theta)`` and stores the
values in ``record.extra``, where the loggers placed after it in the callback list
(progress, TensorBoard, the result file's history) find them. It changes nothing the
solver uses: the record's ``theta`` is the point the solver has just linearised, and
the equilibrium keeps its solution (and factorisation) for that point in its cache, so
the extra ``simulate`` is a cache hit that costs no factorisation and no solve.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from ..records import IterationRecord

if TYPE_CHECKING:  # pragma: no cover
    from ..problems import InverseProblem


class MetricsCallback:
    """Add ``problem.metrics(record.theta)`` to ``record.extra``.

    Args:
        problem: the inverse problem being fitted.
        every: evaluate every ``every`` iterations (iteration 0 always); records in
            between carry no metrics.

    Attributes:
        last: the metrics of the last evaluated record (``{}`` before the first).
    """

    def __init__(self, problem: "InverseProblem", every: int = 1) -> None:
        if every < 1:
            raise ValueError(f"metrics interval must be >= 1, got {every}")
        self.problem = problem
        self.every = int(every)
        self.last: dict[str, float] = {}

    def __call__(self, record: IterationRecord) -> None:
        if record.iteration % self.every:
            return None
        values = self.problem.metrics(record.theta)
        record.extra.update(values)
        self.last = values
        return None
