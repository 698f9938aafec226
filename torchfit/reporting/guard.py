"""The guard that keeps a drawing failure from failing a fit.

Every drawing of a run (TensorBoard images, PNGs, exported meshes) goes through one
:class:`PlotGuard`: an exception while drawing or saving is logged once per run as a
warning (logger ``torchfit.reporting.guard``) and the fit goes on; later failures of the
same run are counted but not repeated.
"""
from __future__ import annotations

import logging
from typing import Any, Callable, TypeVar

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
        except Exception as e:  # noqa: BLE001  (any drawing error: matplotlib, disk, ...)
            if not self.failures:
                log.warning("could not draw %s (%s: %s); the fit and its result files are "
                            "not affected, further drawing failures of this run are not "
                            "reported", what, type(e).__name__, e)
            self.failures.append(what)
            return None
