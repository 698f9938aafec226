"""Logging layer: TensorBoard, progress display, run-directory files, per-iteration metrics.

Everything here observes a run through the callback protocol of :mod:`torchfit.records`
(an :class:`~torchfit.records.IterationRecord` in, ``None`` out) or writes files after it;
nothing here computes anything a solver needs, and nothing imports :mod:`torchfit.solvers`.
In a run (:func:`torchfit.fit.fit`) the callbacks are called in the order

``MetricsCallback, ProgressPrinter, <checkpoint commit>, TensorBoardLogger, FieldSnapshots``

so that the metrics :class:`MetricsCallback` adds to ``record.extra`` reach everything after
it, and an iteration is in the checkpoint before TensorBoard shows it (a resumed run adds
what TensorBoard lost, :meth:`TensorBoardLogger.resume`).
"""
from .metrics import METRIC_KEYS, MetricsCallback
from .pictures import PlotGuard, write_run_pngs
from .progress import PROGRESS_LOGGER, ProgressPrinter, ensure_progress_visible
from .results import history_rows, save_params, save_torch, write_json
from .tensorboard import (FieldSnapshots, TensorBoardLogger, field_is_chain, supports_field_images,
                          tag_for)

__all__ = [
    "FieldSnapshots", "METRIC_KEYS", "MetricsCallback", "PROGRESS_LOGGER", "PlotGuard",
    "ProgressPrinter", "TensorBoardLogger", "ensure_progress_visible", "field_is_chain",
    "history_rows", "save_params", "save_torch", "supports_field_images", "tag_for",
    "write_json", "write_run_pngs",
]
