"""Set-up progress on the console: a named step, its counts and its elapsed time.

A problem's set-up (reading an animation, tetrahedralising, embedding, the first
simulation) can take minutes before the first iteration. Each step logs a line when it
starts (``tetrahedralising the rest surface (16,200 faces) ...``), optional heartbeats
while it runs, and a line when it ends with what it made and how long it took::

    with step("embedding 1,922 surface vertices in 9,257 tetrahedra") as s:
        ...
        s.result = "largest distance outside 0.0 m"

The lines are records of the standard :mod:`logging` module, logger ``torchfit.setup``
(INFO): Hydra's apps print them on the console and into ``<job>.log``; elsewhere they are
visible once logging is configured (``logging.basicConfig(level=logging.INFO)``). A step
that raises logs nothing more (the error says what happened). Neutral layer: any layer may
use it; it imports nothing of torchfit.
"""
from __future__ import annotations

import contextlib
import logging
import time
from typing import Any, Iterator

SETUP_LOGGER = "torchfit.setup"
log = logging.getLogger(SETUP_LOGGER)


def count(n: int) -> str:
    """``16,200``: a count with thousands separators."""
    return f"{int(n):,}"


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """Within the block, steps log only warnings: the same set-up made again for a part of
    what was built (the held-out frames of the same body) is not printed twice."""
    level = log.level
    log.setLevel(max(logging.WARNING, level))
    try:
        yield
    finally:
        log.setLevel(level)


class step:
    """Context manager of one set-up step (module docstring).

    Attributes:
        what: what is being done (the start line is ``<what> ...``).
        result: set inside the block: what the step made (the end line).
        start: ``time.perf_counter()`` at the start.
    """

    def __init__(self, what: str, logger: logging.Logger | None = None) -> None:
        self.what = what
        self.result = ""
        self.logger = logger or log
        self.start = time.perf_counter()

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def beat(self, detail: str = "") -> None:
        """A heartbeat line: ``<what>: <detail>, 12 s``."""
        self.logger.info("%s: %s%.0f s", self.what, f"{detail}, " if detail else "running, ",
                         self.elapsed)

    def __enter__(self) -> "step":
        self.start = time.perf_counter()
        self.logger.info("%s ...", self.what)
        return self

    def __exit__(self, kind: Any, value: Any, traceback: Any) -> None:
        if kind is None:
            self.logger.info("%s: %s%.1f s", self.what, f"{self.result}, " if self.result
                             else "done in ", self.elapsed)
