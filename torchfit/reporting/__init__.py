"""Reporting layer: TensorBoard, progress display, pictures and run-directory files.

Everything here observes a run: record callbacks (an
:class:`~torchfit.records.IterationRecord` in, ``None`` out), observers that read the run's
one evaluation per recorded iteration (:mod:`.evaluation`), or writers of files after it.
Nothing here simulates or computes anything a solver needs, and nothing imports
:mod:`torchfit.solvers`. What a user calls beside a solver: :class:`TensorBoardLogger` and
:class:`ProgressPrinter` (lines on the :data:`PROGRESS_LOGGER` logger); the run
(:mod:`torchfit.run`) uses the rest of this face: the observers of a body
(:mod:`.body`, :mod:`.body_files`), of a 2-D field (:mod:`.field_snapshots`,
:mod:`.figures`) and of a motion (:mod:`.motion`), the identifiability files, the files of
``simulate`` (:mod:`.simulation`) and the run directory's files (:mod:`.results`).
"""
from .body import BodyOutputs, frame_spans
from .body_files import fitted_damping, modulus_units
from .evaluation import Evaluation
from .field_snapshots import FieldSnapshots
from .figures import field_is_chain, write_run_pngs
from .guard import PlotGuard
from .identifiability import write_identifiability
from .motion import MotionOutputs
from .progress import PROGRESS_LOGGER, ProgressPrinter, ensure_progress_visible
from .results import (CHECKPOINT_FILE, PARAMS_FILE, RESULT_FILE, atomic_write, jsonable,
                      remove_stale_temporaries, save_params, save_torch, write_json)
from .simulation import comparison_picture, write_frames
from .tensorboard import TensorBoardLogger, event_files

__all__ = ["BodyOutputs", "CHECKPOINT_FILE", "Evaluation", "FieldSnapshots", "MotionOutputs",
           "PARAMS_FILE", "PROGRESS_LOGGER", "PlotGuard", "ProgressPrinter", "RESULT_FILE",
           "TensorBoardLogger", "atomic_write", "comparison_picture", "ensure_progress_visible",
           "event_files", "field_is_chain", "fitted_damping", "frame_spans", "jsonable", "modulus_units",
           "remove_stale_temporaries", "save_params", "save_torch", "write_frames",
           "write_identifiability", "write_json", "write_run_pngs"]
