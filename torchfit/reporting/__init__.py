"""Reporting layer: TensorBoard, progress display, pictures and run-directory files.

Everything here observes a run through the callback protocol of :mod:`torchfit.records`
(an :class:`~torchfit.records.IterationRecord` in, ``None`` out) or writes files after it;
nothing here computes anything a solver needs, and nothing imports :mod:`torchfit.solvers`.
"""
from .body import BodyOutputs
from .field_snapshots import FieldSnapshots
from .guard import PlotGuard
from .metrics import MetricsCallback
from .motion import MotionOutputs
from .progress import PROGRESS_LOGGER, ProgressPrinter
from .tensorboard import TensorBoardLogger

__all__ = ["BodyOutputs", "FieldSnapshots", "MetricsCallback", "MotionOutputs", "PROGRESS_LOGGER",
           "PlotGuard", "ProgressPrinter", "TensorBoardLogger"]
