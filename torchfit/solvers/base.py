"""What every solver shares: the run clock, record emission and the result."""
from __future__ import annotations

import time
from typing import Iterable

from torch import Tensor

from ..linalg import COUNTERS
from ..records import Callback, IterationRecord, SolveResult


class RunClock:
    """Wall time and counter offsets since the start of a solver run."""

    def __init__(self) -> None:
        self.start = time.perf_counter()
        self.counters0 = COUNTERS.snapshot()

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def counts(self) -> tuple[int, int]:
        delta = COUNTERS - self.counters0
        return delta.factorizations, delta.solves


def emit(callbacks: Iterable[Callback], record: IterationRecord) -> bool:
    """Send a record to every callback; ``True`` if one asked to stop."""
    stop = False
    for callback in callbacks:
        stop = bool(callback(record)) or stop
    return stop


def finish(theta: Tensor, converged: bool, reason: str, history: list[IterationRecord],
           clock: RunClock) -> SolveResult:
    factorizations, solves = clock.counts()
    return SolveResult(theta, converged, reason, history[-1].iteration, history,
                       clock.elapsed(), factorizations, solves)

