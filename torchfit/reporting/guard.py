"""The guard that keeps a drawing failure from failing a fit.

Every drawing of a run (TensorBoard images, PNGs, exported meshes) goes through one
:class:`PlotGuard`: an exception while drawing or saving is logged once per run as a
warning (logger ``torchfit.reporting.guard``) and the fit goes on; later failures of the
same run are counted but not repeated. A write that fails for a reason the user can act on
(a full disk, a file-size limit, a read-only place: :func:`torchfit.errors.write_failure`)
is not a drawing failure: it is raised, so that the run stops with its one line and the
resume writes every output (a run that ended "done" with ``usd/`` missing could not).
"""
from __future__ import annotations

import logging
from typing import Any, Callable, TypeVar

from ..errors import write_failure

log = logging.getLogger(__name__)
T = TypeVar("T")


class PlotGuard:
    """Run drawing code so that its failure never fails the fit; warn once per run.

    Attributes:
        failures: ``what`` of every drawing that failed, in order.
    """

    def __init__(self) -> None:
        self.failures: list[str] = []

    def run(self, what: str, draw: Callable[..., T], *args: Any, **kwargs: Any) -> T | None:
        """``draw(*args, **kwargs)``, or ``None`` (and a warning the first time) if it raises."""
        try:
            return draw(*args, **kwargs)
        except Exception as e:  # noqa: BLE001  (any drawing error: matplotlib, a bad value)
            if write_failure(e) is not None:
                raise
            if not self.failures:
                log.warning("could not draw %s (%s: %s); the fit and its result files are "
                            "not affected, further drawing failures of this run are not "
                            "reported", what, type(e).__name__, e)
            self.failures.append(what)
            return None
