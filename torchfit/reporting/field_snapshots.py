"""The 2-D field of a fit as it evolves: TensorBoard images, per-frame errors, snapshot PNGs.

:class:`FieldSnapshots` (poisson2d, membrane2d: a
:class:`~torchfit.problems.base.FieldImageProblem`) writes ``field/<name>_true_image``
once, ``field/<name>_image`` and the (aligned) error image at iteration 0, the snapshot
iterations, every ``every`` iterations and the last one, ``field/<name>_panels`` at the
last one, per-frame position errors ``frames/u_err_inf/frame_<f>`` and
``frames/u_err_2/frame_<f>`` of a framed problem every iteration, and the deformed mesh
``sheet/frame_<f>`` at the snapshots; at the end ``snapshots.png`` (the seed's figure),
``frame_errors.png`` and ``sheet_frame<f>.png`` in the run directory.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from ..problems import FramedProblem, MeshProblem
from .evaluation import Evaluation
from .figures import (ERROR_CMAP, aligned, colorize, field_panels, frame_errors_figure,
                      image_extent, save_png, sheet_figure, snapshots_figure,
                      supports_field_images, symmetric_range, upscale)
from .guard import PlotGuard

if TYPE_CHECKING:  # pragma: no cover
    from ..problems import InverseProblem
    from .tensorboard import TensorBoardLogger


def error_image_tag(problem: "InverseProblem") -> str:
    """Tag of the error image: ``field/<name>_error_aligned_image`` for a scale-free problem
    (the fit is scaled onto the truth first), ``field/<name>_error_image`` otherwise."""
    kind = "error_aligned" if problem.scale_free else "error"
    return f"field/{problem.field_name}_{kind}_image"


class FieldSnapshots:
    """Observer drawing a 2-D field during a fit (TensorBoard images and run-dir PNGs).

    Called with the run's :class:`~torchfit.reporting.evaluation.Evaluation` of every
    record, and :meth:`finish` with the one at the end. Needs a problem with
    ``field_image(field) -> (H, W)`` (row 0 at the top); uses, for a
    :class:`~torchfit.problems.base.FramedProblem`, ``frame_errors(x)`` and
    ``frame_names()``, for a :class:`~torchfit.problems.base.MeshProblem` its ``mesh``
    (``points``, ``cells``, ``extent``), and ``x_true``.

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
        self._last_step: int | None = None
        self._wrote_truth = False

    # -- helpers ------------------------------------------------------------------------
    def _field(self, evaluation: Evaluation) -> np.ndarray:
        field = evaluation.field.detach().cpu().numpy()
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

    def _state(self, evaluation: Evaluation) -> Tensor | None:
        return evaluation.state if self._needs_state else None

    def _errors(self, x: Tensor | None) -> dict[str, np.ndarray] | None:
        if x is None or not self.framed or self.problem.x_true is None:
            return None
        return self.problem.frame_errors(x)

    def _sheet(self, field: np.ndarray, x: Tensor | None, title: str):
        mesh = self.mesh
        if mesh is None or x is None or x.shape[-1] != 2:
            return None
        f = self.sheet_frame
        target = None
        if self.problem.x_true is not None:
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

    def _write_images(self, step: int, evaluation: Evaluation) -> tuple[np.ndarray, np.ndarray]:
        """Field and error images of ``evaluation`` at ``step``; returns ``(field, image)``."""
        field = self._field(evaluation)
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

    # -- the observer -------------------------------------------------------------------
    def __call__(self, evaluation: Evaluation) -> None:
        assert evaluation.record is not None, "an observer reads the evaluation of a record"
        step = self.tb.step_of(evaluation.record)
        if self.tb.already_logged(step):
            # restored by TensorBoardLogger.resume: the interrupted run drew this step
            self._wrote_truth = True
            self._last_step = step
            self.imaged_steps.append(step)
            return None
        if not self._wrote_truth and self.truth is not None:
            self._wrote_truth = True
            self.guard.run(f"TensorBoard image field/{self.name}_true_image", self._write_truth)
        x = self._state(evaluation)
        errors = self._errors(x)
        if errors is not None:
            for key, values in errors.items():
                for f, value in enumerate(values):
                    self.tb.scalar(f"frames/{key}/frame_{f}", value, step)
            self.error_history[step] = np.asarray(errors["u_err_inf"])
        self._last_step = step
        if self.wants_image(step):
            self.guard.run(f"TensorBoard images of iteration {step}", self._snapshot, step,
                           evaluation, x, errors)
        return None

    def _snapshot(self, step: int, evaluation: Evaluation, x: Tensor | None,
                  errors: dict[str, np.ndarray] | None) -> None:
        field, image = self._write_images(step, evaluation)
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
    def finish(self, final: Evaluation) -> list[Path]:
        """Last iteration's images (``final``: the run's evaluation at its end) and the
        ``field/<name>_panels`` figure in TensorBoard; ``snapshots.png``,
        ``frame_errors.png`` and ``sheet_frame<f>.png`` in ``run_dir``.

        Returns the files written (a drawing that failed is reported once and left out).
        """
        if self._last_step is None:
            return []
        last_step = self._last_step
        if last_step not in self.imaged_steps:
            self.guard.run(f"TensorBoard images of iteration {last_step}", self._write_images,
                           last_step, final)
        panels = self.guard.run(f"TensorBoard figure field/{self.name}_panels", field_panels,
                                self.problem, final.field,
                                f"{self.problem.name}: {self.name} after {last_step} iterations")
        if panels is not None:
            self.guard.run(f"TensorBoard figure field/{self.name}_panels",
                           self.tb.writer.add_figure, f"field/{self.name}_panels", panels,
                           last_step, close=False)
        if self.run_dir is None:
            return []
        self.run_dir.mkdir(parents=True, exist_ok=True)
        written = self.guard.run("snapshots.png / frame_errors.png / sheet figure",
                                 self._write_files, last_step, final)
        return written or []

    def _write_files(self, last_step: int, final: Evaluation) -> list[Path]:
        written: list[Path] = []
        field = self._field(final)
        image = self._image(field)
        x = self._state(final)
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
