"""Who simulates a problem during a run: a counter wrapped around ``problem.simulate``."""
from __future__ import annotations

import collections
import sys
from types import FrameType
from typing import Any

EVALUATOR = "torchfit.run.evaluator"


class SimulationCounter:
    """Counts every call of ``problem.simulate`` by who made it.

    Attributes:
        per_record: ``{iteration: n}`` simulations the run's evaluator made for the record
            of that iteration (directly, not a problem's own metric that simulates).
        end: the evaluator's simulations outside a record (the end of the run, a baseline).
        observers: calls with a ``torchfit.reporting`` frame on the stack (must be 0).
        total: every call.
    """

    def __init__(self, problem: Any) -> None:
        self.per_record: collections.Counter[int] = collections.Counter()
        self.end = 0
        self.observers = 0
        self.total = 0
        original = problem.simulate

        def simulate(*args: Any, **kwargs: Any) -> Any:
            self._attribute(sys._getframe(1))
            return original(*args, **kwargs)

        problem.simulate = simulate

    def _attribute(self, caller: FrameType) -> None:
        self.total += 1
        frames = []
        frame: FrameType | None = caller
        while frame is not None:
            frames.append(frame)
            frame = frame.f_back
        if any(str(f.f_globals.get("__name__", "")).startswith("torchfit.reporting")
               for f in frames):
            self.observers += 1
            return
        if caller.f_globals.get("__name__") != EVALUATOR or caller.f_code.co_name != "evaluate":
            return
        record = caller.f_locals.get("record")
        if record is None:
            self.end += 1
        else:
            self.per_record[int(record.iteration)] += 1
