"""Outputs of a 3-D body fitted to an animation (``arm3d``, ``animation``).

:class:`BodyOutputs` is a run observer (per recorded iteration: the per-frame surface error
of the run's evaluation, kept for ``frame_errors.png``) and, at the end of a run, writes
into the run directory

``frames/frame_NNN.obj``
    the simulated surface of every frame on the user's own vertices and faces (vertex order
    as in the rest surface), an OBJ sequence for any DCC tool;
``body.vtu``
    the tetrahedral mesh (rest positions) for ParaView (meshio): cell data ``E`` (fitted),
    ``E_true`` (synthetic targets), ``region``; point data ``displacement_NNN`` per frame
    (``Warp By Vector`` shows a frame);
``rig.json``
    the rig the body was attached with (:func:`.body_files.write_rig`);
``regions.json``
    the fitted field summarised per region (tets, volume, mean, min, max, volume-weighted
    mean), and the truth's for synthetic targets; ``uncertainty``, where the run made one
    (:mod:`torchfit.run.uncertainty`): per region the standard deviation and two-sigma band
    of the volume-weighted mean modulus, and the fit on a second mesh (``mesh_check``);
``model_comparison.json`` and ``frame_comparison.png``
    the same field, rig and frames with the ``linear`` model beside the fitted model (the
    states the run simulated for it, :meth:`BodyOutputs.comparison_models`): per-frame mean
    surface error and joint-region volume change, and a picture of the reference frame
    (animation | linear | fitted model), the seed's frame-24 figure, through the body's
    camera (``view_axes``: the file's up axis up), one colour range for every panel
    (:func:`comparison_range`: the fitted model's largest error) with a colour bar in mm;
``frame_errors.png``
    mean surface error per animation frame: the homogeneous material (iteration 0) against
    the fit, the validation frames (held out of the fit) drawn and marked, integer ticks;
``animation/``
    a copy of the animation folder when the problem wrote it itself (``arm3d``): a worked
    example of the format;
``frame_errors.jsonl``
    the per-frame errors of every recorded iteration as the run goes (one JSON line each:
    ``iteration``, ``surface_err_mean`` per fitted frame, ``validation`` per held-out frame
    or ``null``), so that a resumed run draws ``frame_errors_history.png`` over the whole
    fit: a resume reads the lines up to its checkpoint's iteration
    (:meth:`BodyOutputs.restore_history`) and rewrites the file with them.

TensorBoard (``tb/``): meshes (``add_mesh``) of the chosen frames coloured by surface error
(``mesh/surface_error_frame<f>``) and of the tetrahedral boundary coloured by Young's
modulus (``mesh/E_frame<f>``), and the per-frame curves as scalars whose step is the frame
(``frames/surface_err_mean``, ``frames/surface_err_mean_homogeneous``,
``frames/joint_volume_change_<model>``). Nothing here simulates: every state is one the
run evaluated.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
import torch
from torch import Tensor

from ..problems import BodyProblem
from .evaluation import Evaluation
from .figures import colorize, frame_errors_figure, save_png
from .guard import PlotGuard
from .progress import PROGRESS_LOGGER
from .body_files import (FRAMES_DIR, VTU_FILE, file_surface, fitted_damping, vtu_cell_data,
                         write_body_vtu, write_obj_sequence, write_rig, write_usd)
from .results import write_folder, write_json

#: the per-frame errors of every recorded iteration (module docstring)
FRAME_ERRORS_FILE = "frame_errors.jsonl"

if TYPE_CHECKING:  # pragma: no cover
    from .tensorboard import TensorBoardLogger

log = logging.getLogger(__name__)
progress = logging.getLogger(PROGRESS_LOGGER)

COMPARISON_PNG = "frame_comparison.png"
COMPARISON_JSON = "model_comparison.json"
REGIONS_JSON = "regions.json"


def _numpy(x: Tensor) -> np.ndarray:
    return x.detach().cpu().numpy().astype(np.float64)


def vertex_field(cells: np.ndarray, values: np.ndarray, n_vertices: int) -> np.ndarray:
    """Per-vertex mean of a per-cell field ``(n_vertices,)`` (for colouring a surface)."""
    total = np.zeros(n_vertices)
    count = np.zeros(n_vertices)
    np.add.at(total, cells.reshape(-1), np.repeat(values, cells.shape[1]))
    np.add.at(count, cells.reshape(-1), 1.0)
    return total / np.maximum(count, 1.0)


def comparison_range(errors: dict[tuple[str, str], np.ndarray], model: str) -> float:
    """The colour range's top (m) of the model comparison's panels: the largest error of
    the panels of the fitted ``model`` (homogeneous and fitted field), so that neither is
    dark beside a far worse comparison model (``linear`` under a large bend: its panel is
    clipped, the colour bar's arrow says so, its label gives its mean). ``errors``:
    ``(material, model) -> (V,)`` per-vertex errors; 1.0 where every error is 0."""
    own = [e for (_, name), e in errors.items() if name == model] or list(errors.values())
    top = max((float(np.max(e)) for e in own if np.size(e)), default=0.0)
    return top if top > 0 and np.isfinite(top) else 1.0


def surface_figure(panels: Sequence[tuple[str, np.ndarray, np.ndarray | None]],
                   faces: np.ndarray, vmax: float, title: str | None = None,
                   view: np.ndarray | None = None, label: str = "surface error (mm)"):
    """Surfaces side by side (matplotlib 3-D), each ``(label, vertices (V, 3), error (V,))``
    coloured by its per-vertex error (m) on a common scale ``[0, vmax]`` (grey without
    one), with a colour bar in millimetres (``label``; an arrow where a panel goes beyond
    ``vmax``).

    ``view`` ``(3, 3)``: the camera's axes, rows ``right, depth, up`` (the problem's
    ``view_axes``: up is the picture's up); the camera looks along ``depth``, slightly from
    above. ``None``: the world's ``x, y, z``."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    coloured = [error for _, _, error in panels if error is not None]
    width = 4.2 * len(panels) + (0.9 if coloured else 0.0)
    fig = Figure(figsize=(width, 5.2), dpi=100, layout="constrained")
    if view is not None:
        panels = [(label, np.asarray(vertices) @ np.asarray(view).T, error)
                  for label, vertices, error in panels]
    all_points = np.concatenate([p[1] for p in panels])
    lo, hi = all_points.min(0), all_points.max(0)
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2
    cmap = colormaps["magma"]
    axes = []
    for i, (panel_label, vertices, error) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), i + 1, projection="3d")
        axes.append(ax)
        triangles = vertices[faces]
        if error is None:
            colours = np.tile([0.75, 0.75, 0.78, 1.0], (len(faces), 1))
        else:
            colours = cmap(np.clip(error[faces].mean(axis=1) / max(vmax, 1e-300), 0, 1))
        # simple Lambert shading so the shape reads without a colour scale
        normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
        light = 0.55 + 0.45 * np.abs(normals @ np.array([0.3, -0.8, 0.5]) / np.linalg.norm(
            [0.3, -0.8, 0.5]))
        colours = colours.copy()
        colours[:, :3] *= light[:, None]
        ax.add_collection3d(Poly3DCollection(triangles, facecolors=colours, linewidths=0))
        for axis, c in zip("xyz", centre):
            getattr(ax, f"set_{axis}lim")(c - half, c + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=10, azim=-90)
        ax.set_axis_off()
        ax.set_title(panel_label, fontsize=9)
    if coloured:
        beyond = max(float(np.max(e)) for e in coloured if np.size(e)) > vmax * (1 + 1e-9)
        bar = fig.colorbar(ScalarMappable(Normalize(0.0, 1e3 * vmax), cmap), ax=axes,
                           shrink=0.7, extend="max" if beyond else "neither")
        bar.set_label(label)
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


def per_frame_errors_figure(series: Sequence[tuple[str, str, dict[int, float]]],
                            validation: Sequence[int] = ()):
    """Mean surface error per animation frame: each of ``series`` ``(label, colour,
    {frame number: error (m)})`` a line over its frames (in mm), the ``validation`` frames
    (held out of the fit) marked by squares with their own legend entry; integer frame
    ticks."""
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.ticker import MaxNLocator

    held = {int(f) for f in validation}
    fig = Figure(figsize=(7.0, 3.6), dpi=100, layout="constrained")
    ax = fig.add_subplot()
    for label, colour, values in series:
        frames = sorted(values)
        errors = np.array([values[f] for f in frames]) * 1e3
        fitted = [i for i, f in enumerate(frames) if f not in held]
        ax.plot(frames, errors, "-", color=colour, lw=1.2)
        ax.plot(np.asarray(frames)[fitted], errors[fitted], "o", color=colour, ms=3,
                label=label)
        shown = [i for i, f in enumerate(frames) if f in held]
        if shown:
            ax.plot(np.asarray(frames)[shown], errors[shown], "s", color=colour, ms=7,
                    mec="k", mew=0.8)
    if held:
        for f in held:
            ax.axvspan(f - 0.4, f + 0.4, color="0.9", zorder=0)
        handles, labels = ax.get_legend_handles_labels()
        handles.append(Line2D([], [], ls="", marker="s", ms=7, mfc="w", mec="k", mew=0.8))
        labels.append("validation frame (held out of the fit)")
        ax.legend(handles, labels, fontsize=8)
    else:
        ax.legend(fontsize=8)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("animation frame")
    ax.set_ylabel("mean surface error (mm)")
    ax.grid(alpha=0.3)
    return fig


class BodyOutputs:
    """Per-iteration per-frame errors and the end-of-run files of a 3-D body (module doc).

    Called with the run's :class:`~torchfit.reporting.evaluation.Evaluation` of every
    record; :meth:`finish` with the one at the end, then :meth:`compare` with it, the
    homogeneous material's (:attr:`baseline`, or one the run made when it did not start
    there) and the states of :meth:`comparison_models`, then :meth:`copy_animation`.

    Args:
        problem: a :class:`~torchfit.problems.base.BodyProblem`.
        tb: the run's TensorBoard logger.
        run_dir: the run directory.
        frames: frames to show as TensorBoard meshes (default: the reference frame, the
            problem's ``full_bend_frame``, and frame 0).
        guard: the run's plot guard (a drawing failure is warned about, never fatal).
        suggest_continuation: the end-of-run warning about folded frames suggests fitting
            the others first (not in a run that is a stage of one: it reports itself).
    """

    def __init__(self, problem: BodyProblem, tb: "TensorBoardLogger", run_dir: str | Path,
                 frames: Sequence[int] | None = None, guard: PlotGuard | None = None,
                 suggest_continuation: bool = True) -> None:
        self.problem = problem
        self.tb = tb
        self.run_dir = Path(run_dir)
        self.frames = sorted({int(problem.full_bend_frame), 0} if frames is None
                             else {int(f) for f in frames})
        self.guard = guard or PlotGuard()
        self.history: dict[int, np.ndarray] = {}
        #: per recorded iteration: the validation frames' mean surface error (where held out)
        self.validation_history: dict[int, np.ndarray] = {}
        #: the evaluation of the homogeneous material (the initial guess) at iteration 0:
        #: the model comparison's baseline (``None``: the run did not start there)
        self.baseline: Evaluation | None = None
        self.started_elsewhere = False     # iteration 0 was not the initial guess (init=)
        self.suggest_continuation = suggest_continuation
        #: the data determine no material and the run's end is its start (set by the run
        #: before :meth:`finish`): the USD material says so
        self.kept_start = False
        #: one line per file worth pointing a user at, once :meth:`compare` wrote it
        self.highlights: list[str] = []
        #: the fit's uncertainty, set by the run before :meth:`finish`: ``regions`` (added to
        #: ``regions.json`` as ``uncertainty``) and ``cell_band`` ``(m,)`` (the modulus'
        #: two-sigma band per tetrahedron, written to ``usd/body.usda``); ``None``: none
        self.uncertainty: dict[str, Any] | None = None

    def __call__(self, evaluation: Evaluation) -> None:
        assert evaluation.record is not None, "an observer reads the evaluation of a record"
        iteration = int(evaluation.record.iteration)
        curves = self.problem.frame_errors(evaluation.state)
        # a resume's first record is its checkpoint's iteration: restored, not written again
        restored = iteration in self.history
        self.history[iteration] = curves["surface_err_mean"]
        if evaluation.validation_errors is not None:
            self.validation_history[iteration] = np.asarray(evaluation.validation_errors)
        if not restored:
            with open(self.run_dir / FRAME_ERRORS_FILE, "a", encoding="utf-8") as stream:
                stream.write(json.dumps(self._history_row(iteration)) + "\n")
        if iteration == 0:
            self.started_elsewhere = not torch.equal(evaluation.theta, self.problem.theta0)
            if not self.started_elsewhere:
                self.baseline = evaluation

    def _history_row(self, iteration: int) -> dict[str, Any]:
        validation = self.validation_history.get(iteration)
        return {"iteration": iteration,
                "surface_err_mean": [float(v) for v in self.history[iteration]],
                "validation": None if validation is None else [float(v) for v in validation]}

    def restore_history(self, last_iteration: int | None) -> None:
        """The per-frame errors of iterations ``0..last_iteration`` from the run directory's
        ``frame_errors.jsonl`` (a resume: ``last_iteration`` is its checkpoint's), the file
        rewritten with just those (atomically); ``None``: a fresh run, the file emptied. A
        torn or unreadable line ends what is read (as ``history.jsonl``'s)."""
        path = self.run_dir / FRAME_ERRORS_FILE
        rows: list[dict[str, Any]] = []
        if last_iteration is not None and path.is_file():
            for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
                try:
                    row = json.loads(line)
                    iteration = int(row["iteration"])
                    errors = np.asarray(row["surface_err_mean"], dtype=np.float64)
                except (ValueError, KeyError, TypeError):
                    break
                if iteration <= last_iteration:
                    rows.append(row)
                    self.history[iteration] = errors
                    if row.get("validation") is not None:
                        self.validation_history[iteration] = np.asarray(row["validation"])
        tmp = path.with_name(f".{path.name}.{os.getpid()}.0.tmp")
        tmp.write_text("".join(json.dumps(r) + "\n" for r in rows), encoding="utf-8")
        os.replace(tmp, path)

    def comparison_models(self) -> list[str]:
        """The constitutive models the comparison shows beside the fitted one (``linear``),
        whose states :meth:`compare` needs for the homogeneous and the fitted field; none
        for a body in time (``problem.dynamic=true``: the comparison is quasistatic)."""
        cfg = self.problem.cfg
        return [] if cfg.model.value == "linear" or getattr(cfg, "dynamic", False) else ["linear"]

    # -- end of the run ---------------------------------------------------------------
    def finish(self, final: Evaluation) -> list[Path]:
        """The fold warning and the files of the fitted state (``final``: the run's
        evaluation at its end): OBJ frames, VTU, regions, TensorBoard meshes,
        ``frame_errors.png``; returns the files written."""
        problem = self.problem
        field, x = final.field, final.state
        # a run started from an earlier one (init=) is that continuation already
        warn_inverted(problem.frame_errors(x).get("inverted_tets"), problem.frame_numbers(),
                      suggest=self.suggest_continuation and not self.started_elsewhere,
                      docs=problem.fold_docs)
        files: list[Path] = []
        steps = [
            ("simulated frames (OBJ)", self._write_frames, (x,)),
            ("body.vtu", self._write_vtu, (x, field)),
            ("USD frames and tet mesh", self._write_usd, (x, field, final.theta)),
            ("regions.json", self._write_regions, (field,)),
            ("rig.json", write_rig, (self.run_dir, problem)),
            ("TensorBoard meshes", self._write_meshes, (x, field)),
            ("frame_errors.png", self._write_frame_errors, (final,)),
        ]
        for what, step, args in steps:
            written = self.guard.run(what, step, *args)
            files.extend(written or [])
        return files

    def compare(self, final: Evaluation, baseline: Evaluation,
                others: dict[str, dict[str, Tensor]]) -> tuple[list[Path], dict[str, Any]]:
        """The model comparison: ``model_comparison.json`` and ``frame_comparison.png``;
        returns ``(files, comparison)`` (the latter goes into ``result.json``; both empty
        where drawing failed).

        Args:
            final: the run's evaluation at its end.
            baseline: the homogeneous material's (the initial guess), simulated cold.
            others: ``{'homogeneous': {model: state}, 'fitted': {model: state}}`` for
                every model of :meth:`comparison_models`.
        """
        compared = self.guard.run("model comparison", self._compare_models, final.state,
                                  baseline, others)
        if compared is None:
            return [], {}
        models = " and ".join([*self.comparison_models(), self.problem.cfg.model.value])
        panels = f"animation | {models}, homogeneous and fitted"
        self.highlights.append(
            f"pictures: {self.run_dir / COMPARISON_PNG} ({panels}, at the most deformed "
            f"frame), fitted field per region: {self.run_dir / REGIONS_JSON}, for "
            f"ParaView: {self.run_dir / VTU_FILE}")
        return compared

    def copy_animation(self) -> list[Path]:
        """A copy of the animation folder the problem wrote itself (``animation/``)."""
        return self.guard.run("animation copy", self._copy_animation) or []

    def _write_frames(self, x: Tensor) -> list[Path]:
        paths = write_obj_sequence(self.run_dir / FRAMES_DIR,
                                   *file_surface(self.problem, _numpy(self.problem.observation.surface(x))))
        progress.info("wrote %d simulated frames to %s", len(paths), self.run_dir / FRAMES_DIR)
        return paths

    def _write_vtu(self, x: Tensor, field: Tensor) -> list[Path]:
        problem = self.problem
        truth = None if problem.field_true is None else _numpy(problem.field_true)
        cell_data = vtu_cell_data(problem, _numpy(field), truth)
        return [write_body_vtu(self.run_dir / VTU_FILE, np.asarray(problem.mesh.points),
                               problem.mesh.cells, _numpy(x), cell_data)]

    def _write_usd(self, x: Tensor, field: Tensor, theta: Tensor) -> list[Path]:
        band = None if self.uncertainty is None else self.uncertainty.get("cell_band")
        return write_usd(self.run_dir, self.problem, _numpy(self.problem.observation.surface(x)),
                         _numpy(field), self.problem.poses.material_density(
                             self.problem.simulation_input(theta)),
                         fitted_damping(self.problem, theta), band=band,
                         kept_start=self.kept_start)

    def _write_regions(self, field: Tensor) -> list[Path]:
        problem = self.problem
        out: dict[str, Any] = {"fitted": problem.report.region_summary(field)}
        if problem.field_true is not None:
            out["true"] = problem.report.region_summary(problem.field_true)
            # scale-free: the fit is known up to a global factor; report it aligned too
            f, t = _numpy(field), _numpy(problem.field_true)
            a = float(f @ t / (f @ f)) if float(f @ f) > 0 else 1.0
            out["alignment_scale"] = a
            out["fitted_aligned"] = problem.report.region_summary(field * a)
        if self.uncertainty is not None and self.uncertainty.get("regions") is not None:
            out["uncertainty"] = self.uncertainty["regions"]
        path = self.run_dir / REGIONS_JSON
        write_json(path, out)
        return [path]

    def _mesh_colours(self, values: np.ndarray, vmin: float, vmax: float,
                      cmap: str) -> np.ndarray:
        return colorize(values[None, :], vmin, vmax, cmap)[0]

    def _write_meshes(self, x: Tensor, field: Tensor) -> list[Path]:
        problem = self.problem
        writer = self.tb.writer
        faces = np.asarray(problem.animation.faces)
        surface = _numpy(problem.observation.surface(x))
        errors = _numpy(problem.observation.surface_error_field(x, problem.x_true))  # (F, V)
        vmax = float(errors.max()) if errors.size else 1.0
        from ..mesh import boundary_faces

        tet_faces, _ = boundary_faces(np.asarray(problem.mesh.cells))
        E_vertex = vertex_field(np.asarray(problem.mesh.cells), _numpy(field),
                                problem.mesh.points.shape[0])
        positions = _numpy(x)
        step = self.tb.last_step or 0
        for f in self.frames:
            if f >= surface.shape[0]:
                continue
            colours = self._mesh_colours(errors[f], 0.0, vmax, "magma")
            writer.add_mesh(f"mesh/surface_error_frame{f}", torch.as_tensor(surface[f][None]),
                            colors=torch.as_tensor(colours[None]),
                            faces=torch.as_tensor(faces[None].astype(np.int32)), global_step=step)
            colours = self._mesh_colours(E_vertex, float(E_vertex.min()), float(E_vertex.max()),
                                         "viridis")
            writer.add_mesh(f"mesh/E_frame{f}", torch.as_tensor(positions[f][None]),
                            colors=torch.as_tensor(colours[None]),
                            faces=torch.as_tensor(tet_faces[None].astype(np.int32)),
                            global_step=step)
        curves = problem.frame_errors(x)
        for f, value in enumerate(curves["surface_err_mean"]):
            writer.add_scalar("frames/surface_err_mean", float(value), f)
        if 0 in self.history:
            for f, value in enumerate(self.history[0]):
                writer.add_scalar("frames/surface_err_mean_homogeneous", float(value), f)
        model = problem.cfg.model.value
        for f, value in enumerate(curves["joint_volume_change"]):
            writer.add_scalar(f"frames/joint_volume_change_{model}", float(value), f)
        for f, value in enumerate(curves["inverted_tets"]):
            writer.add_scalar(f"frames/inverted_tets_{model}", float(value), f)
        writer.flush()
        return []

    def _write_frame_errors(self, final: Evaluation) -> list[Path]:
        problem = self.problem
        numbers = problem.frame_numbers()
        split = getattr(problem, "frame_split", None)     # held-out frames (RiggedBody)
        held = [int(f) for f in split.validation] if split is not None else []

        def by_frame(fitted: np.ndarray | None, validated: Any) -> dict[int, float]:
            values = {} if fitted is None else dict(zip(numbers, map(float, fitted)))
            if validated is not None and len(validated) == len(held):
                values.update(zip(held, map(float, validated)))
            return values

        series = []
        if 0 in self.history:
            series.append(("homogeneous (initial)", "0.5",
                           by_frame(self.history[0], self.validation_history.get(0))))
        series.append(("fitted", "C0", by_frame(problem.frame_errors(final.state)[
            "surface_err_mean"], final.validation_errors)))
        fig = per_frame_errors_figure(series, held)
        path = self.run_dir / "frame_errors.png"
        save_png(fig, path)
        paths = [path]
        if len(self.history) > 1:
            fig = frame_errors_figure(self.history, problem.frame_names())
            fig.axes[0].set_ylabel("mean surface error (m)")
            history_path = self.run_dir / "frame_errors_history.png"
            save_png(fig, history_path)
            paths.append(history_path)
        return paths

    def _compare_models(self, x: Tensor, baseline: Evaluation,
                        others: dict[str, dict[str, Tensor]]) -> tuple[list[Path], dict[str, Any]]:
        """``linear`` against the fitted model, with the homogeneous material (the seed's
        comparison: same animation, same rig, no fitting) and with the fitted field."""
        problem = self.problem
        model = problem.cfg.model.value
        frame = int(problem.full_bend_frame)
        names = problem.frame_names()
        states = {"homogeneous": {model: baseline.state, **others.get("homogeneous", {})},
                  "fitted": {model: x, **others.get("fitted", {})}}
        summary: dict[str, Any] = {"frame": frame, "frame_name": names[frame],
                                   "homogeneous": {}, "fitted": {}}
        for material, by_model in states.items():
            for name in sorted(by_model, key=lambda n: n != "linear"):
                curves = problem.frame_errors(by_model[name])
                summary[material][name] = {
                    "surface_err_mean": float(np.mean(curves["surface_err_mean"])),
                    "joint_volume_change_at_frame": float(curves["joint_volume_change"][frame]),
                    "surface_err_mean_per_frame": curves["surface_err_mean"].tolist(),
                    "joint_volume_change_per_frame": curves["joint_volume_change"].tolist(),
                    "inverted_tets_per_frame": curves["inverted_tets"].tolist(),
                }
        target = _numpy(problem.observation.clean_surface(problem.x_true))[frame]
        panels = [("animation (target)", target, None)]
        shown = [("homogeneous", n) for n in sorted(states["homogeneous"], key=lambda n: n != "linear")]
        shown.append(("fitted", model))
        errors = {key: _numpy(problem.observation.surface_error_field(states[key[0]][key[1]],
                                                                  problem.x_true))[frame]
                  for key in shown}
        vmax = comparison_range(errors, model)
        summary["picture"] = {"colour_max_mm": 1e3 * vmax, "panel_max_mm": {
            f"{material}/{name}": 1e3 * float(np.max(errors[(material, name)]))
            for material, name in shown}}
        json_path = self.run_dir / COMPARISON_JSON
        write_json(json_path, summary)
        for material, name in shown:
            info = summary[material][name]
            label = f"{name}, {'fitted E' if material == 'fitted' else 'homogeneous E'}"
            panels.append((f"{label}\n{problem.joint_label} volume "
                           f"{100 * info['joint_volume_change_at_frame']:+.1f} %, "
                           f"mean error {1e3 * float(errors[(material, name)].mean()):.2f} mm",
                           _numpy(problem.observation.surface(states[material][name]))[frame],
                           errors[(material, name)]))
        fig = surface_figure(panels, np.asarray(problem.animation.faces), vmax,
                             title=f"{names[frame]} (colour: surface error, 0 to "
                                   f"{1e3 * vmax:.2f} mm, the {model} panels' largest)",
                             view=problem.view_axes)
        png = self.run_dir / COMPARISON_PNG
        save_png(fig, png)
        return [png, json_path], summary

    def _copy_animation(self) -> list[Path]:
        source = Path(self.problem.animation.path).parent
        if not self.problem.writes_animation:
            return []
        target = self.run_dir / "animation"
        write_folder(target, lambda partial: shutil.copytree(source, partial,
                                                             dirs_exist_ok=True))
        return [target / source.joinpath("animation.yaml").name]


def frame_spans(frames: Sequence[int]) -> str:
    """Frame numbers with consecutive runs as ranges: ``[8, 9, 10, 12]`` -> ``'8-10, 12'``."""
    frames = np.asarray(frames, dtype=int)
    if frames.size == 0:
        return ""
    breaks = np.flatnonzero(np.diff(frames) != 1)
    starts, ends = np.r_[frames[0], frames[breaks + 1]], np.r_[frames[breaks], frames[-1]]
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in zip(starts, ends))


def warn_inverted(counts: np.ndarray | None, numbers: Sequence[int] | None = None,
                   suggest: bool = True, docs: str | None = None) -> None:
    """One log line naming the frames whose equilibrium has inverted tetrahedra (where
    Newton can reach several equilibria, so the frame depends on where it started), and
    the continuation that avoids it: the other frames first, then all from that run.

    ``counts`` ``(F,)`` per fitted frame; ``numbers`` the animation's frame numbers of the
    fitted frames (``problem.frames``; default ``0 .. F-1``); ``suggest``: add the
    continuation (not for a run that started from an earlier one); ``docs``: where the
    problem's documentation explains it (the arm's; none for other bodies)."""
    if counts is None or not np.any(counts > 0):
        return
    numbers = np.arange(len(counts)) if numbers is None else np.asarray(numbers)
    frames = numbers[counts > 0]
    spans = frame_spans(frames)
    others = numbers[counts == 0]
    hint = ("; to keep the fit off other branches, fit the frames far from the fold first "
            "and then all from there: continuation=true, or by hand "
            f"'problem.frames=[{','.join(str(int(f)) for f in others)}]' and then all frames "
            "with init=<that run's directory>") if len(others) and suggest else ""
    subject = f"frames {spans} have" if len(frames) > 1 else f"frame {spans} has"
    where = f" ({docs})" if docs else ""
    progress.warning("%s tetrahedra turned inside out at equilibrium (at most %d): a frame "
                     "like that has several equilibria, and which one Newton reaches depends "
                     "on where it starts%s%s", subject, int(counts.max()), where, hint)
