"""Outputs of a dynamic fit (``problem.dynamic=true``): errors over time and frame strips.

:class:`MotionOutputs` is an observer of :func:`torchfit.run.fit` for a
:class:`~torchfit.problems.base.MotionProblem`: from the run's evaluations it records the
position error at every output time (``u_err_inf`` per time, against the noise-free truth)
at iteration 0, the snapshot iterations and the last iteration, and writes

TensorBoard
    ``motion/time_errors`` (figure: max position error against time, one curve per
    recorded iteration) and ``motion/frames_strip`` (figure: simulated against target
    frames at a few output times) at iteration 0 and at the last iteration; the
    per-time error curve of the last iteration and of the initial guess as scalars whose
    step is the output-time index: ``time/u_err_inf``, ``time/u_err_inf_initial``.
run directory
    ``time_errors.png`` and ``frames_strip.png`` (the same figures, last iteration).

The strip is drawn for a chain (1-D) or a sheet (2-D); a 3-D body has no strip here: its
frames are drawn by the body's own pictures (``frame_comparison.png``, the point cache).

Damping coefficients and their errors (``alpha_damping``, ``beta_damping``,
``alpha_damping_err_rel``, ``beta_damping_err_rel``) are metrics of the problem: per-iteration scalars like every metric.
Drawing failures go through the run's :class:`~.guard.PlotGuard`.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np
from torch import Tensor

from ..problems import MeshProblem
from .evaluation import Evaluation
from .figures import save_png
from .guard import PlotGuard

if TYPE_CHECKING:  # pragma: no cover
    from ..problems import InverseProblem
    from .tensorboard import TensorBoardLogger

TIME_ERRORS_PNG = "time_errors.png"
FRAMES_STRIP_PNG = "frames_strip.png"


def time_errors_figure(times: np.ndarray, history: dict[int, np.ndarray], title: str | None = None):
    """Max position error against time, one curve per recorded iteration."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 3.4), dpi=100, layout="constrained")
    ax = fig.add_subplot()
    for i, step in enumerate(sorted(history)):
        ax.semilogy(times, np.maximum(history[step], 1e-300), marker=".", lw=1.2,
                    label=f"iteration {step}", color=f"C{i % 10}")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("max |x - x_true|")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    if title:
        ax.set_title(title, fontsize=9)
    return fig


def strip_frames(n_frames: int, count: int = 6) -> list[int]:
    """``count`` output-time indices spread over ``0 .. n_frames - 1`` (last included)."""
    return sorted({int(round(i)) for i in np.linspace(0, n_frames - 1, min(count, n_frames))})


def frames_strip_figure(times: Sequence[float], simulated: np.ndarray, target: np.ndarray,
                        cells: np.ndarray | None = None, values: np.ndarray | None = None,
                        name: str = "E", title: str | None = None):
    """Simulated against target frames, one panel per frame.

    Args:
        times: ``(P,)`` the frames' times (s).
        simulated, target: ``(P, n, d)`` positions (``d = 1``: a chain drawn as position
            against node; ``d = 2``: a triangle mesh, ``cells`` ``(m, 3)``, coloured by
            ``values`` ``(m,)``, the target as a wireframe).
    """
    from matplotlib.figure import Figure

    panels = len(times)
    dim = simulated.shape[-1]
    if dim == 1:
        fig = Figure(figsize=(1.6 * panels + 0.8, 3.6), dpi=100, layout="constrained")
        axes = fig.subplots(1, panels, sharey=True, squeeze=False)[0]
        nodes = np.arange(simulated.shape[1])
        for ax, t, sim, tgt in zip(axes, times, simulated, target):
            ax.plot(nodes, tgt[:, 0], "o", ms=2.5, color="0.45", label="target")
            ax.plot(nodes, sim[:, 0], "-", lw=1.3, color="C0", label="simulated")
            ax.set_title(f"t = {t:.3g} s", fontsize=8)
            ax.set_xlabel("node", fontsize=7)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
        axes[0].set_ylabel("position along gravity", fontsize=8)
        axes[0].invert_yaxis()
        axes[0].legend(fontsize=6)
    else:
        from matplotlib.tri import Triangulation

        fig = Figure(figsize=(3.0 * min(panels, 3) + 0.6, 1.6 * ((panels + 2) // 3) + 0.6),
                     dpi=100, layout="constrained")
        axes = fig.subplots((panels + 2) // 3, min(panels, 3), squeeze=False).reshape(-1)
        coll = None
        for ax, t, sim, tgt in zip(axes, times, simulated, target):
            tri = Triangulation(sim[:, 0], sim[:, 1], cells)
            coll = ax.tripcolor(tri, facecolors=values, cmap="viridis", edgecolors="none")
            ax.triplot(Triangulation(tgt[:, 0], tgt[:, 1], cells), color="k", lw=0.12, alpha=0.6)
            ax.set_aspect("equal")
            ax.set_title(f"t = {t:.3g} s", fontsize=8)
            ax.tick_params(labelsize=6)
        for ax in axes[panels:]:
            ax.set_visible(False)
        if coll is not None:
            fig.colorbar(coll, ax=list(axes[:panels]), shrink=0.7, label=name)
    if title:
        fig.suptitle(title, fontsize=9)
    return fig


class MotionOutputs:
    """Observer recording per-time errors of a dynamic fit and drawing its frame strips
    (module docstring): called with the run's evaluation of every record, :meth:`finish`
    with the one at the end.

    Args:
        problem: a :class:`~torchfit.problems.base.MotionProblem` with a truth.
        tb: the run's :class:`~.tensorboard.TensorBoardLogger`.
        run_dir: where :meth:`finish` writes the PNGs (``None``: no files).
        snapshot_iterations: iterations whose per-time errors are kept for the figure.
        guard: the run's drawing guard.
    """

    def __init__(self, problem: "InverseProblem", tb: "TensorBoardLogger",
                 run_dir: str | Path | None = None,
                 snapshot_iterations: Sequence[int] = (1, 5, 10, 40),
                 guard: PlotGuard | None = None) -> None:
        self.problem = problem
        self.tb = tb
        self.run_dir = None if run_dir is None else Path(run_dir)
        self.snapshot_iterations = {int(i) for i in snapshot_iterations}
        self.guard = guard or PlotGuard()
        self.times = problem.output_times.detach().cpu().numpy()
        self.history: dict[int, np.ndarray] = {}
        self._last_step: int | None = None
        truth = problem.x_true
        #: frames strips only for positions of 1 or 2 dimensions (module docstring)
        self.strips = truth is not None and int(truth.shape[-1]) in (1, 2)

    def _errors(self, x: Tensor) -> np.ndarray:
        return np.asarray(self.problem.frame_errors(x)["u_err_inf"], dtype=np.float64)

    def __call__(self, evaluation: Evaluation) -> None:
        assert evaluation.record is not None, "an observer reads the evaluation of a record"
        step = self.tb.step_of(evaluation.record)
        self._last_step = step
        if self.tb.already_logged(step) or self.problem.x_true is None:
            return None
        if step == 0 or step in self.snapshot_iterations:
            self.history[step] = self._errors(evaluation.state)
            if step == 0:
                self.guard.run("TensorBoard motion figures of iteration 0", self._figures, 0,
                               evaluation)
        return None

    def _strip(self, evaluation: Evaluation, step: int):
        problem = self.problem
        frames = strip_frames(len(self.times))
        simulated = evaluation.state[frames].cpu().numpy()
        target = problem.x_true[frames].detach().cpu().numpy()
        mesh = problem.mesh if isinstance(problem, MeshProblem) else None
        cells = None if mesh is None else np.asarray(mesh.cells)
        values = evaluation.field.detach().cpu().numpy() if cells is not None else None
        return frames_strip_figure(self.times[frames], simulated, target, cells, values,
                                   problem.field_name,
                                   f"{problem.name}: simulated (colour/line) against target "
                                   f"(wire/dots), iteration {step}")

    def _time_figure(self, step: int):
        return time_errors_figure(self.times, self.history,
                                  f"{self.problem.name}: position error over time")

    def _figures(self, step: int, evaluation: Evaluation) -> None:
        writer = self.tb.writer
        writer.add_figure("motion/time_errors", self._time_figure(step), step, close=False)
        if self.strips:
            writer.add_figure("motion/frames_strip", self._strip(evaluation, step), step,
                              close=False)

    def finish(self, final: Evaluation) -> list[Path]:
        """Last iteration (``final``: the run's evaluation at its end): its per-time errors,
        the TensorBoard figures and scalars, the PNGs."""
        if self.problem.x_true is None:
            return []
        step = self._last_step if self._last_step is not None else 0
        self.history[step] = self._errors(final.state)
        for i, value in enumerate(self.history[step]):
            self.tb.scalar("time/u_err_inf", float(value), i)
        if 0 in self.history:
            for i, value in enumerate(self.history[0]):
                self.tb.scalar("time/u_err_inf_initial", float(value), i)
        self.guard.run("TensorBoard motion figures", self._figures, step, final)
        if self.run_dir is None:
            return []
        self.run_dir.mkdir(parents=True, exist_ok=True)
        written: list[Path] = []
        drawings = [(TIME_ERRORS_PNG, lambda: self._time_figure(step))]
        if self.strips:
            drawings.append((FRAMES_STRIP_PNG, lambda: self._strip(final, step)))
        for name, draw in drawings:
            figure = self.guard.run(name, draw)
            if figure is not None and self.guard.run(name, save_png, figure,
                                                     self.run_dir / name) is not False:
                if (self.run_dir / name).is_file():
                    written.append(self.run_dir / name)
        return written
