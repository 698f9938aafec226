"""Pictures of a finished run for people who never open TensorBoard, and the guard that
keeps a drawing failure from failing a fit.

Files written into the run directory by :func:`write_run_pngs`:

``field.png``
    a 2-D field (a problem with ``field_image``, poisson2d and membrane2d): the truth, the
    fit and the error side by side, each with its colour bar. For a scale-free problem
    the fit is first multiplied by the best global scale onto the truth
    (``a = <k, k_true> / <k, k>``, the ``k_err_rel_aligned`` of PROBLEMS.md) and the error
    panel is the *aligned* error ``a k - k_true`` (the title says so). A 1-D chain
    (spring1d): ``k`` per spring, truth and fit, as a step plot.
``error_curves.png``
    ``misfit`` and ``k_err_rel_aligned`` (``k_err_rel`` for a problem that is not
    scale-free), and ``tv`` when the solver reports it (Split Bregman), against the
    iteration on log axes.

Every drawing goes through a :class:`PlotGuard`: an exception while drawing or saving
is logged once per run as a warning (logger ``torchfit.logging.pictures``) and the fit
goes on; later failures of the same run are counted but not repeated.
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence, TypeVar

import numpy as np
import torch
from torch import Tensor

from ..problems.base import FieldImageProblem, MeshProblem
from .plots import aligned, error_curves_figure, field_figure, field_panels_figure, save_png

if TYPE_CHECKING:  # pragma: no cover
    from ..problems import InverseProblem

log = logging.getLogger(__name__)
T = TypeVar("T")

FIELD_PNG = "field.png"
ERROR_CURVES_PNG = "error_curves.png"


class PlotGuard:
    """Run drawing code so that its failure never fails the fit; warn once per run.

    Attributes:
        failures: ``what`` of every drawing that failed, in order.
    """

    def __init__(self) -> None:
        self.failures: list[str] = []

    def run(self, what: str, draw: Callable[..., T], *args: Any, **kwargs: Any) -> T | None:
        """``draw(*args, **kwargs)``, or ``None`` (and a warning the first time) if it raises."""
        try:
            return draw(*args, **kwargs)
        except Exception as e:  # noqa: BLE001  (any drawing error: matplotlib, disk, ...)
            if not self.failures:
                log.warning("could not draw %s (%s: %s); the fit and its result files are "
                            "not affected, further drawing failures of this run are not "
                            "reported", what, type(e).__name__, e)
            self.failures.append(what)
            return None


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


def write_run_pngs(run_dir: str | Path, problem: "InverseProblem", theta: Tensor,
                   history: Sequence[Mapping[str, float]], guard: PlotGuard | None = None,
                   chain: bool = False) -> list[Path]:
    """Write ``field.png`` and ``error_curves.png`` into ``run_dir`` (see the module docstring).

    Args:
        theta: ``(n_params,)`` final parameters.
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
    field = problem.field(theta)
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
