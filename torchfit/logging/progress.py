"""One compact line per outer iteration on the terminal.

Example (Gauss-Newton on spring1d)::

     iter      misfit   objective   k_err_rel    cg    damping     |step|  solves   wall s
        0   6.135e+00   1.882e+01   7.077e-01     0          -          -       0     0.00
        1   5.457e+00   1.489e+01   6.004e-01     5          -   1.27e+00      27     0.05

``k_err_rel`` appears when a metrics callback ran before the printer (a problem with a
known truth), ``damping`` for Levenberg-Marquardt; a rejected step is marked
``rejected``. Columns without a value show ``-``.
"""
from __future__ import annotations

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


class ProgressPrinter:
    """Print a header, then one line per :class:`IterationRecord`.

    Args:
        stream: where to print (standard output by default, looked up at each call so
            that captured output works).
        every: print every ``every`` iterations (iteration 0 always).
        step_offset: added to the printed iteration (a resumed run continues the count).
    """

    header = _HEADER

    def __init__(self, stream: TextIO | None = None, every: int = 1, step_offset: int = 0) -> None:
        if every < 1:
            raise ValueError(f"progress interval must be >= 1, got {every}")
        self._stream = stream
        self.every = int(every)
        self.step_offset = int(step_offset)
        self._printed_header = False

    @property
    def stream(self) -> TextIO:
        return self._stream if self._stream is not None else sys.stdout

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
        stream = self.stream
        if not self._printed_header:
            print(self.header, file=stream)
            self._printed_header = True
        print(self.format(record), file=stream, flush=True)
        return None
