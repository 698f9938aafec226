"""TensorBoard output of a fit: per-iteration scalars, the fitted field, hparams, exact resume.

:class:`TensorBoardLogger` is a record callback: one scalar per record entry and written
iteration, tagged by :func:`~torchfit.reporting.tags.tag_for` (``fit/``, ``metrics/``,
``solver/``); the step is the outer iteration plus ``step_offset`` (a resumed run), and
iteration 0 is the initial point. With ``log_every = n`` the iterations ``0, n, 2n, ...``
and always the last one are written. At the end of a run (:meth:`TensorBoardLogger.finish`):
``field/<name>`` histograms of the fit and the truth (a 1-D chain: the image
``field/<name>_profile``), ``final/iterations``, ``final/wall_s`` and the HParams session
(every ``problem.*`` and ``solver.*`` setting against the final metrics, no per-run
experiment summary, so that TensorBoard builds one experiment from all runs of a sweep).
``config`` at the start: the resolved config as text.

Scalars are float32 tensor summaries of the ``scalars`` plugin (``new_style=True``), the
form TensorBoard's default loader reads; the exact doubles are in ``result.json``. The
event file is flushed after every written iteration; :meth:`TensorBoardLogger.resume`
restores what an interrupted run lost, so that every step appears once.
"""
from __future__ import annotations

import functools
import logging
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence, TypeVar

from torch import Tensor
from torch.utils.tensorboard import SummaryWriter
from tensorboard.backend.event_processing.event_file_loader import EventFileLoader
from tensorboard.compat.proto import summary_pb2
from tensorboard.plugins.hparams import api_pb2, plugin_data_pb2
from tensorboard.plugins.hparams import metadata as _hparams_metadata
from tensorboard.plugins.hparams import summary_v2 as _hparams_v2

from ..records import IterationRecord
from .figures import field_figure, field_is_chain
from .guard import PlotGuard
from .tags import hparam_values, metric_tag, tag_for

if TYPE_CHECKING:  # pragma: no cover
    from ..problems import InverseProblem

log = logging.getLogger(__name__)


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


def _hparams_summary_pb(tag: str, data: plugin_data_pb2.HParamsPluginData) -> summary_pb2.Summary:
    """A summary holding hparams plugin data (what ``summary_v2`` writes, without TF)."""
    summary = summary_pb2.Summary()
    summary.value.add(tag=tag, metadata=_hparams_metadata.create_summary_metadata(data),
                      tensor=_hparams_metadata.NULL_TENSOR)
    return summary


_Method = TypeVar("_Method", bound=Callable[..., Any])


def _names_its_file(method: _Method) -> _Method:
    """An ``OSError`` without a file name from the writer (its thread's full disk, re-raised
    at the next call) gets the event file's name: the app's one line says what was being
    written."""
    @functools.wraps(method)
    def wrapper(self: "TensorBoardLogger", *args: Any, **kwargs: Any) -> Any:
        try:
            return method(self, *args, **kwargs)
        except OSError as error:
            if error.errno is None or error.filename:
                raise
            raise OSError(error.errno, error.strerror or str(error),
                          str(self.event_file)) from error
    return wrapper  # type: ignore[return-value]


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
            try:
                writer = SummaryWriter(log_dir=str(self.logdir))
            except OSError as error:        # a full disk as it writes the file's header
                if error.errno is None or error.filename:
                    raise
                new = [f for f in event_files(self.logdir) if f not in self._old_files]
                raise OSError(error.errno, error.strerror or str(error),
                              str(new[-1] if new else self.logdir)) from error
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
    @property
    def event_file(self) -> Path:
        """The event file this logger writes."""
        return Path(self.writer._get_file_writer().event_writer._file_name)

    def step_of(self, record: IterationRecord) -> int:
        return self.step_offset + record.iteration

    def already_logged(self, step: int) -> bool:
        """Whether ``step`` belongs to the iterations restored by :meth:`resume`."""
        return self.resumed_through is not None and step <= self.resumed_through

    @_names_its_file
    def __call__(self, record: IterationRecord) -> None:
        if self.already_logged(self.step_of(record)):
            self._pending = None    # the checkpoint's iteration, logged by the first run
        elif record.iteration == 0 or record.iteration % self.log_every == 0:
            self._write(record)
            self._pending = None
        else:
            self._pending = record
        return None

    @_names_its_file
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

    @_names_its_file
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

    @_names_its_file
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
    @_names_its_file
    def log_config(self, text: str) -> None:
        """The resolved config (YAML) as text, shown in the Text dashboard."""
        self.writer.add_text("config", "```yaml\n" + text + "\n```", self.step_offset)

    @_names_its_file
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

    @_names_its_file
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

    @_names_its_file
    def finish(self, problem: "InverseProblem", field: Tensor, metrics: Mapping[str, float],
               hparams: Mapping[str, Any] | None = None, guard: PlotGuard | None = None) -> None:
        """End of a run: pending iteration, histogram/plot of the fitted ``field``, hparams,
        then close.

        ``metrics``: the final metrics of the HParams session (:meth:`log_hparams`);
        ``guard`` reports a failure to draw the field once instead of raising.
        """
        self.flush_pending()
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

    @_names_its_file
    def flush(self) -> None:
        self.writer.flush()

    @_names_its_file
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
