"""Figures of a run (matplotlib ``Figure`` objects, no pyplot state) and its two pictures.

Functions here take arrays (or a problem and a field) and return figures or RGB arrays;
nothing computes anything a solver needs. :func:`write_run_pngs` writes into a run
directory

``field.png``
    a 2-D field (a :class:`~torchfit.problems.base.FieldImageProblem`): truth, fit and
    error side by side, each with its colour bar; for a scale-free problem the fit is first
    multiplied by the best global scale onto the truth (``a = <k, k_true> / <k, k>``, the
    ``k_err_rel_aligned`` of docs/problems.md) and the error panel is ``a k - k_true``. A 1-D
    chain (:func:`field_is_chain`): ``k`` per cell, truth and fit, as a step plot.
``error_curves.png``
    ``misfit``, the field error (``k_err_rel_aligned`` or ``k_err_rel``), the damping
    errors of a dynamic problem and ``tv`` when recorded, against the iteration (log axes).

Every drawing of a run goes through a :class:`~torchfit.reporting.guard.PlotGuard`.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from ..problems import FieldImageProblem, MeshProblem
from .guard import PlotGuard
from .results import atomic_write

if TYPE_CHECKING:  # pragma: no cover
    from ..problems import InverseProblem

FIELD_PNG = "field.png"
ERROR_CURVES_PNG = "error_curves.png"


def aligned(field: np.ndarray, truth: np.ndarray | None) -> tuple[np.ndarray, float]:
    """``(a field, a)`` with ``a`` the least-squares scale onto ``truth`` (1 without one)."""
    if truth is None:
        return field, 1.0
    denom = float(np.dot(field.reshape(-1), field.reshape(-1)))
    a = float(np.dot(field.reshape(-1), truth.reshape(-1))) / denom if denom > 0 else 1.0
    return a * field, a


def colorize(image: np.ndarray, vmin: float, vmax: float, cmap: str = "viridis") -> np.ndarray:
    """``(H, W)`` values as ``(H, W, 3)`` uint8 RGB with a fixed colour range."""
    from matplotlib import colormaps

    span = vmax - vmin if vmax > vmin else 1.0
    normalized = np.clip((np.asarray(image, dtype=np.float64) - vmin) / span, 0.0, 1.0)
    rgba = colormaps[cmap](normalized)
    return (rgba[..., :3] * 255).round().astype(np.uint8)


def field_figure(field, truth=None, name: str = "k", title: str | None = None):
    """Figure of a 1-D field per cell (step plot), with the truth if given.

    ``field`` and ``truth``: ``(n_cells,)`` arrays or tensors.
    """
    from matplotlib.figure import Figure

    values = _numpy(field).reshape(-1)
    fig = Figure(figsize=(6.4, 3.2), dpi=100, layout="constrained")
    ax = fig.add_subplot()
    cells = np.arange(values.size)
    if truth is not None:
        ax.step(cells, _numpy(truth).reshape(-1), where="mid", color="0.4", lw=2.0,
                label="true")
    ax.step(cells, values, where="mid", color="C0", lw=1.2, label="fitted")
    ax.set_xlabel("cell")
    ax.set_ylabel(name)
    if title:
        ax.set_title(title)
    ax.legend(loc="best")
    ax.grid(alpha=0.3)
    return fig


def _numpy(values) -> np.ndarray:
    """An array of ``values`` (a NumPy array, a torch tensor on any device, a list)."""
    if hasattr(values, "detach"):
        values = values.detach().cpu().numpy()
    return np.asarray(values, dtype=np.float64)


def snapshots_figure(images: Sequence[tuple[str, np.ndarray]], extent: tuple[float, float, float, float],
                     vmin: float, vmax: float, name: str = "E",
                     frame_errors: Sequence[np.ndarray | None] | None = None,
                     frame_labels: Sequence[str] | None = None, title: str | None = None):
    """Field images side by side (one row each), beside each the per-frame position error.

    Args:
        images: ``(label, image)`` pairs, image rows top to bottom (row 0 = max y).
        extent: ``(x0, x1, y0, y1)`` of the sheet.
        frame_errors: per image, the max position error of every frame (or ``None``).
    """
    from matplotlib.figure import Figure

    n = len(images)
    with_errors = frame_errors is not None and any(e is not None for e in frame_errors)
    width_ratios = [4.0, 1.4] if with_errors else [1.0]
    fig = Figure(figsize=(9.5 if with_errors else 7.5, 1.7 * n + 0.6), dpi=100,
                 layout="constrained")
    axes = fig.subplots(n, len(width_ratios), squeeze=False,
                        gridspec_kw={"width_ratios": width_ratios})
    mappable = None
    for i, (label, image) in enumerate(images):
        ax = axes[i, 0]
        mappable = ax.imshow(image, extent=extent, vmin=vmin, vmax=vmax, cmap="viridis",
                             interpolation="nearest", aspect="equal")
        ax.set_title(label, fontsize=9, loc="left")
        ax.tick_params(labelsize=7)
        if with_errors:
            ax_e = axes[i, 1]
            errors = frame_errors[i] if frame_errors is not None else None
            if errors is None:
                ax_e.axis("off")
            else:
                frames = np.arange(len(errors))
                ax_e.bar(frames, errors, color="C3")
                ax_e.set_yscale("log")
                ax_e.set_xticks(frames)
                ax_e.tick_params(labelsize=6)
                ax_e.set_title("max |x - x_true| per frame", fontsize=7)
    if mappable is not None:
        fig.colorbar(mappable, ax=axes[:, 0].tolist(), location="bottom", shrink=0.6,
                     aspect=40, pad=0.02, label=name)
    if title:
        fig.suptitle(title, fontsize=10)
    if frame_labels is not None and with_errors:
        axes[-1, 1].set_xlabel("frame", fontsize=7)
    return fig


def sheet_figure(points: np.ndarray, cells: np.ndarray, values: np.ndarray,
                 target: np.ndarray | None = None, rest: np.ndarray | None = None,
                 vmin: float | None = None, vmax: float | None = None, name: str = "E",
                 title: str | None = None):
    """A deformed triangle mesh coloured per triangle, with the target's outline.

    Args:
        points: ``(n, 2)`` deformed positions; ``cells`` ``(m, 3)``; ``values`` ``(m,)``.
        target: ``(n, 2)`` target positions (drawn as a thin wireframe), optional.
        rest: ``(n, 2)`` rest positions (drawn as a light outline), optional.
    """
    from matplotlib.figure import Figure
    from matplotlib.tri import Triangulation

    fig = Figure(figsize=(8.0, 3.2), dpi=100, layout="constrained")
    ax = fig.add_subplot()
    if rest is not None:
        ax.triplot(Triangulation(rest[:, 0], rest[:, 1], cells), color="0.85", lw=0.2)
    tri = Triangulation(points[:, 0], points[:, 1], cells)
    coll = ax.tripcolor(tri, facecolors=values, cmap="viridis", vmin=vmin, vmax=vmax,
                        edgecolors="none")
    if target is not None:
        ax.triplot(Triangulation(target[:, 0], target[:, 1], cells), color="k", lw=0.15,
                   alpha=0.6)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=7)
    fig.colorbar(coll, ax=ax, shrink=0.8, label=name)
    if title:
        ax.set_title(title, fontsize=9)
    return fig


def frame_errors_figure(history: Mapping[int, np.ndarray], labels: Sequence[str] | None = None,
                        title: str | None = None):
    """Per-frame max position error against the iteration (one curve per frame)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 3.6), dpi=100, layout="constrained")
    ax = fig.add_subplot()
    steps = sorted(history)
    if steps:
        errors = np.stack([history[s] for s in steps])
        for f in range(errors.shape[1]):
            label = f"{f}: {labels[f]}" if labels is not None and f < len(labels) else f"frame {f}"
            ax.semilogy(steps, np.maximum(errors[:, f], 1e-300), label=label, lw=1.2)
        ax.legend(fontsize=6, ncol=2)
    ax.set_xlabel("iteration")
    ax.set_ylabel("max |x - x_true|")
    ax.grid(alpha=0.3)
    if title:
        ax.set_title(title, fontsize=9)
    return fig


# -- images ------------------------------------------------------------------------------

#: Colour map of signed error images: blue negative, white zero, red positive.
ERROR_CMAP = "RdBu_r"


def upscale(image: np.ndarray, min_size: int = 256, max_factor: int = 16) -> np.ndarray:
    """Repeat every pixel ``f x f`` times (nearest neighbour) so that the longer side of
    ``image`` reaches ``min_size`` pixels; ``f`` is an integer in ``[1, max_factor]``.

    TensorBoard shows an image at its own pixel size; a 31 x 31 field would be a stamp.
    Works on ``(H, W)`` and ``(H, W, C)``.
    """
    longest = max(int(image.shape[0]), int(image.shape[1]), 1)
    factor = int(min(max_factor, max(1, -(-min_size // longest))))
    if factor == 1:
        return image
    return np.repeat(np.repeat(image, factor, axis=0), factor, axis=1)


def symmetric_range(values: np.ndarray) -> tuple[float, float]:
    """``(-m, m)`` with ``m = max |values|`` (``(-1, 1)`` for an all-zero array)."""
    m = float(np.max(np.abs(values))) if np.size(values) else 0.0
    m = m if m > 0 and np.isfinite(m) else 1.0
    return -m, m


def field_panels_figure(fitted: np.ndarray, truth: np.ndarray | None, error: np.ndarray | None,
                        extent: tuple[float, float, float, float], vmin: float, vmax: float,
                        name: str = "k", fitted_label: str | None = None,
                        error_label: str | None = None, title: str | None = None):
    """Truth / fit / error images side by side (one above the other for a domain more
    than twice as wide as high), each with its colour bar.

    Args:
        fitted, truth, error: ``(H, W)`` images, row 0 at the top; ``truth`` and
            ``error`` may be ``None`` (user data without a truth).
        extent: ``(x0, x1, y0, y1)`` of the domain.
        vmin, vmax: colour range shared by truth and fit.
        error_label: title of the error panel (say "aligned" for a scale-free problem).
    """
    from matplotlib.figure import Figure

    panels: list[tuple[str, np.ndarray, str, float, float]] = []
    if truth is not None:
        panels.append((f"true {name}", truth, "viridis", vmin, vmax))
    panels.append((fitted_label or f"fitted {name}", fitted, "viridis", vmin, vmax))
    if error is not None:
        lo, hi = symmetric_range(error)
        panels.append((error_label or f"{name} - {name}_true", error, ERROR_CMAP, lo, hi))
    height, width = float(extent[3] - extent[2]), float(extent[1] - extent[0])
    aspect = height / width if width > 0 else 1.0
    if aspect >= 0.5:       # squarish (poisson2d): side by side, colour bars below
        panel_w = 3.6
        fig = Figure(figsize=(panel_w * len(panels), min(8.0, panel_w * aspect + 0.9)),
                     dpi=100, layout="constrained")
        axes = fig.subplots(1, len(panels), squeeze=False)[0]
        bar_location = "bottom"
    else:                   # a wide strip (membrane2d): one above the other, bars beside
        panel_w = 8.0
        fig = Figure(figsize=(panel_w + 1.2, len(panels) * (panel_w * aspect + 0.5) + 0.4),
                     dpi=100, layout="constrained")
        axes = fig.subplots(len(panels), 1, squeeze=False)[:, 0]
        bar_location = "right"
    for ax, (label, image, cmap, lo, hi) in zip(axes, panels):
        shown = ax.imshow(image, extent=extent, vmin=lo, vmax=hi, cmap=cmap,
                          interpolation="nearest", aspect="equal")
        ax.set_title(label, fontsize=9)
        ax.tick_params(labelsize=7)
        bar = fig.colorbar(shown, ax=ax, shrink=0.85, location=bar_location, pad=0.02,
                           aspect=25 if bar_location == "bottom" else 10)
        bar.ax.tick_params(labelsize=7)
        if cmap == ERROR_CMAP:
            bar.formatter.set_powerlimits((-2, 3))
            bar.update_ticks()
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


def error_curves_figure(history: Sequence[Mapping[str, float]], keys: Sequence[str],
                        title: str | None = None):
    """One log-scale panel per key against the iteration (shared x axis).

    Args:
        history: one mapping per recorded iteration with ``iteration`` and the keys
            (``result.json``'s ``history`` rows); missing, non-finite or non-positive
            values are left out of the curve.
        keys: what to draw, one panel each, top to bottom (e.g. ``misfit``,
            ``k_err_rel_aligned``, ``tv``).
    """
    from matplotlib.figure import Figure

    keys = list(keys)
    fig = Figure(figsize=(6.4, 1.0 + 1.9 * max(1, len(keys))), dpi=100, layout="constrained")
    axes = fig.subplots(max(1, len(keys)), 1, sharex=True, squeeze=False)[:, 0]
    steps = np.array([float(row.get("iteration", i)) for i, row in enumerate(history)])
    for i, (ax, key) in enumerate(zip(axes, keys)):
        values = np.array([float(row.get(key, np.nan)) for row in history], dtype=np.float64)
        keep = np.isfinite(values) & (values > 0)
        ax.semilogy(steps[keep], values[keep], marker="." if keep.sum() < 40 else None,
                    lw=1.3, color=f"C{i}")
        ax.set_ylabel(key, fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3, which="both")
        if keep.any():
            ax.set_title(f"{key}: {values[keep][0]:.3g} -> {values[keep][-1]:.3g}", fontsize=8,
                         loc="left")
    axes[-1].set_xlabel("iteration")
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


def save_png(fig, path) -> None:
    """Render ``fig`` with the Agg canvas (no display, no pyplot state) into ``path``
    (atomically: a full disk or a kill leaves the earlier picture or none, never a part)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    atomic_write(Path(path), lambda f: fig.savefig(f, format="png"))


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


def supports_field_images(problem: "InverseProblem") -> bool:
    """Whether the problem can draw its field as an image (``field_image(field)``)."""
    return isinstance(problem, FieldImageProblem)


@dataclasses.dataclass
class FieldImages:
    """A 2-D field drawn for comparison with its truth.

    Attributes:
        fitted: ``(H, W)`` image of the fit, multiplied by ``scale``.
        truth: ``(H, W)`` image of the truth or ``None``.
        error: ``(H, W)`` image of ``scale * field - truth`` or ``None``.
        scale: the global factor applied to the fit (1 unless ``aligned``).
        aligned: whether ``scale`` is the best scale onto the truth (scale-free problem).
    """

    fitted: np.ndarray
    truth: np.ndarray | None
    error: np.ndarray | None
    scale: float
    aligned: bool


def field_images(problem: "InverseProblem", field: Tensor | np.ndarray) -> FieldImages:
    """Images of ``field`` (``(n_field,)``), of the truth and of the (aligned) error."""
    values = np.asarray(field.detach().cpu().numpy() if isinstance(field, Tensor) else field,
                        dtype=np.float64).reshape(-1)
    truth_t = problem.field_true
    truth = None if truth_t is None else truth_t.detach().cpu().numpy().reshape(-1)
    is_aligned = bool(problem.scale_free and truth is not None)
    scaled, scale = aligned(values, truth if is_aligned else None)

    def image(v: np.ndarray) -> np.ndarray:
        return np.asarray(problem.field_image(torch.as_tensor(v)), dtype=np.float64)

    return FieldImages(image(scaled), None if truth is None else image(truth),
                       None if truth is None else image(scaled - truth), scale, is_aligned)


def field_colour_range(problem: "InverseProblem", image: np.ndarray) -> tuple[float, float]:
    """Colour range of field images: ``[min(0, k_true), 1.15 max k_true]``, fixed for a run
    so that images of different iterations compare; the image's own range without a truth."""
    truth = problem.field_true
    if truth is None:
        return float(np.min(image)), float(np.max(image))
    values = truth.detach().cpu().numpy()
    return float(min(0.0, values.min())), float(values.max()) * 1.15


def image_extent(problem: "InverseProblem", image: np.ndarray) -> tuple[float, float, float, float]:
    """``(x0, x1, y0, y1)`` of a field image: the mesh's box when there is one, else cells."""
    box = problem.mesh.extent if isinstance(problem, MeshProblem) and problem.mesh is not None \
        else None
    if box is not None:
        return float(box[0][0]), float(box[0][1]), float(box[1][0]), float(box[1][1])
    return 0.0, float(image.shape[1]), 0.0, float(image.shape[0])


def error_label(problem: "InverseProblem", images: FieldImages) -> str:
    """Title of an error image: says whether the fit was aligned (scaled) first."""
    name = problem.field_name
    if images.aligned:
        return f"aligned error a {name} - {name}_true (a = {images.scale:.4g})"
    return f"error {name} - {name}_true"


def field_panels(problem: "InverseProblem", field: Tensor, title: str | None = None):
    """The truth / fit / error figure of a 2-D field (:func:`field_panels_figure`)."""
    images = field_images(problem, field)
    vmin, vmax = field_colour_range(problem, images.fitted)
    name = problem.field_name
    fitted_label = f"fitted {name} x {images.scale:.4g} (aligned)" if images.aligned \
        else f"fitted {name}"
    return field_panels_figure(images.fitted, images.truth, images.error,
                               image_extent(problem, images.fitted), vmin, vmax, name,
                               fitted_label, error_label(problem, images), title)


def chain_figure(problem: "InverseProblem", field: Tensor, title: str | None = None):
    """A 1-D field per cell (spring1d: ``k`` per spring), truth and fit."""
    return field_figure(field.detach().cpu(), None if problem.field_true is None
                        else problem.field_true.detach().cpu(), problem.field_name, title=title)


def error_curve_keys(history: Sequence[Mapping[str, float]]) -> list[str]:
    """What ``error_curves.png`` draws: ``misfit``, the field error, the damping errors
    (dynamic problems), ``tv`` if recorded."""
    present = set().union(*(row.keys() for row in history)) if history else set()
    keys = ["misfit"]
    # k_err_rel_aligned exists only for a scale-free problem, whose k_err_rel mostly
    # measures the arbitrary global scale of the fit.
    for key in ("k_err_rel_aligned", "k_err_rel"):
        if key in present:
            keys.append(key)
            break
    keys.extend(key for key in ("alpha_damping_err_rel", "beta_damping_err_rel") if key in present)
    if "tv" in present:
        keys.append("tv")
    return keys


def write_run_pngs(run_dir: str | Path, problem: "InverseProblem", field: Tensor,
                   history: Sequence[Mapping[str, float]], guard: PlotGuard | None = None,
                   chain: bool = False) -> list[Path]:
    """Write ``field.png`` and ``error_curves.png`` into ``run_dir`` (see the module docstring).

    Args:
        field: ``(n_field,)`` the fitted field.
        history: one row per recorded iteration (``iteration``, ``misfit``, metrics, ...),
            as in ``result.json``.
        chain: the field is one value per cell of a 1-D chain (a line plot, not an image).

    Returns:
        The files written (a drawing that failed is reported by ``guard`` and left out).
    """
    guard = guard or PlotGuard()
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    steps = [int(row["iteration"]) for row in history if "iteration" in row]
    last = f" after {steps[-1]} iterations" if steps else ""

    def save(fig, path: Path) -> Path:
        save_png(fig, path)
        return path

    figure = None
    if supports_field_images(problem):
        figure = guard.run(FIELD_PNG, field_panels, problem, field,
                           f"{problem.name}: {problem.field_name}{last}")
    elif chain:
        figure = guard.run(FIELD_PNG, chain_figure, problem, field,
                           f"{problem.name}: {problem.field_name} per cell{last}")
    if figure is not None and guard.run(FIELD_PNG, save, figure, run_dir / FIELD_PNG):
        written.append(run_dir / FIELD_PNG)
    if history:
        keys = error_curve_keys(history)
        figure = guard.run(ERROR_CURVES_PNG, error_curves_figure, history, keys,
                           f"{problem.name}: convergence")
        if figure is not None and guard.run(ERROR_CURVES_PNG, save, figure,
                                            run_dir / ERROR_CURVES_PNG):
            written.append(run_dir / ERROR_CURVES_PNG)
    return written
