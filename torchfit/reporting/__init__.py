"""Reporting layer: TensorBoard, progress display, pictures and run-directory files.

Everything here observes a run: record callbacks (an
:class:`~torchfit.records.IterationRecord` in, ``None`` out), observers that read the run's
one evaluation per recorded iteration (:mod:`.evaluation`), or writers of files after it.
Nothing here simulates or computes anything a solver needs, and nothing imports
:mod:`torchfit.solvers`. What a user calls beside a solver: :class:`TensorBoardLogger` and
:class:`ProgressPrinter` (lines on the :data:`PROGRESS_LOGGER` logger); the run
(:mod:`torchfit.run`) uses the modules themselves.
"""
from .progress import PROGRESS_LOGGER, ProgressPrinter
from .tensorboard import TensorBoardLogger

__all__ = ["PROGRESS_LOGGER", "ProgressPrinter", "TensorBoardLogger"]
