"""TensorBoard output of a fit: per-iteration scalars, the fitted field, hparams.

Tag scheme (one TensorBoard section per prefix)
------------------------------------------------

=================  ===========================================================================
``fit/<key>``      what is minimised: ``fit/misfit`` (``||r||_2``, the PROBLEMS.md ``misfit``),
                   ``fit/objective`` (``0.5 ||r||^2`` for least squares), and ``fit/tv`` /
                   ``fit/penalty`` when a solver reports them.
``metrics/<key>``  the other metrics of PROBLEMS.md, against the truth:
                   ``metrics/u_err_inf``, ``metrics/u_err_2``, ``metrics/k_err_inf``,
                   ``metrics/k_err_2``, ``metrics/k_err_rel``, ``metrics/k_err_rel_aligned``
                   (any further ``*_err*`` key lands here too).
``solver/<key>``   how the solver got there: ``solver/step_norm``, ``solver/cg_iterations``,
                   ``solver/damping`` (Levenberg-Marquardt only; NaN is never written),
                   ``solver/accepted`` (1/0), ``solver/factorizations``, ``solver/solves``,
                   ``solver/wall_time`` (cumulative since the solver started), and every
                   other solver-specific entry of ``record.extra`` (``solver/eta``,
                   ``solver/gradient_norm``, ``solver/gain_ratio``, ...).
``field/<name>``   at the end: histogram of the fitted field (``field/k``) and of the truth
                   (``field/k_true``); for a 1-D field (a chain) an image
                   ``field/<name>_profile`` of fitted vs true per cell.
``config``         at the start: the resolved config as text.
``field/<name>_*``  (2-D fields, :class:`FieldSnapshots`: poisson2d, membrane2d) images,
                   upscaled (at most 16x) so the longer side has >= 256 pixels:
                   ``field/<name>_true_image`` once (first step); ``field/<name>_image``, the
                   fit (for a scale-free problem multiplied by the best global scale onto
                   the truth; fixed colour range ``[min(0, truth), 1.15 max truth]``) and
                   ``field/<name>_error_aligned_image`` (``field/<name>_error_image`` when
                   not scale-free), ``a k - k_true``, blue < 0 < red, range ``+-max|error|``
                   of that image, at iteration 0, the snapshot iterations (default 1, 5,
                   10, 40), every ``snapshot_every`` iterations (default 10) and the last
                   iteration; ``field/<name>_panels`` at the last iteration: truth, fit and
                   error with colour bars (the run directory's ``field.png``).
``final/<key>``    once, at the last step: ``final/iterations``, ``final/wall_s`` (HParams
                   metrics that have no per-iteration curve).
``frames/<key>``   per-frame position errors against the truth, one curve per frame:
                   ``frames/u_err_inf/frame_<f>``, ``frames/u_err_2/frame_<f>``.
``sheet/frame_<f>``  the deformed mesh of one frame coloured by the field, with the target
                   wireframe, at iteration 0 and the snapshot iterations.
=================  ===========================================================================

Scalars are float32 tensor summaries of the ``scalars`` plugin (``add_scalar(...,
new_style=True)``, dtype ``DT_FLOAT``), the form TensorBoard's default loader (the Rust
data server of ``tensorboard --logdir``) reads; it drops ``DT_DOUBLE`` scalars, which
therefore appeared only with ``--load_fast=false``. The exact double values are in
``result.json`` (its ``history`` and final metrics); what TensorBoard shows equals them to
float32 precision (relative ``6e-8``). Read them back as a user sees them through the
server's HTTP API (``/data/plugin/scalars/scalars?run=...&tag=...``, see
``tests/conftest.py``), or with ``EventAccumulator.Tensors(tag)``.

An ``extra`` key that already contains a ``/`` is used verbatim as its tag, so a
callback can choose its own section. The step of every scalar is the outer iteration
(plus ``step_offset`` for a resumed run): iteration 0 is the initial point. The event file
is flushed after every written iteration (``flush_every=1``); :meth:`TensorBoardLogger.resume`
restores what an interrupted run lost, so that every step appears once. With
``log_every = n`` the iterations ``0, n, 2n, ...`` and always the last one are written
(the last one when :meth:`TensorBoardLogger.close` or :meth:`finish` is called).

:meth:`TensorBoardLogger.log_hparams` writes the HParams session (start info with every
``problem.*`` and ``solver.*`` setting, end info) into the same run, without a per-run
experiment summary, so that TensorBoard builds the experiment from all runs of a sweep
(see that method); the metric columns are the scalar tags, e.g. ``fit/misfit``,
``metrics/k_err_rel_aligned``, ``metrics/k_err_rel``, ``metrics/u_err_2``,
``final/iterations``, ``final/wall_s``, with their final values.
"""
from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor
from torch.utils.tensorboard import SummaryWriter
from tensorboard.backend.event_processing.event_file_loader import EventFileLoader
from tensorboard.compat.proto import summary_pb2
from tensorboard.plugins.hparams import api_pb2, plugin_data_pb2
from tensorboard.plugins.hparams import metadata as _hparams_metadata
from tensorboard.plugins.hparams import summary_v2 as _hparams_v2

from ..problems.base import FramedProblem, MeshProblem
from ..records import IterationRecord
from .metrics import METRIC_KEYS
from .pictures import PlotGuard, field_panels, image_extent, supports_field_images
from .plots import (ERROR_CMAP, aligned, colorize, field_figure, frame_errors_figure, save_png,
                    sheet_figure, snapshots_figure, symmetric_range, upscale)

if TYPE_CHECKING:  # pragma: no cover
    from ..problems import InverseProblem

log = logging.getLogger(__name__)

FIT_KEYS = ("misfit", "objective", "tv", "penalty")
#: fitted scalars reported as metrics (dynamic problems: the Rayleigh damping coefficients)
PARAMETER_KEYS = ("alpha_damping", "beta_damping")


def tag_for(key: str) -> str:
    """TensorBoard tag of a record scalar (see the module docstring)."""
    if "/" in key:
        return key
    if key in FIT_KEYS:
        return f"fit/{key}"
    if key in METRIC_KEYS or "_err" in key or key in PARAMETER_KEYS:
        return f"metrics/{key}"
    return f"solver/{key}"


def field_is_chain(problem: "InverseProblem") -> bool:
    """Whether the problem's field is one value per cell of a 1-D chain (plot as a line)."""
    param = problem.parameterization
    param = getattr(param, "field_parameterization", param)   # [field, scalars]: the field
    if param.basis is not None or param.n_field != param.n_params:
        return False
    edges = torch.as_tensor(param.edges).reshape(-1, 2)
    n = param.n_params
    if n == 1:
        return True
    expected = torch.stack([torch.arange(n - 1), torch.arange(1, n)], dim=1)
    return edges.shape == expected.shape and bool(torch.equal(edges.cpu(), expected))


def event_files(logdir: str | Path) -> list[Path]:
    """The TensorBoard event files directly in ``logdir`` (one run), oldest first."""
    logdir = Path(logdir)
    if not logdir.is_dir():
        return []
    return sorted(p for p in logdir.iterdir() if p.is_file() and "tfevents" in p.name)


def scalar_steps(files: Sequence[str | Path]) -> set[tuple[str, int]]:
    """``(tag, step)`` of every scalar in the event ``files`` (legacy ``simple_value`` or a
    tensor of the ``scalars`` plugin), read with TensorBoard's event file reader (every
    event, no sampling). A record cut off by a crash ends the reading of its file."""
    out: set[tuple[str, int]] = set()
    for path in files:
        tags_scalar: dict[str, bool] = {}
        try:
            for event in EventFileLoader(str(path)).Load():
                if not event.HasField("summary"):
                    continue
                for value in event.summary.value:
                    kind = value.WhichOneof("value")
                    if kind == "simple_value":
                        out.add((value.tag, int(event.step)))
                    elif kind == "tensor":
                        if value.HasField("metadata"):
                            tags_scalar[value.tag] = \
                                value.metadata.plugin_data.plugin_name == "scalars"
                        if tags_scalar.get(value.tag):
                            out.add((value.tag, int(event.step)))
        except Exception as e:  # noqa: BLE001  (a damaged file: keep what was read)
            log.warning("could not read all of the event file %s (%s: %s)", path,
                        type(e).__name__, e)
    return out


def flatten(config: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{'solver': {'tau': 1.5}} -> {'solver.tau': 1.5}`` (lists stay whole)."""
    out: dict[str, Any] = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flatten(value, f"{name}."))
        else:
            out[name] = value
    return out


def metric_tag(key: str) -> str:
    """Tag of a final metric of the HParams session: the per-iteration tag of a record key
    (``misfit`` -> ``fit/misfit``, ``k_err_rel`` -> ``metrics/k_err_rel``), else
    ``final/<key>`` (``iterations``, ``wall_s``: one value per run)."""
    if "/" in key or key in FIT_KEYS or key in METRIC_KEYS or key in PARAMETER_KEYS:
        return tag_for(key)
    return f"final/{key}"


def hparam_values(hparams: Mapping[str, Any]) -> dict[str, bool | int | float | str]:
    """Flattened settings as HParams values: bools, numbers and strings as they are,
    other values (lists) as their text; ``None`` ("automatic", e.g. Split Bregman's
    ``mu``) is left out, so that a sweep mixing ``None`` and numbers keeps a numeric
    column (blank where automatic)."""
    out: dict[str, bool | int | float | str] = {}
    for key, value in flatten(hparams).items():
        if value is None:
            continue
        out[key] = value if isinstance(value, (bool, int, float, str)) else str(value)
    return out


def _hparams_summary_pb(tag: str, data: plugin_data_pb2.HParamsPluginData) -> summary_pb2.Summary:
    """A summary holding hparams plugin data (what ``summary_v2`` writes, without TF)."""
    summary = summary_pb2.Summary()
    summary.value.add(tag=tag, metadata=_hparams_metadata.create_summary_metadata(data),
                      tensor=_hparams_metadata.NULL_TENSOR)
    return summary


class TensorBoardLogger:
    """Callback writing one TensorBoard scalar per record entry and iteration.

    Args:
        logdir: directory of the event files (created).
        log_every: write iterations ``0, n, 2n, ...`` and the last one.
        step_offset: added to every step (a resumed run continues where it stopped).
        flush_every: flush the event file every this many written iterations (default 1:
            after every iteration, so that an iteration whose checkpoint was committed is
            on disk when the next one starts; see :meth:`resume`).

    Use as a context manager or call :meth:`close` (which also writes a pending last
    iteration); :meth:`finish` writes the field and hparams of the finished run.
    """

    def __init__(self, logdir: str | Path, log_every: int = 1, step_offset: int = 0,
                 flush_every: int = 1) -> None:
        if log_every < 1:
            raise ValueError(f"log_every must be >= 1, got {log_every}")
        if flush_every < 1:
            raise ValueError(f"flush_every must be >= 1, got {flush_every}")
        self.logdir = Path(logdir)
        self.logdir.mkdir(parents=True, exist_ok=True)
        self.log_every = int(log_every)
        self.step_offset = int(step_offset)
        self.flush_every = int(flush_every)
        # The event files already in logdir, before this writer creates its own.
        self._old_files = event_files(self.logdir)
        self.writer = self._new_writer()
        self._pending: IterationRecord | None = None
        self._last_step: int | None = None
        self._written = 0
        self._closed = False
        self._tag_steps: dict[str, int] = {}    # tag -> last step written
        self._present: set[tuple[str, int]] = set()   # (tag, step) of older files (resume)
        self.resumed_through: int | None = None
        self.start_time = time.time()

    def _new_writer(self, max_wait_s: float = 3.0) -> SummaryWriter:
        """A SummaryWriter whose event file sorts after every older one of ``logdir``.

        TensorBoard (both loaders) reads a run's event files in the order of their names
        (``events.out.tfevents.<unix seconds>.<host>.<pid>...``), and a point whose step
        is not after the last one read for its tag discards the points read at that step
        and later ("preemption", meant for restarted jobs). A file of a resumed run that
        sorted before the interrupted run's file (same second, smaller pid) would have its
        steps discarded by the older ones; so wait for the next second if needed."""
        newest = max((p.name for p in self._old_files), default=None)
        deadline = time.monotonic() + max_wait_s
        while True:
            writer = SummaryWriter(log_dir=str(self.logdir))
            name = Path(writer._get_file_writer().event_writer._file_name).name
            if newest is None or name > newest:
                return writer
            if time.monotonic() > deadline:
                log.warning("the TensorBoard event file %s sorts before the older %s of the "
                            "same run (clock skew between machines?); TensorBoard may hide "
                            "the points of this run that precede older steps", name, newest)
                return writer
            writer.close()
            (self.logdir / name).unlink(missing_ok=True)
            time.sleep(1.0 - time.time() % 1.0 + 0.01)

    # -- per iteration ------------------------------------------------------------------
    def step_of(self, record: IterationRecord) -> int:
        return self.step_offset + record.iteration

    def already_logged(self, step: int) -> bool:
        """Whether ``step`` belongs to the iterations restored by :meth:`resume`."""
        return self.resumed_through is not None and step <= self.resumed_through

    def __call__(self, record: IterationRecord) -> None:
        if self.already_logged(self.step_of(record)):
            self._pending = None    # the checkpoint's iteration, logged by the first run
        elif record.iteration == 0 or record.iteration % self.log_every == 0:
            self._write(record)
            self._pending = None
        else:
            self._pending = record
        return None

    def scalar(self, tag: str, value: float, step: int) -> bool:
        """Write one scalar (float32, see the module docstring); NaN and infinities, and a
        ``(tag, step)`` up to the resumed iteration that the event files found by
        :meth:`resume` already hold, are skipped. Returns whether it was written."""
        value = float(value)
        step = int(step)
        if not math.isfinite(value) or (self.already_logged(step) and (tag, step) in self._present):
            return False
        # new_style: a float32 tensor summary of the scalars plugin (DT_FLOAT), which both
        # TensorBoard loaders (the Rust data server and --load_fast=false) read.
        self.writer.add_scalar(tag, value, step, new_style=True)
        if step >= self._tag_steps.get(tag, step):
            self._tag_steps[tag] = step
        return True

    def _write(self, record: IterationRecord) -> None:
        step = self.step_of(record)
        for key, value in record.scalars().items():
            self.scalar(tag_for(key), value, step)
        self._last_step = step
        self._written += 1
        if self._written % self.flush_every == 0:
            self.writer.flush()

    def resume(self, history_rows: Sequence[Mapping[str, Any]], last_iteration: int) -> int:
        """Continue the TensorBoard curves of an interrupted run in the same ``logdir``.

        Reads the event files that were in ``logdir`` when this logger was created (every
        event, with TensorBoard's own event file reader, no sampling), collects the
        ``(tag, step)`` of their scalars, and writes every scalar of ``history_rows``
        (``{'iteration': step, key: value, ...}`` as in ``result.json``'s ``history``,
        keys mapped by :func:`tag_for`) with ``iteration <= last_iteration`` that comes
        after the last step of its tag in those files: what the interrupted run lost after
        committing its checkpoint and before its event file reached the disk. From then on
        records whose step is ``<= last_iteration`` are not written again (the resumed
        solver's first record, the checkpoint's iteration, was logged by the first run)
        and the curves continue at ``last_iteration + 1``. This logger's event file sorts
        after the older ones (see :meth:`_new_writer`).

        A point missing *before* the last step of its tag is not written: TensorBoard
        would discard that tag's later points (it treats a step that goes back as a
        restart). Scalars at steps ``> last_iteration`` in the old files cannot come
        from a run that commits each checkpoint before logging its iteration; if there
        are some (event files of another run, an older checkpoint) a warning names them;
        TensorBoard shows them until this run writes that tag again, then discards them
        (the same preemption) and shows this run's points.
        Per-frame scalars of :class:`FieldSnapshots` and images are not restored.

        Returns:
            How many scalars were written.
        """
        last_iteration = int(last_iteration)
        present = scalar_steps(self._old_files)
        self._present |= present
        last_present: dict[str, int] = {}
        for tag, step in present:
            last_present[tag] = max(step, last_present.get(tag, step))
        later = sorted({step for _, step in present if step > last_iteration})
        if later:
            log.warning("TensorBoard logdir %s already holds scalars at steps %s after the "
                        "checkpoint's iteration %d (event files of another run?); TensorBoard "
                        "replaces them by this run's points as it writes them", self.logdir,
                        later if len(later) <= 10 else f"{later[:10]} ...", last_iteration)
        written = 0
        for row in sorted(history_rows, key=lambda r: int(r["iteration"])):
            step = int(row["iteration"])
            if step > last_iteration:
                continue
            for key, value in row.items():
                if key == "iteration" or isinstance(value, (str, bool)) or \
                        not isinstance(value, (int, float)):
                    continue
                tag = tag_for(key)
                if step > last_present.get(tag, -1) and self.scalar(tag, value, step):
                    self._present.add((tag, step))
                    written += 1
        for tag, step in last_present.items():
            self._tag_steps[tag] = max(step, self._tag_steps.get(tag, step))
        self.resumed_through = last_iteration
        if self._last_step is None or self._last_step < last_iteration:
            self._last_step = last_iteration
        self.writer.flush()
        return written

    def flush_pending(self) -> None:
        """Write the last iteration if ``log_every`` skipped it."""
        if self._pending is not None:
            self._write(self._pending)
            self._pending = None

    @property
    def last_step(self) -> int | None:
        """Step of the last written iteration (``None`` before the first)."""
        return self._last_step

    # -- once per run ---------------------------------------------------------------------
    def log_config(self, text: str) -> None:
        """The resolved config (YAML) as text, shown in the Text dashboard."""
        self.writer.add_text("config", "```yaml\n" + text + "\n```", self.step_offset)

    def log_field(self, field: Tensor, truth: Tensor | None = None, name: str = "k",
                  chain: bool = False, step: int | None = None) -> None:
        """Histogram of the fitted (and true) field; for a chain, a fitted-vs-true plot."""
        step = self._final_step(step)
        values = field.detach().cpu().reshape(-1)
        self.writer.add_histogram(f"field/{name}", values, step)
        if truth is not None:
            self.writer.add_histogram(f"field/{name}_true", truth.detach().cpu().reshape(-1), step)
        if chain:
            fig = field_figure(values, None if truth is None else truth.detach().cpu(), name,
                               title=f"{name} per cell after {step} iterations")
            self.writer.add_figure(f"field/{name}_profile", fig, step, close=False)

    def log_hparams(self, hparams: Mapping[str, Any], metrics: Mapping[str, float]) -> None:
        """HParams session of this run: ``hparams`` (flattened config) vs final ``metrics``.

        Writes the session start info (every flattened setting, see :func:`hparam_values`)
        and the session end info of the hparams plugin, and no experiment summary: the
        plugin then builds the experiment from the session infos of every run under the
        logdir (the union of their settings, a type per setting that fits every run),
        so a sweep over solvers or problems shows every setting. Its metric columns are
        the runs' scalar tags: ``metrics`` that are record keys (``misfit``,
        ``k_err_rel_aligned``, ...) are their per-iteration tags, whose last value the
        dashboard shows (written again at the last step if that step lacks them); any
        other key (``iterations``, ``wall_s``) is written once as ``final/<key>``.
        """
        self.flush_pending()
        step = self._final_step(None)
        for key, value in metrics.items():
            value = float(value)
            tag = metric_tag(key)
            if self._tag_steps.get(tag) != step:
                self.scalar(tag, value, step)
        values = hparam_values(hparams)
        file_writer = self.writer._get_file_writer()
        file_writer.add_summary(_hparams_v2.hparams_pb(values, start_time_secs=self.start_time),
                                step)
        end = plugin_data_pb2.SessionEndInfo(status=api_pb2.STATUS_SUCCESS,
                                             end_time_secs=time.time())
        file_writer.add_summary(_hparams_summary_pb(_hparams_metadata.SESSION_END_INFO_TAG,
                                                    plugin_data_pb2.HParamsPluginData(
                                                        session_end_info=end)), step)

    def finish(self, problem: "InverseProblem", theta: Tensor, metrics: Mapping[str, float],
               hparams: Mapping[str, Any] | None = None, guard: PlotGuard | None = None) -> None:
        """End of a run: pending iteration, field histogram/plot, hparams, then close.

        ``metrics``: the final metrics of the HParams session (:meth:`log_hparams`);
        ``guard`` reports a failure to draw the field once instead of raising.
        """
        self.flush_pending()
        field = problem.field(theta)
        (guard or PlotGuard()).run(f"TensorBoard field/{problem.field_name}", self.log_field,
                                   field, problem.field_true, problem.field_name,
                                   field_is_chain(problem))
        if hparams is not None:
            self.log_hparams(hparams, metrics)
        self.close()

    def _final_step(self, step: int | None) -> int:
        if step is not None:
            return int(step)
        return self._last_step if self._last_step is not None else self.step_offset

    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        if self._closed:
            return
        self.flush_pending()
        self.writer.flush()
        self.writer.close()
        self._closed = True

    def __enter__(self) -> "TensorBoardLogger":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def error_image_tag(problem: "InverseProblem") -> str:
    """Tag of the error image: ``field/<name>_error_aligned_image`` for a scale-free problem
    (the fit is scaled onto the truth first), ``field/<name>_error_image`` otherwise."""
    kind = "error_aligned" if problem.scale_free else "error"
    return f"field/{problem.field_name}_{kind}_image"


class FieldSnapshots:
    """Callback drawing a 2-D field during a fit (TensorBoard images and run-dir PNGs).

    Needs a problem with ``field_image(field) -> (H, W)`` (row 0 at the top); uses, when
    present, ``frame_errors(x) -> {'u_err_inf': (F,), 'u_err_2': (F,)}``,
    ``frame_names()``, ``mesh`` (``points``, ``cells``, ``extent``), ``x_true`` and
    ``default_sheet_frame``.

    TensorBoard images (nearest-neighbour upscaled by an integer factor so that the longer
    side has at least ``image_min_size`` pixels):

    * ``field/<name>_true_image`` once, at the first step;
    * ``field/<name>_image`` (the fit; for a scale-free problem multiplied by the best
      scale onto the truth, fixed colour range ``[min(0, truth), 1.15 max truth]``) and
      ``field/<name>_error_aligned_image`` (``field/<name>_error_image`` when not
      scale-free: ``a k - k_true``, blue negative, red positive, symmetric range
      ``+-max|error|`` of that image) at iteration 0, the ``snapshot_iterations``, every
      ``every`` iterations and the last iteration (written by :meth:`finish`);
    * ``field/<name>_panels`` at the last iteration: truth, fit and error with colour bars
      (the run directory's ``field.png``).

    Args:
        problem: the inverse problem.
        tb: the run's :class:`TensorBoardLogger` (its writer and step offset are used).
        run_dir: where :meth:`finish` writes ``snapshots.png``, ``frame_errors.png`` and
            ``sheet_frame<f>.png`` (``None``: no files).
        snapshot_iterations: iterations kept for ``snapshots.png`` (the seed's figure)
            and drawn in TensorBoard.
        every: also draw every ``every`` iterations (0: never).
        sheet_frame: frame whose deformed mesh is drawn (default: the problem's choice).
        guard: reports a drawing failure once instead of failing the fit (shared with
            the run's other pictures).
        image_min_size: pixels of the longer side of a TensorBoard image (at least).
    """

    def __init__(self, problem: "InverseProblem", tb: TensorBoardLogger, run_dir: str | Path | None = None,
                 snapshot_iterations: tuple[int, ...] | list[int] = (1, 5, 10, 40),
                 every: int = 10, sheet_frame: int | None = None,
                 guard: PlotGuard | None = None, image_min_size: int = 256) -> None:
        if not supports_field_images(problem):
            raise ValueError(f"problem {problem.name!r} cannot draw its field as an image")
        if every < 0:
            raise ValueError(f"snapshot interval must be >= 0, got {every}")
        if any(int(i) < 0 for i in snapshot_iterations):
            raise ValueError(f"snapshot iterations must be >= 0, got {list(snapshot_iterations)}")
        if image_min_size < 1:
            raise ValueError(f"image_min_size must be >= 1 pixel, got {image_min_size}")
        self.problem = problem
        self.tb = tb
        self.run_dir = None if run_dir is None else Path(run_dir)
        self.snapshot_iterations = sorted({int(i) for i in snapshot_iterations})
        self.every = int(every)
        self.guard = guard or PlotGuard()
        self.image_min_size = int(image_min_size)
        truth = problem.field_true
        self.truth = None if truth is None else truth.detach().cpu().numpy()
        self.name = problem.field_name
        self.error_tag = error_image_tag(problem)
        self.vmin = 0.0 if self.truth is None else float(min(0.0, self.truth.min()))
        self.vmax = None if self.truth is None else float(self.truth.max()) * 1.15
        framed = isinstance(problem, FramedProblem)
        self.n_frames = int(problem.n_frames) if framed else 0
        if sheet_frame is not None:
            frame = sheet_frame
        else:
            frame = problem.default_sheet_frame if framed else 0
        if self.n_frames and not -self.n_frames <= int(frame) < self.n_frames:
            raise ValueError(f"sheet_frame={frame} is not a frame of {problem.name} "
                             f"(0..{self.n_frames - 1})")
        self.sheet_frame = int(frame) % self.n_frames if self.n_frames else 0
        # The state x is needed only for per-frame errors and the deformed-mesh figure.
        self.framed = framed
        self.mesh = problem.mesh if isinstance(problem, MeshProblem) else None
        self._needs_state = framed or self.mesh is not None
        self.snapshots: dict[int, tuple[np.ndarray, np.ndarray | None]] = {}
        self.error_history: dict[int, np.ndarray] = {}
        self.imaged_steps: list[int] = []
        self._last: tuple[int, Tensor] | None = None
        self._wrote_truth = False

    # -- helpers ------------------------------------------------------------------------
    def _field(self, theta: Tensor) -> np.ndarray:
        field = self.problem.field(theta).detach().cpu().numpy()
        scaled, _ = aligned(field, self.truth if self.problem.scale_free else None)
        return scaled

    def _image(self, field: np.ndarray) -> np.ndarray:
        return np.asarray(self.problem.field_image(torch.as_tensor(field)))

    def _range(self, image: np.ndarray) -> tuple[float, float]:
        if self.vmax is not None:
            return self.vmin, self.vmax
        return float(image.min()), float(image.max())

    def _rgb(self, image: np.ndarray, vmin: float, vmax: float, cmap: str = "viridis") -> np.ndarray:
        return upscale(colorize(image, vmin, vmax, cmap), self.image_min_size)

    def _state(self, theta: Tensor) -> Tensor | None:
        if not self._needs_state:
            return None
        with torch.no_grad():   # a cache hit: the solver has just evaluated this point
            return self.problem.simulate(self.problem.simulation_input(theta)).detach()

    def _errors(self, x: Tensor | None) -> dict[str, np.ndarray] | None:
        if x is None or not self.framed or getattr(self.problem, "x_true", None) is None:
            return None
        return self.problem.frame_errors(x)

    def _sheet(self, field: np.ndarray, x: Tensor | None, title: str):
        mesh = self.mesh
        if mesh is None or x is None or x.shape[-1] != 2:
            return None
        f = self.sheet_frame
        target = None
        if getattr(self.problem, "x_true", None) is not None:
            target = self.problem.x_true[f].detach().cpu().numpy()
        return sheet_figure(x[f].cpu().numpy(), mesh.cells, field, target=target,
                            rest=mesh.points, vmin=self.vmin, vmax=self.vmax, name=self.name,
                            title=title)

    def wants_image(self, step: int) -> bool:
        return step in self.snapshot_iterations or step == 0 or \
            (self.every > 0 and step % self.every == 0)

    def _write_truth(self) -> None:
        image = self._image(self.truth)
        self.tb.writer.add_image(f"field/{self.name}_true_image",
                                 self._rgb(image, *self._range(image)), self.tb.step_offset,
                                 dataformats="HWC")

    def _write_images(self, step: int, theta: Tensor) -> tuple[np.ndarray, np.ndarray]:
        """Field and error images of ``theta`` at ``step``; returns ``(field, image)``."""
        field = self._field(theta)
        image = self._image(field)
        writer = self.tb.writer
        writer.add_image(f"field/{self.name}_image", self._rgb(image, *self._range(image)),
                         step, dataformats="HWC")
        if self.truth is not None:
            error = image - self._image(self.truth)
            writer.add_image(self.error_tag, self._rgb(error, *symmetric_range(error), ERROR_CMAP),
                             step, dataformats="HWC")
        self.imaged_steps.append(step)
        return field, image

    # -- the callback -------------------------------------------------------------------
    def __call__(self, record: IterationRecord) -> None:
        step = self.tb.step_of(record)
        if self.tb.already_logged(step):
            # restored by TensorBoardLogger.resume: the interrupted run drew this step
            self._wrote_truth = True
            self._last = (step, record.theta)
            self.imaged_steps.append(step)
            return None
        if not self._wrote_truth and self.truth is not None:
            self._wrote_truth = True
            self.guard.run(f"TensorBoard image field/{self.name}_true_image", self._write_truth)
        x = self._state(record.theta)
        errors = self._errors(x)
        if errors is not None:
            for key, values in errors.items():
                for f, value in enumerate(values):
                    self.tb.scalar(f"frames/{key}/frame_{f}", value, step)
            self.error_history[step] = np.asarray(errors["u_err_inf"])
        self._last = (step, record.theta)
        if self.wants_image(step):
            self.guard.run(f"TensorBoard images of iteration {step}", self._snapshot, step,
                           record.theta, x, errors)
        return None

    def _snapshot(self, step: int, theta: Tensor, x: Tensor | None,
                  errors: dict[str, np.ndarray] | None) -> None:
        field, image = self._write_images(step, theta)
        if step in self.snapshot_iterations or step == 0:
            # the mesh figure (a matplotlib render, ~0.3 s) only at the snapshots
            figure = self._sheet(field, x, f"frame {self.sheet_frame}, iteration {step}")
            if figure is not None:
                self.tb.writer.add_figure(f"sheet/frame_{self.sheet_frame}", figure, step,
                                          close=False)
        if step in self.snapshot_iterations:
            self.snapshots[step] = (image, None if errors is None else
                                    np.asarray(errors["u_err_inf"]))

    # -- end of the run -----------------------------------------------------------------
    def finish(self) -> list[Path]:
        """Last iteration's images and the ``field/<name>_panels`` figure in TensorBoard;
        ``snapshots.png``, ``frame_errors.png`` and ``sheet_frame<f>.png`` in ``run_dir``.

        Returns the files written (a drawing that failed is reported once and left out).
        """
        if self._last is None:
            return []
        last_step, last_theta = self._last
        if last_step not in self.imaged_steps:
            self.guard.run(f"TensorBoard images of iteration {last_step}", self._write_images,
                           last_step, last_theta)
        panels = self.guard.run(f"TensorBoard figure field/{self.name}_panels", field_panels,
                                self.problem, self.problem.field(last_theta),
                                f"{self.problem.name}: {self.name} after {last_step} iterations")
        if panels is not None:
            self.guard.run(f"TensorBoard figure field/{self.name}_panels",
                           self.tb.writer.add_figure, f"field/{self.name}_panels", panels,
                           last_step, close=False)
        if self.run_dir is None:
            return []
        self.run_dir.mkdir(parents=True, exist_ok=True)
        written = self.guard.run("snapshots.png / frame_errors.png / sheet figure",
                                 self._write_files, last_step, last_theta)
        return written or []

    def _write_files(self, last_step: int, last_theta: Tensor) -> list[Path]:
        written: list[Path] = []
        field = self._field(last_theta)
        image = self._image(field)
        x = self._state(last_theta)
        errors = self._errors(x)
        panels: list[tuple[str, np.ndarray]] = []
        panel_errors: list[np.ndarray | None] = []
        if self.truth is not None:
            panels.append((f"true {self.name}", self._image(self.truth)))
            panel_errors.append(None)
        for step in self.snapshot_iterations:
            if step in self.snapshots:
                snap, err = self.snapshots[step]
                panels.append((f"iteration {step}", snap))
                panel_errors.append(err)
        if last_step not in self.snapshots:
            panels.append((f"iteration {last_step} (last)", image))
            panel_errors.append(None if errors is None else np.asarray(errors["u_err_inf"]))
        extent = image_extent(self.problem, image)
        vmin, vmax = self._range(image)
        scaled = " (scaled onto the truth)" if self.problem.scale_free and self.truth is not None else ""
        fig = snapshots_figure(panels, extent, vmin, vmax, self.name, panel_errors,
                               title=f"{self.problem.name}: {self.name}{scaled}")
        path = self.run_dir / "snapshots.png"
        save_png(fig, path)
        written.append(path)
        if self.error_history:
            labels = self.problem.frame_names() if self.framed else None
            fig = frame_errors_figure(self.error_history, labels,
                                      title=f"{self.problem.name}: position error per frame")
            path = self.run_dir / "frame_errors.png"
            save_png(fig, path)
            written.append(path)
        fig = self._sheet(field, x, f"{self.problem.name}: frame {self.sheet_frame} after "
                                    f"{last_step} iterations")
        if fig is not None:
            path = self.run_dir / f"sheet_frame{self.sheet_frame}.png"
            save_png(fig, path)
            written.append(path)
        return written
