"""Logging layer: TensorBoard, progress display, result files, per-iteration metrics.

Everything here observes a run through the solvers' callback protocol
(:class:`torchfit.solvers.IterationRecord` in, ``None`` out) or writes files after it;
nothing here computes anything a solver needs. The order of callbacks in a run is

``[MetricsCallback, ProgressPrinter, TensorBoardLogger, CheckpointWriter]``

so that the problem metrics added by :class:`MetricsCallback` to ``record.extra`` are
seen by the loggers after it.
"""
from .metrics import METRIC_KEYS, MetricsCallback
from .pictures import PlotGuard, write_run_pngs
from .progress import PROGRESS_LOGGER, ProgressPrinter, ensure_progress_visible
from .results import (Checkpoint, CheckpointWriter, load_checkpoint, result_dict, save_checkpoint,
                      save_params, write_json, write_result)
from .tensorboard import (FieldSnapshots, TensorBoardLogger, field_is_chain, supports_field_images,
                          tag_for)

__all__ = [
    "Checkpoint", "CheckpointWriter", "FieldSnapshots", "METRIC_KEYS", "MetricsCallback",
    "PROGRESS_LOGGER", "ensure_progress_visible",
    "PlotGuard", "ProgressPrinter", "TensorBoardLogger", "field_is_chain", "load_checkpoint", "result_dict",
    "save_checkpoint", "save_params", "supports_field_images", "tag_for", "write_json",
    "write_result", "write_run_pngs",
]
