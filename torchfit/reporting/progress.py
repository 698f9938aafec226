"""One compact line per outer iteration on the terminal.

Example (Gauss-Newton on spring1d)::

     iter      misfit   objective   k_err_rel    cg    damping     |step|  solves   wall s
        0   6.135e+00   1.882e+01   7.077e-01     0          -          -       0     0.00
        1   5.457e+00   1.489e+01   6.004e-01     5          -   1.27e+00      27     0.05

``k_err_rel`` appears when a metrics callback ran before the printer (a problem with a
known truth), ``damping`` for Levenberg-Marquardt; a rejected step is marked
``rejected``. Columns without a value show ``-``.

The header and the lines are records of the standard :mod:`logging` module (logger
``torchfit.progress``, level INFO), so that the log files of an application (Hydra's
``<job>.log``) hold the table. :func:`ensure_progress_visible` (called by
:class:`ProgressPrinter` unless told not to) makes them visible where logging is not
configured (a notebook, a script): a handler on ``torchfit.progress`` prints them on
standard output *only when no other handler* of the logger hierarchy (Hydra's console and
file handlers on the root logger, a ``logging.basicConfig``) takes them, so nothing is
printed twice, whether logging is configured before or after the printer is made.
"""
from __future__ import annotations

import logging
import math
import sys
from typing import TextIO

from ..records import IterationRecord

_HEADER = (f"{'iter':>5} {'misfit':>11} {'objective':>11} {'k_err_rel':>11} {'cg':>5} "
           f"{'damping':>10} {'|step|':>10} {'solves':>7} {'wall s':>8}")


def _sci(value: float | None, width: int, digits: int = 3) -> str:
    if value is None or not math.isfinite(value):
        return f"{'-':>{width}}"
    return f"{value:>{width}.{digits}e}"


PROGRESS_LOGGER = "torchfit.progress"


class StdoutFallbackHandler(logging.StreamHandler):
    """Prints a record (its message only) on ``stream`` (standard output by default, looked
    up at each record so that captured output works) unless another handler of the
    logger hierarchy handles it."""

    def __init__(self, stream: TextIO | None = None) -> None:
        super().__init__(stream)
        self._own_stream = stream
        self.setFormatter(logging.Formatter("%(message)s"))

    @property
    def stream(self) -> TextIO:  # type: ignore[override]
        return self._own_stream if self._own_stream is not None else sys.stdout

    @stream.setter
    def stream(self, value: TextIO | None) -> None:
        self._own_stream = value

    def handled_elsewhere(self, record: logging.LogRecord) -> bool:
        """Whether a handler other than this one gets ``record`` (as ``Logger.callHandlers``
        walks the hierarchy)."""
        logger: logging.Logger | None = logging.getLogger(record.name)
        while logger is not None:
            for handler in logger.handlers:
                if handler is not self and record.levelno >= handler.level:
                    return True
            if not logger.propagate:
                return False
            logger = logger.parent
        return False

    def emit(self, record: logging.LogRecord) -> None:
        if not self.handled_elsewhere(record):
            super().emit(record)


def ensure_progress_visible(stream: TextIO | None = None,
                            name: str = PROGRESS_LOGGER) -> StdoutFallbackHandler:
    """Make the progress lines visible without any logging configuration (idempotent).

    Sets the level of logger ``name`` to INFO if it has none, and attaches (once) a
    :class:`StdoutFallbackHandler`: it prints the lines on ``stream`` (standard output)
    whenever no other handler would take them, and stays silent where an application
    (Hydra, ``logging.basicConfig``) configured handlers, so that the table is never
    printed twice. Returns the handler.
    """
    logger = logging.getLogger(name)
    if logger.level == logging.NOTSET:
        logger.setLevel(logging.INFO)
    for handler in logger.handlers:
        if isinstance(handler, StdoutFallbackHandler):
            if stream is not None:
                handler.stream = stream
            return handler
    handler = StdoutFallbackHandler(stream)
    logger.addHandler(handler)
    return handler


class ProgressPrinter:
    """Log a header, then one line per :class:`IterationRecord` (logger
    ``torchfit.progress``, INFO; see the module docstring).

    Args:
        every: print every ``every`` iterations (iteration 0 always).
        step_offset: added to the printed iteration (a resumed run continues the count).
        logger: the logger (or its name) of the lines.
        ensure_visible: call :func:`ensure_progress_visible` for that logger, so that the
            lines reach standard output where logging is not configured (default).
    """

    header = _HEADER

    def __init__(self, every: int = 1, step_offset: int = 0,
                 logger: logging.Logger | str = PROGRESS_LOGGER,
                 ensure_visible: bool = True) -> None:
        if every < 1:
            raise ValueError(f"progress interval must be >= 1, got {every}")
        self.every = int(every)
        self.step_offset = int(step_offset)
        self.logger = logging.getLogger(logger) if isinstance(logger, str) else logger
        if ensure_visible:
            ensure_progress_visible(name=self.logger.name)
        self._printed_header = False

    def format(self, record: IterationRecord) -> str:
        """The line of one record (without a newline)."""
        k_err = record.extra.get("k_err_rel")
        step = record.step_norm if record.iteration > 0 else None
        line = (f"{record.iteration + self.step_offset:>5d} {_sci(record.misfit, 11)} "
                f"{_sci(record.objective, 11)} {_sci(k_err, 11)} {record.cg_iterations:>5d} "
                f"{_sci(record.damping, 10, 2)} {_sci(step, 10, 2)} {record.solves:>7d} "
                f"{record.wall_time:>8.2f}")
        if not record.accepted:
            line += "  rejected"
        return line

    def __call__(self, record: IterationRecord) -> None:
        if record.iteration % self.every:
            return None
        if not self._printed_header:
            self.logger.info(self.header)
            self._printed_header = True
        self.logger.info(self.format(record))
        return None
