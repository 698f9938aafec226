"""What the data determine: the identifiability report of a fit, from its Jacobian at the end.

After the solver stops, :func:`identify` says which parameters the data determine:

* **Sensitivity** of parameter ``j``: ``s_j = ||J e_j|| * u_j``, the change of the
  observed data per unit *relative* change of the parameter's effect (``u_j = 1`` for the
  ``exp`` transform, whose ``theta`` is a logarithm already; ``u_j = |theta_j|``, floored at
  ``1e-3`` of the mean ``|theta|``, for ``identity``). ``relative_j = s_j / max s``; a parameter is
  *determined* when ``relative_j >= RELATIVE_THRESHOLD`` (its effect is at least 1 % of the
  strongest one's) and the fit as a whole is determined. The sensitivities do not change
  when the data are scaled, nor (``identity``) when a parameter is.
* **Singular values** of the scaled Jacobian ``J diag(u)`` (dense path only) and the
  **effective rank**: the number of them ``>= RELATIVE_THRESHOLD`` times the largest (0 for
  an undetermined fit). Column norms are necessary per parameter; the rank says how many
  directions the data fix jointly (two parameters with one column each count once). A
  scale-free problem (only prescribed displacements) never fixes the overall scale: its
  rank is at most ``n - 1`` (``gauge: true``).
* **The fit as a whole** is *not determined* when the data do not depend on the material,
  or when the fit shows none of it. Every test is scale-free (the data's units cancel) and
  its bar sits decades from the values on either side, so one body gives one verdict on
  any mesh of it (docs/notes/identifiability.md):

  - the **effect** is small: ``effect = max s / ||r_0||``, the change of the data that an
    e-fold change of the most-seen parameter makes, over the misfit the fit started from
    (``||r_0||``, history row 0; the residual at the report's point where no history is
    given, the data's spread ``||data - mean(data)||`` where no residual is either), is
    below ``EFFECT_THRESHOLD``. A body that any material moves alike gives round-off here
    (1e-7 and less); a material that explains the data, a sizeable fraction (0.08 and
    more on the project's bodies; ``inf`` where the start reproduces the data exactly);
  - for a body with a rest surface (``problem.animation``), every frame's targets are a
    rigid motion of the rest: the RMS distance of the observed targets from the best rigid
    motion of the rest (Kabsch, per frame) is below ``RIGID_THRESHOLD`` times the rest's
    bounding-box diagonal, or below the noise when the noise level ``delta`` is known (a
    point's RMS noise distance ``1.1 sqrt(3) delta / sqrt(m)`` over the diagonal). Any
    material then moves the body the same way; a Jacobian that is not flat there comes from
    the drive of the prescribed vertices, not from the data;
  - the fit **reduced nothing**: the error it reached is less than ``1 + NO_REDUCTION``
    times smaller than the baseline's (a body's ``surface_err_reduction``, against the
    homogeneous material; else the misfit at the start over the misfit at the end, where
    the fit started at the problem's own start and not at ``init=`` an earlier fit). Its
    field is then the start's moved where the data barely see: nothing in the data says
    it is better than the start.

  The outputs of a fit that is not determined keep its starting field
  (:func:`torchfit.run.fitting.keep_the_start`) and the run never says "converged".

Where the Jacobian comes from (``source``): the dense Jacobian the solver made at its last
accepted point (Levenberg-Marquardt and Gauss-Newton on the dense path: no extra work); else
``PROBES`` products ``J^T w`` with Rademacher ``w`` at the solver's last linearisation
(:func:`torchfit.linalg.estimators.column_norms`: column norms within about 18 %, no
singular values), or, where the solver holds none at the final point, a new linearisation
there (one simulation). ``extra_products`` counts them.

Per field element (cell): the interpolation-weighted mean of the parameters' relative
sensitivities and of their determined flags (``1``: every parameter the cell depends on is
determined). Per region (the body's labels, else one region ``body``): the volume-weighted
fraction of determined cells, and the parameters that carry most of their weight there and
how many of them are determined; parameters with no weight on any cell (grid nodes outside
the body) are counted under ``no_cells``.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from ..linalg import column_norms
from ..problems import BodyProblem, InverseProblem

#: a parameter is determined when its sensitivity is at least this fraction of the largest
#: (and a singular value counts in the effective rank when it is this fraction of the largest)
RELATIVE_THRESHOLD = 1e-2
#: the data do not depend on the material when the largest sensitivity (an e-fold change of
#: one parameter) changes the data by less than this fraction of the start's misfit
EFFECT_THRESHOLD = 1e-3
#: a fit reduced nothing when its error is not ``1 + NO_REDUCTION`` times below the baseline's
NO_REDUCTION = 0.05
#: targets are a rigid motion of the rest when their RMS distance from the best rigid
#: motion is below this fraction of the rest's bounding-box diagonal
RIGID_THRESHOLD = 1e-6
#: products ``J^T w`` of the matrix-free estimate of the column norms
PROBES = 16


@dataclasses.dataclass
class Identifiability:
    """The report (module docstring); arrays are NumPy, per parameter or per field element.

    Attributes:
        determined: whether the data determine the material at all.
        reason: why not (``None`` when determined); ``cause`` which test said so:
            ``rigid``, ``effect`` or ``reduction`` (module docstring).
        source: where the Jacobian came from.
        sensitivity, relative, parameter_determined: ``(n,)`` per parameter.
        singular_values: ``(min(m, n),)`` of ``J diag(u)``, largest first, or ``None``.
        effective_rank: or ``None`` without singular values.
        data_spread: ``||data - mean(data)||``.
        effect: ``max s / ||r_0||``; ``reference_misfit`` the ``||r_0||`` it used.
        reduction: how many times the fit lowered its error below ``baseline`` (``None``:
            not given), with ``baseline`` naming it (``the homogeneous material``).
        rigid_deviation: the targets' largest per-frame RMS distance from a rigid motion of
            the rest, relative to the rest's diagonal (``None``: no rest surface).
        gauge: the problem is scale-free (one direction is never determined).
        extra_products: products or simulations spent on the report.
        cell_sensitivity, cell_determined: ``(n_field,)`` per field element, or ``None``.
        regions: per region ``fraction_determined``, ``parameters``, ``determined``,
            ``sensitivity_mean``; ``no_cells`` the parameters without weight.
    """

    determined: bool
    reason: str | None
    source: str
    sensitivity: np.ndarray
    relative: np.ndarray
    parameter_determined: np.ndarray
    singular_values: np.ndarray | None
    effective_rank: int | None
    data_spread: float
    effect: float = math.inf
    reference_misfit: float = 0.0
    reduction: float | None = None
    baseline: str | None = None
    cause: str | None = None
    rigid_deviation: float | None = None
    gauge: bool = False
    extra_products: int = 0
    cell_sensitivity: np.ndarray | None = None
    cell_determined: np.ndarray | None = None
    regions: dict[str, dict[str, float]] = dataclasses.field(default_factory=dict)
    no_cells: int = 0

    @property
    def n_determined(self) -> int:
        return int(self.parameter_determined.sum())

    def summary(self) -> dict[str, Any]:
        """What ``result.json`` holds of it (``identifiability``)."""
        out: dict[str, Any] = {"determined": self.determined,
                               "n_params": int(self.sensitivity.size),
                               "n_determined": self.n_determined,
                               "effective_rank": self.effective_rank, "source": self.source,
                               "effect": _finite(self.effect),
                               "reduction": _finite(self.reduction)}
        if self.reason:
            out["reason"], out["cause"] = self.reason, self.cause
        return out

    def as_json(self) -> dict[str, Any]:
        """The content of ``identifiability.json``."""
        out = self.summary()
        out.update({
            "thresholds": {"relative": RELATIVE_THRESHOLD, "effect": EFFECT_THRESHOLD,
                           "rigid": RIGID_THRESHOLD, "no_reduction": NO_REDUCTION},
            "gauge": self.gauge, "data_spread": self.data_spread,
            "reference_misfit": self.reference_misfit, "baseline": self.baseline,
            "rigid_deviation": self.rigid_deviation,
            "largest_sensitivity": float(self.sensitivity.max()) if self.sensitivity.size else 0.0,
            "extra_products": self.extra_products, "regions": self.regions,
            "no_cells": self.no_cells,
            "singular_values": None if self.singular_values is None
            else [float(v) for v in self.singular_values],
            "parameters": {"sensitivity": [float(v) for v in self.sensitivity],
                           "relative": [float(v) for v in self.relative],
                           "determined": [bool(v) for v in self.parameter_determined]}})
        return out

    def verdict(self) -> str:
        """The summary line's verdict: ``the data determine the material``, else what the
        fit is (``cause``) and that its outputs keep the start."""
        if self.determined:
            return "the data determine the material"
        if self.cause == "reduction":
            return (f"the fit is NOT better than {self.baseline} ({self.reduction:.2f}x): "
                    f"the outputs keep the starting field (identifiability.json)")
        return ("the data do NOT determine the material: the outputs keep the starting field "
                "(identifiability.json)")

    def warning(self) -> str | None:
        """The one warning line of an undetermined fit (``None`` when determined)."""
        if self.determined:
            return None
        if self.cause == "reduction":
            return (f"the fit shows nothing the data determine: {self.reason}; the solver's "
                    f"stop means nothing and the outputs keep the starting field (result.json: "
                    f"determined false; identifiability.json)")
        return (f"the data do not determine the material: {self.reason}; any material fits "
                f"them alike, so the solver's stop means nothing (result.json: determined "
                f"false; identifiability.json)")


def _finite(value: float | None) -> float | str | None:
    """JSON holds no infinity: ``"inf"`` for it."""
    return None if value is None else float(value) if math.isfinite(value) else "inf"


# -- the numbers ----------------------------------------------------------------------------
def parameter_scale(theta: Tensor, transform: str) -> Tensor:
    """``u`` (module docstring): ones for ``exp``, else ``|theta|`` floored at ``1e-3`` of
    its mean (1 where ``theta`` is 0)."""
    if transform == "exp":
        return torch.ones_like(theta)
    magnitude = theta.detach().abs()
    floor = 1e-3 * float(magnitude.mean()) if magnitude.numel() else 0.0
    return magnitude.clamp_min(floor if floor > 0 else 1.0)


def rigid_deviation(rest: np.ndarray, targets: np.ndarray) -> float:
    """Largest per-frame RMS distance of ``targets`` ``(F, V, 3)`` from the best rigid motion
    of ``rest`` ``(V, 3)`` (Kabsch, reflections excluded), over the rest's diagonal."""
    rest = np.asarray(rest, dtype=np.float64)
    targets = np.asarray(targets, dtype=np.float64)
    size = float(np.linalg.norm(rest.max(0) - rest.min(0))) or 1.0
    centred = rest - rest.mean(0)
    moved = targets - targets.mean(1, keepdims=True)                   # (F, V, 3)
    covariance = np.einsum("vi,fvj->fij", centred, moved)               # (F, 3, 3)
    u, _, vt = np.linalg.svd(covariance)
    sign = np.sign(np.linalg.det(np.einsum("fij,fjk->fik", u, vt)))
    u[:, :, -1] *= sign[:, None]
    rotation = np.einsum("fij,fjk->fik", u, vt)                         # rest @ R ~ moved
    fitted = np.einsum("vi,fij->fvj", centred, rotation)
    rms = np.sqrt(((moved - fitted) ** 2).sum(-1).mean(-1))             # (F,)
    return float(rms.max()) / size


def assess(sensitivity: Tensor, singular_values: Tensor | None, data: Tensor,
           rigid: float | None = None, noise_level: float | None = None, size: float = 1.0,
           source: str = "", gauge: bool = False, misfit: float | None = None,
           reduction: float | None = None,
           baseline: str = "the homogeneous material") -> Identifiability:
    """The report's numbers from the per-parameter sensitivities (and singular values).

    Args:
        sensitivity: ``(n,)`` ``s_j`` (module docstring).
        singular_values: of ``J diag(u)`` or ``None``.
        data: ``(m,)`` the data (their spread is the effect's reference without ``misfit``).
        rigid: :func:`rigid_deviation` of the targets or ``None``.
        noise_level: ``delta`` or ``None``; ``size`` the rest's diagonal (with ``rigid``).
        misfit: ``||r_0||``, the misfit the fit started from (the effect's reference).
        reduction: how many times the fit lowered its error below ``baseline``, or ``None``.
    """
    s = sensitivity.detach().double().cpu()
    data = data.detach().double().cpu()
    spread = float(torch.linalg.vector_norm(data - data.mean())) if data.numel() else 0.0
    largest = float(s.max()) if s.numel() else 0.0
    reference = spread if misfit is None else float(misfit)
    effect = largest / reference if reference > 0 else math.inf if largest > 0 else 0.0
    reason = cause = None
    noise_rms = 1.1 * math.sqrt(3.0) * noise_level / math.sqrt(data.numel()) / size \
        if noise_level and data.numel() else 0.0
    if rigid is not None and rigid <= max(RIGID_THRESHOLD, noise_rms):
        cause = "rigid"
        reason = (f"every frame's targets are a rigid motion of the rest (RMS distance from "
                  f"one {rigid:.2g} of the body's size)")
    elif not effect >= EFFECT_THRESHOLD or largest == 0.0:
        cause = "effect"
        reason = (f"the simulated data do not change with the material (an e-fold change of "
                  f"the most-seen parameter moves them by {effect:.2g} of the start's misfit; "
                  f"{EFFECT_THRESHOLD:g} needed)")
    elif reduction is not None and not reduction >= 1.0 + NO_REDUCTION:
        cause = "reduction"
        reason = (f"the fit's error is {reduction:.2f}x below {baseline}'s, within "
                  f"{NO_REDUCTION:.0%} of it")
    relative = s / largest if largest > 0 else torch.zeros_like(s)
    determined = reason is None
    flags = (relative >= RELATIVE_THRESHOLD) & determined
    rank = None
    values = None
    if singular_values is not None:
        values = singular_values.detach().double().cpu()
        top = float(values.max()) if values.numel() else 0.0
        rank = int((values >= RELATIVE_THRESHOLD * top).sum()) if determined and top > 0 else 0
        values = values.numpy()
    return Identifiability(determined, reason, source, s.numpy(), relative.numpy(),
                           flags.numpy(), values, rank, spread, effect, reference, reduction,
                           None if reduction is None else baseline, cause, rigid, gauge)


def from_jacobian(J: Any, theta: Tensor, data: Tensor, transform: str = "exp",
                  **kwargs: Any) -> Identifiability:
    """:func:`assess` of a dense Jacobian ``J`` ``(m, n)`` at ``theta``; rows kept on the
    ranks of a distributed run (no tensor, :mod:`.distributed.ranks.rows`) go through :func:`from_gram`."""
    if not isinstance(J, Tensor):
        return from_gram(J.T @ J, theta, data, transform, **kwargs)
    scaled = J.detach() * parameter_scale(theta, transform).to(J)[None, :]
    values = torch.linalg.svdvals(scaled) if scaled.numel() else scaled.new_zeros(0)
    return assess(torch.linalg.vector_norm(scaled, dim=0), values, data, **kwargs)


def from_gram(gram: Tensor, theta: Tensor, data: Tensor, transform: str = "exp",
              **kwargs: Any) -> Identifiability:
    """:func:`assess` from ``J^T J`` ``(n, n)``: the column norms are the square roots of
    the scaled diagonal, the singular values those of its eigenvalues (clamped at 0; the
    smallest lose half their digits to the squaring, far below the report's thresholds)."""
    scale = parameter_scale(theta, transform).to(gram)
    scaled = gram * scale[:, None] * scale[None, :]
    scaled = 0.5 * (scaled + scaled.T)
    values = torch.linalg.eigvalsh(scaled).clamp_min(0).sqrt().flip(0) if scaled.numel() \
        else scaled.new_zeros(0)
    return assess(scaled.diagonal().clamp_min(0).sqrt(), values, data, **kwargs)


# -- from a run ------------------------------------------------------------------------------
def achieved_reduction(metrics: Mapping[str, Any] | None,
                       history: Sequence[Mapping[str, Any]] | None, own_start: bool = True
                       ) -> tuple[float | None, str]:
    """How many times the fit lowered its error, and below what: a body's
    ``surface_err_reduction`` (the homogeneous material), else history row 0's ``misfit``
    over the final ``metrics``' (the start); ``None`` where neither is known, where the start
    reproduced the data already, or where the start is not the problem's own (``own_start``
    false: ``init=`` an earlier fit, which a good continuation barely improves)."""
    metrics = metrics or {}
    if metrics.get("surface_err_reduction") is not None:
        return float(metrics["surface_err_reduction"]), "the homogeneous material"
    start = history[0].get("misfit") if history and own_start else None
    end = metrics.get("misfit")
    if start is None or end is None or not float(start) > 0:
        return None, "the start"
    return (float(start) / float(end) if float(end) > 0 else math.inf), "the start"


def identify(problem: InverseProblem, lin: Any, theta: Tensor,
             metrics: Mapping[str, Any] | None = None,
             history: Sequence[Mapping[str, Any]] | None = None,
             own_start: bool = True) -> Identifiability:
    """The report of ``problem`` at its fitted ``theta`` (module docstring).

    ``lin``: the solver's last linearisation (``solver.lin``) or ``None``; used where it is
    at ``theta`` and linearises the problem's own residual. ``metrics``: the final
    metrics at ``theta``, ``history``: the run's rows (row 0: the start), for the misfit
    the fit started from and the reduction it achieved (:func:`achieved_reduction`); without
    them the effect is measured against the residual at ``theta`` and no reduction is asked.
    ``own_start``: the fit started at the problem's own start (``theta0``, not ``init=``).
    """
    theta = theta.detach()
    data = problem.data
    transform = problem.parameterization.transform
    usable = lin is not None and getattr(lin, "r", None) is not None and \
        lin.r.numel() == data.numel() and torch.equal(lin.theta, theta)
    reduction, baseline = achieved_reduction(metrics, history, own_start)
    start = history[0].get("misfit") if history else None
    common = {"gauge": bool(problem.scale_free), "reduction": reduction,
              "baseline": baseline, **_rigid(problem)}
    if start is not None:
        common["misfit"] = float(start)
    elif usable:
        common["misfit"] = float(torch.linalg.vector_norm(lin.r))
    if usable and getattr(lin, "dense", False):
        report = from_jacobian(lin.jacobian(), theta, data, transform,
                               source="dense Jacobian of the last iteration", **common)
    else:
        extra = 0 if usable else 1
        if not usable:
            lin = problem.residual().linearize(theta)
            common.setdefault("misfit", float(torch.linalg.vector_norm(lin.r)))
        generator = torch.Generator().manual_seed(0)
        norms = column_norms(lin.vjp, lin.r, theta, PROBES, generator)
        s = norms * parameter_scale(theta, transform).to(norms)
        report = assess(s, None, data, source=f"column norms from {PROBES} products J^T w"
                        + ("" if usable else " at a new linearisation (one simulation)"),
                        **common)
        report.extra_products = PROBES + extra
    _per_cell(problem, theta, report)
    return report


def _rigid(problem: InverseProblem) -> dict[str, Any]:
    """``rigid``, ``noise_level``, ``size`` of a body whose data are its observed surface
    vertices (``animation``, ``observed_vertices``; frame-major ``(F, n_obs, 3)``)."""
    out: dict[str, Any] = {"noise_level": problem.noise_level}
    if not isinstance(problem, BodyProblem):
        return out
    rest = np.asarray(problem.animation.rest_vertices)[np.asarray(
        problem.observed_vertices.cpu())]
    data = problem.data.detach().cpu().numpy()
    if len(rest) < 3 or data.size % (3 * len(rest)):
        return out
    out["rigid"] = rigid_deviation(rest, data.reshape(-1, len(rest), 3))
    out["size"] = float(np.linalg.norm(rest.max(0) - rest.min(0))) or 1.0
    return out


def _per_cell(problem: InverseProblem, theta: Tensor, report: Identifiability) -> None:
    """Per field element and per region (module docstring); nothing where the
    parameterisation has no plain basis."""
    parameterization = problem.parameterization
    n = int(theta.numel())
    basis = getattr(parameterization, "basis", None)
    n_field = int(getattr(parameterization, "n_field", -1))
    if basis is None and n_field == n:
        weights = torch.eye(n, dtype=torch.float64).to_sparse()
    elif isinstance(basis, Tensor) and tuple(basis.shape) == (n_field, n):
        weights = (basis.to_sparse() if basis.layout == torch.strided else basis
                   ).to_sparse_coo().coalesce().cpu().double()
        weights = torch.sparse_coo_tensor(weights.indices(), weights.values().abs(),
                                          weights.shape).coalesce()
    else:
        return
    row_sums = torch.sparse.mm(weights, torch.ones(n, 1, dtype=torch.float64))[:, 0]
    row_sums = row_sums.clamp_min(torch.finfo(torch.float64).tiny)

    def cell_mean(values: np.ndarray) -> np.ndarray:
        v = torch.as_tensor(values, dtype=torch.float64)[:, None]
        return (torch.sparse.mm(weights, v)[:, 0] / row_sums).numpy()

    report.cell_sensitivity = cell_mean(report.relative)
    report.cell_determined = cell_mean(report.parameter_determined.astype(np.float64))
    volumes = np.ones(n_field)
    labels, names = None, []
    if isinstance(problem, BodyProblem) and len(problem.mesh.cells) == n_field:
        volumes = np.abs(np.asarray(problem.mesh.signed_volumes(), dtype=np.float64))
        labels, names = problem.tet_regions, list(problem.region_names)
    if labels is None or len(labels) != n_field:
        labels, names = np.zeros(n_field, dtype=np.int64), ["body"]
    labels = np.asarray(labels)
    # each parameter belongs to the region holding most of its (volume-weighted) weight
    masses = np.stack([torch.sparse.mm(weights.t(), torch.as_tensor(
        volumes * (labels == r), dtype=torch.float64)[:, None])[:, 0].numpy()
        for r in range(len(names))], axis=1)                        # (n, regions)
    home = masses.argmax(1)
    no_cells = masses.sum(1) <= 0
    for r, name in enumerate(names):
        cells = labels == r
        volume = volumes[cells].sum()
        mine = (home == r) & ~no_cells
        report.regions[name] = {
            "fraction_determined": float((volumes[cells] * report.cell_determined[cells]).sum()
                                         / volume) if volume > 0 else 0.0,
            "sensitivity_mean": float((volumes[cells] * report.cell_sensitivity[cells]).sum()
                                      / volume) if volume > 0 else 0.0,
            "parameters": int(mine.sum()),
            "determined": int((mine & report.parameter_determined).sum())}
    report.no_cells = int(no_cells.sum())


__all__ = ["EFFECT_THRESHOLD", "Identifiability", "NO_REDUCTION", "PROBES",
           "RELATIVE_THRESHOLD", "RIGID_THRESHOLD", "achieved_reduction", "assess",
           "from_jacobian", "identify", "parameter_scale", "rigid_deviation"]
