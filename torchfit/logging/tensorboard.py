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
=================  ===========================================================================

Scalars are written in double precision (new-style tensor summaries of the ``scalars``
plugin, ``DT_DOUBLE``), so the logged misfit equals the one in ``result.json`` exactly;
read them back with ``EventAccumulator.Tensors(tag)`` (not ``Scalars``, which holds only
legacy float32 values) or TensorBoard's data provider.

An ``extra`` key that already contains a ``/`` is used verbatim as its tag, so a
callback can choose its own section. The step of every scalar is the outer iteration
(plus ``step_offset`` for a resumed run): iteration 0 is the initial point. With
``log_every = n`` the iterations ``0, n, 2n, ...`` and always the last one are written
(the last one when :meth:`TensorBoardLogger.close` or :meth:`finish` is called).

:meth:`TensorBoardLogger.log_hparams` writes the HParams summary into the same run
(no timestamped sub-run as ``SummaryWriter.add_hparams`` would make); its metrics are
the per-iteration tags above, so the HParams dashboard shows their final values.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np
import torch
from torch import Tensor
from torch.utils.tensorboard import SummaryWriter
from torch.utils.tensorboard.summary import hparams as _hparams_summary

from ..solvers import IterationRecord
from .metrics import METRIC_KEYS

if TYPE_CHECKING:  # pragma: no cover
    from ..problems import InverseProblem

FIT_KEYS = ("misfit", "objective", "tv", "penalty")


def tag_for(key: str) -> str:
    """TensorBoard tag of a record scalar (see the module docstring)."""
    if "/" in key:
        return key
    if key in FIT_KEYS:
        return f"fit/{key}"
    if key in METRIC_KEYS or "_err" in key:
        return f"metrics/{key}"
    return f"solver/{key}"


def field_is_chain(problem: "InverseProblem") -> bool:
    """Whether the problem's field is one value per cell of a 1-D chain (plot as a line)."""
    param = problem.parameterization
    if getattr(param, "basis", None) is not None or param.n_field != param.n_params:
        return False
    edges = torch.as_tensor(param.edges).reshape(-1, 2)
    n = param.n_params
    if n == 1:
        return True
    expected = torch.stack([torch.arange(n - 1), torch.arange(1, n)], dim=1)
    return edges.shape == expected.shape and bool(torch.equal(edges.cpu(), expected))


def _hparam_value(value: Any) -> bool | int | float | str:
    if isinstance(value, (bool, int, float, str)):
        return value
    if value is None:
        return "None"
    return str(value)


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


def field_figure(field: Tensor, truth: Tensor | None = None, name: str = "k",
                 title: str | None = None):
    """Matplotlib figure of a 1-D field per cell (step plot), with the truth if given."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 3.2), dpi=100, layout="constrained")
    ax = fig.add_subplot()
    cells = np.arange(int(field.numel()))
    if truth is not None:
        ax.step(cells, truth.detach().cpu().numpy(), where="mid", color="0.4", lw=2.0,
                label="true")
    ax.step(cells, field.detach().cpu().numpy(), where="mid", color="C0", lw=1.2,
            label="fitted")
    ax.set_xlabel("cell")
    ax.set_ylabel(name)
    if title:
        ax.set_title(title)
    ax.legend(loc="best")
    ax.grid(alpha=0.3)
    return fig


class TensorBoardLogger:
    """Callback writing one TensorBoard scalar per record entry and iteration.

    Args:
        logdir: directory of the event files (created).
        log_every: write iterations ``0, n, 2n, ...`` and the last one.
        step_offset: added to every step (a resumed run continues where it stopped).
        flush_every: flush the event file every this many written iterations.

    Use as a context manager or call :meth:`close` (which also writes a pending last
    iteration); :meth:`finish` writes the field and hparams of the finished run.
    """

    def __init__(self, logdir: str | Path, log_every: int = 1, step_offset: int = 0,
                 flush_every: int = 10) -> None:
        if log_every < 1:
            raise ValueError(f"log_every must be >= 1, got {log_every}")
        self.logdir = Path(logdir)
        self.logdir.mkdir(parents=True, exist_ok=True)
        self.log_every = int(log_every)
        self.step_offset = int(step_offset)
        self.flush_every = max(1, int(flush_every))
        self.writer = SummaryWriter(log_dir=str(self.logdir))
        self._pending: IterationRecord | None = None
        self._last_step: int | None = None
        self._written = 0
        self._closed = False

    # -- per iteration ------------------------------------------------------------------
    def step_of(self, record: IterationRecord) -> int:
        return self.step_offset + record.iteration

    def __call__(self, record: IterationRecord) -> None:
        if record.iteration == 0 or record.iteration % self.log_every == 0:
            self._write(record)
            self._pending = None
        else:
            self._pending = record
        return None

    def _write(self, record: IterationRecord) -> None:
        step = self.step_of(record)
        for key, value in record.scalars().items():
            if not math.isfinite(value):
                continue
            self.writer.add_scalar(tag_for(key), value, step, new_style=True,
                                   double_precision=True)
        self._last_step = step
        self._written += 1
        if self._written % self.flush_every == 0:
            self.writer.flush()

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

        ``metrics`` are record keys (``misfit``, ``k_err_rel``, ...); the HParams dashboard
        shows the last value of their per-iteration tags, which are written here too so
        that the final value is present whatever ``log_every`` was.
        """
        self.flush_pending()
        step = self._final_step(None)
        values = {k: _hparam_value(v) for k, v in flatten(hparams).items()}
        finite = {k: float(v) for k, v in metrics.items() if math.isfinite(float(v))}
        tags = {tag_for(k): v for k, v in finite.items()}
        exp, ssi, sei = _hparams_summary(values, tags)
        file_writer = self.writer._get_file_writer()
        for summary in (exp, ssi, sei):
            file_writer.add_summary(summary, step)

    def finish(self, problem: "InverseProblem", theta: Tensor, metrics: Mapping[str, float],
               hparams: Mapping[str, Any] | None = None) -> None:
        """End of a run: pending iteration, field histogram/plot, hparams, then close."""
        self.flush_pending()
        field = problem.field(theta)
        self.log_field(field, problem.field_true, problem.field_name, field_is_chain(problem))
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
