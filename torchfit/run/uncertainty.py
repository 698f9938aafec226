"""Every number with its uncertainty: the Gauss-Newton (Laplace) posterior of a fit at its end.

After the solver stops, :func:`estimate` gives each fitted parameter, each field element
(cell) and each region a standard deviation, following the Laplace approximation of
hIPPYlib (``GaussianLRPosterior``): the posterior covariance is the inverse of the
Gauss-Newton Hessian of the negative log posterior, ``Cov = sigma^2 (J^T J + R)^-1``.

* **No prior.** Our fits are plain least squares (``R = 0``), so ``J^T J`` is inverted on the
  subspace the data determine. The parameters the identifiability report calls not
  determined (:mod:`.identifiability`: their column is under 1 % of the strongest) are
  *undetermined*: their standard deviation is infinite (``null`` in JSON). Those the data
  still see (column at least ``RANK_TOLERANCE`` of the largest) stay in the covariance,
  so their spread is *marginalised* into the others'; only the invisible ones (in a fitted
  grid, nodes driven to moduli where the data no longer see them, columns ``1e-7`` to
  ``1e-10`` of the largest) are held at their fitted values (:func:`held_parameters`).
  Holding every undetermined one made the others' covariance conditional on values the
  noise had moved: on the noisy short arm their spread over noise draws was 1.2x the
  standard deviation and the band covered the truth on 81 % of the determined parameters
  (90 % marginalised; 86 % and 94 % with bounds; ``docs/notes/uncertainty.md``). On the
  free parameters not held, the SVD ``J = U S V^T``, its singular values
  ``s_k >= RANK_TOLERANCE * s_max`` (the numerical rank) give
  ``Cov = sigma^2 V_k S_k^-2 V_k^T``; a parameter with more than ``NULL_COMPONENT`` of its
  unit vector in the remaining directions is undetermined too. A cell or region whose
  field the undetermined parameters make more than ``HELD_SHARE`` of is undetermined.
  Weakly determined directions are kept, so their standard deviations are large, not
  hidden.
* **The gauge.** A scale-free problem (only prescribed displacements) never fixes the overall
  scale: its scale direction ``g`` is projected out of ``J`` first, and every number is *up to
  the overall scale* (``gauge: true``): the spread of the field's shape, not of its level.
  Which shape is meant is fixed by an anchor: the field's volume-weighted mean ``log E``
  (the weights ``a = B^T volumes``, the volume each parameter carries) is held, so
  ``Cov = P C P^T`` with ``P = I - g a^T / (a^T g)``. (Holding the plain mean of ``theta``
  instead would mix the huge spread of grid nodes that barely touch the body into every
  other parameter's.)
* **Bounds.** A parameter on a bound the solver keeps is held there (its column is left
  out; its standard deviation is ``null``, counted in ``on_bound``): the Laplace
  approximation does not hold at the edge of the box.
* **The noise.** ``sigma``, the standard deviation of one datum: ``delta / sqrt(m)`` where the
  problem knows its noise level ``delta`` (synthetic noise), else from the residual,
  ``sigma^2 = ||r||^2 / (m - n_eff)`` with ``n_eff`` the rank kept (``sigma_source``).
* **In the parameters' meaning.** ``theta`` of the ``exp`` transform is a log-modulus: its
  standard deviation ``sd`` is one of ``log E``, reported as the two-sigma multiplicative band
  ``factor = exp(2 sd)`` (the modulus lies in ``[E / factor, E * factor]``). For
  ``identity``, ``sd`` is absolute, in the field's units.
* **Per cell** ``c`` (``field = B transform(theta)``): ``w_c = d log E_c / d theta``
  (``identity``: ``d E_c / d theta``) and ``var_c = w_c^T Cov w_c``. **Per region** (the
  body's labels, else one region ``body``, as :mod:`.identifiability` defines them): the
  variance of the region's volume-weighted mean modulus ``Ebar``, ``g^T Cov g`` with
  ``g = d log Ebar / d theta`` (relative; ``identity``: absolute).

**At a minimum only.** The posterior is centred on the least-squares minimum; a fit stopped
short of it (``max_iter``) carries an error the noise does not explain. The Gauss-Newton
step that remains, ``step = -Cov J^T r / sigma^2`` (from the same factor, no product), says
how far: ``short_of_minimum`` counts the parameters it would move by more than one standard
deviation, and the summary line says that the band then does not hold (fit longer, or
``init=`` this run).

Where the Jacobian comes from (``source``): the dense Jacobian of the solver's last
accepted point (Levenberg-Marquardt and Gauss-Newton on the dense path: no simulation, no
solve), or ``n`` products ``J e_j`` at the solver's last linearisation where
``n <= MATRIX_FREE_MAX_PARAMS`` (one solve per frame and parameter, no factorisation; where
the solver holds none at the fitted point, a new one there: one simulation);
otherwise the uncertainty is **not computed** (``computed: false`` with the reason): a
low-rank (Lanczos) estimate of ``J^T J`` would give the well-determined directions only,
and without a prior it says nothing of the rest, so no number is better than a
misleading one. ``cost`` gives the seconds and the products spent.

**The spread the mesh causes** (a body with ``problem.mesh_check=true``,
:func:`compare_meshes`): the whole fit repeated on a second tetrahedralisation of the same
surface (the edge length times ``MESH_CHECK_EDGE``: another cache key, so a fresh mesh),
and per region the relative difference of the volume-weighted mean moduli. It costs a
second fit (its seconds and factorizations are reported); the posterior above does not
contain it (it is the discretisation's error, not the noise's).
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Callable

import numpy as np
import torch
from torch import Tensor

from ..problems import BodyProblem, InverseProblem

#: a singular value of ``J`` below this fraction of the largest is not seen (the nullspace)
RANK_TOLERANCE = 1e-6
#: a parameter with more than this (squared) fraction of its unit vector in the nullspace is
#: undetermined
NULL_COMPONENT = 1e-6
#: a cell (region) whose field the undetermined parameters make more than this share of is
#: undetermined; below it their spread is in the cell's (the held ones' is not)
HELD_SHARE = 0.5
#: the band reported: the modulus within ``SIGMAS`` standard deviations
SIGMAS = 2.0
#: matrix-free, the Jacobian is formed from ``n`` products ``J e_j`` up to this many parameters
MATRIX_FREE_MAX_PARAMS = 256
#: ``problem.mesh_check``: the second mesh's edge length, a factor of the first's
MESH_CHECK_EDGE = 0.9
#: a parameter within this relative distance of a bound is on it (the solvers' ``BOUND_TOL``)
ON_BOUND = 1e-9


@dataclasses.dataclass
class Uncertainty:
    """The posterior spread (module docstring); arrays are NumPy.

    Attributes:
        computed: whether there is one (``reason`` says why not).
        source: where the Jacobian came from.
        transform: ``exp`` (``sd`` of ``log E``, relative) or ``identity`` (absolute).
        sigma: the standard deviation of one datum; ``sigma_source`` ``noise level`` or
            ``residual``.
        m, rank: the data count and the rank kept (``n_eff``).
        gauge: numbers are up to the overall scale.
        sd: ``(n,)`` per parameter (``inf`` undetermined, ``nan`` on a bound).
        cell_sd: ``(n_field,)`` per field element, or ``None``.
        regions: per region ``sd`` (of the volume-weighted mean) and ``factor``.
        on_bound, undetermined: parameter counts.
        cost: ``seconds``, ``products`` (``J e_j``), ``factorizations`` (always 0).
        mesh_check: per region the fit on a second mesh (:func:`compare_meshes`), or ``None``.
        gauge_direction, anchor: ``(n,)`` with a gauge, ``g`` and ``a`` (module docstring).
        step: ``(n,)`` the Gauss-Newton step that remains; ``short_of_minimum`` the
            parameters it moves by more than one ``sd`` (module docstring).
    """

    computed: bool
    reason: str | None = None
    source: str = ""
    transform: str = "exp"
    sigma: float = math.nan
    sigma_source: str = ""
    m: int = 0
    rank: int = 0
    gauge: bool = False
    sd: np.ndarray | None = None
    cell_sd: np.ndarray | None = None
    regions: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)
    on_bound: int = 0
    undetermined: int = 0
    cost: dict[str, float] = dataclasses.field(default_factory=dict)
    mesh_check: dict[str, Any] | None = None
    gauge_direction: np.ndarray | None = None
    anchor: np.ndarray | None = None
    step: np.ndarray | None = None
    short_of_minimum: int = 0

    @property
    def relative(self) -> bool:
        return self.transform == "exp"

    def finite(self) -> np.ndarray:
        """``(n,)`` the parameters with a finite standard deviation."""
        return np.zeros(0, bool) if self.sd is None else np.isfinite(self.sd)

    def factor(self, sd: Any) -> Any:
        """The ``SIGMAS`` band of ``sd``: ``exp(SIGMAS sd)`` (``exp``), else ``SIGMAS sd``."""
        return np.exp(SIGMAS * np.asarray(sd)) if self.relative else SIGMAS * np.asarray(sd)

    def coverage(self, theta: Tensor, truth: Tensor, among: np.ndarray | None = None
                 ) -> tuple[float, int]:
        """The fraction of the parameters (``among``, default every one with a finite ``sd``)
        whose ``truth`` lies within ``SIGMAS`` standard deviations of ``theta``, and their
        count; with a gauge both are compared up to the overall scale, as the covariance
        holds it: the error ``e`` taken as ``P e`` (module docstring)."""
        assert self.sd is not None
        finite = self.finite()
        chosen = finite if among is None else np.asarray(among, bool) & finite
        error = (theta.detach().double().cpu() - truth.detach().double().cpu()).numpy()
        if self.gauge and self.gauge_direction is not None:
            g = self.gauge_direction
            a = g if self.anchor is None else self.anchor
            error = error - g * float(a @ error) / float(a @ g)
        inside = np.abs(error[chosen]) <= SIGMAS * self.sd[chosen]
        return (float(inside.mean()) if inside.size else math.nan), int(inside.size)

    def summary(self) -> dict[str, Any]:
        """What ``result.json`` holds of it (``uncertainty``)."""
        if not self.computed:
            return {"computed": False, "reason": self.reason}
        finite = self.finite()
        sd = self.sd[finite] if self.sd is not None else np.zeros(0)
        out: dict[str, Any] = {
            "computed": True, "source": self.source, "sigma": self.sigma,
            "sigma_source": self.sigma_source, "rank": self.rank, "gauge": self.gauge,
            "meaning": "sd of log E; factor = exp(2 sd): E within [E/factor, E*factor]"
            if self.relative else "sd of the field, absolute; band = 2 sd",
            "parameters_with_sd": int(finite.sum()), "undetermined": self.undetermined,
            "on_bound": self.on_bound, "short_of_minimum": self.short_of_minimum,
            "sd_median": float(np.median(sd)) if sd.size else None,
            "factor_median": float(self.factor(np.median(sd))) if sd.size else None,
            "regions": self.regions, "cost": self.cost}
        if self.mesh_check is not None:
            out["mesh_check"] = self.mesh_check
        return out

    def as_json(self) -> dict[str, Any]:
        """:meth:`summary` with the per-parameter standard deviations (``null``: none)."""
        out = self.summary()
        if self.sd is not None:
            out["parameters"] = {"sd": [float(v) if math.isfinite(v) else None
                                        for v in self.sd]}
        if self.step is not None:
            out["parameters"]["remaining_step"] = [float(v) for v in self.step]
        return out

    def text(self) -> str | None:
        """The summary line's piece: ``E within x1.31 (2 sigma; bone x1.1, ...)``."""
        if not self.computed:
            return f"uncertainty not computed ({self.reason})"
        parts = []
        for name, values in self.regions.items():
            factor = values.get("factor")
            parts.append(f"{name} {_band(factor, self.relative)}")
        finite = self.finite()
        median = _band(float(self.factor(np.median(self.sd[finite]))) if finite.any()
                       else None, self.relative)
        scale = ", up to the overall scale" if self.gauge else ""
        text = (f"2-sigma band {median} (median of {int(finite.sum())} parameters, "
                f"sigma from the {self.sigma_source}{scale}); per region {', '.join(parts)}")
        if self.short_of_minimum:
            text += (f"; the fit stopped short of its minimum (one more Gauss-Newton step "
                     f"moves {self.short_of_minimum} parameters by more than their sd), so "
                     f"the band does not hold yet")
        if self.mesh_check is not None and self.mesh_check.get("regions"):
            text += "; on a second mesh " + ", ".join(
                f"{name} {100 * values['difference']:+.1f} %"
                for name, values in self.mesh_check["regions"].items())
        return text


def _band(factor: float | None, relative: bool) -> str:
    if factor is None or not math.isfinite(factor):
        return "undetermined"
    return f"x{factor:.4g}" if relative else f"+-{factor:.3g}"


# -- the numbers ----------------------------------------------------------------------------
def covariance_factor(J: Tensor, sigma: float | None = None, gauge: Tensor | None = None,
                      free: Tensor | None = None, residual: Tensor | None = None,
                      anchor: Tensor | None = None) -> tuple[Tensor, Tensor, float, int]:
    """``L`` ``(n, k)`` with ``Cov = L L^T`` (module docstring), the per-parameter
    ``(n,)`` undetermined fraction ``||V_null^T e_j||^2`` (1 where not ``free``), ``sigma``
    and the rank ``k``.

    Args:
        J: ``(m, n)`` the Jacobian at the fitted point.
        sigma: the noise's standard deviation per datum, or ``None``: from ``residual``.
        gauge: ``(n,)`` the unit direction the data never fix (projected out), or ``None``.
        free: ``(n,)`` bool, the parameters not held on a bound (default all).
        residual: ``(m,)`` the residual at the fitted point (with ``sigma=None``).
        anchor: ``(n,)`` with a gauge, the weights ``a`` whose weighted sum of ``theta`` is
            held (module docstring); ``None``: the orthogonal projection (``a = g``).
    """
    J = J.detach().double().cpu()
    m, n = J.shape
    free = torch.ones(n, dtype=torch.bool) if free is None else free.cpu().bool()
    cols = torch.nonzero(free).flatten()
    A = J[:, cols]
    if gauge is not None:
        g = gauge.detach().double().cpu()[cols]
        if float(g.norm()) > 0:
            g = g / g.norm()
            A = A - (A @ g)[:, None] * g[None, :]
    _, s, vt = torch.linalg.svd(A, full_matrices=False)
    top = float(s.max()) if s.numel() else 0.0
    keep = s >= RANK_TOLERANCE * top if top > 0 else torch.zeros_like(s, dtype=torch.bool)
    rank = int(keep.sum())
    if sigma is None:
        assert residual is not None
        dof = max(m - rank, 1)
        sigma = float(torch.linalg.vector_norm(residual.detach().double().cpu())) / math.sqrt(dof)
    L = torch.zeros(n, rank, dtype=torch.float64)
    L[cols] = vt[keep].T / s[keep][None, :] * sigma
    # the free parameters' share of the directions not kept (those with a tiny singular
    # value and, with fewer rows than columns, the ones the SVD does not return)
    kept = (vt[keep] ** 2).sum(0) if rank else torch.zeros(len(cols), dtype=torch.float64)
    null = torch.ones(n, dtype=torch.float64)
    null[cols] = (1.0 - kept).clamp_min(0.0)
    if gauge is not None and float(g.norm()) > 0:
        null[cols] = (null[cols] - g ** 2).clamp_min(0.0)    # the gauge is not a nullspace
        if anchor is not None:
            a = anchor.detach().double().cpu()[cols]
            if float(a @ g) > 0:
                L[cols] = L[cols] - g[:, None] * (a @ L[cols])[None, :] / float(a @ g)
    return L, null, sigma, rank


def estimate(problem: InverseProblem, lin: Any, theta: Tensor,
             free: Tensor | None = None, determined: np.ndarray | None = None) -> Uncertainty:
    """The uncertainty of ``problem`` at its fitted ``theta`` (module docstring).

    ``lin``: the solver's last linearisation (``solver.lin``) or ``None``; used where it is
    at ``theta`` and linearises the problem's own residual (as :func:`.identify` does).
    ``free``: ``(n,)`` bool, the parameters off the bounds (default: from
    ``problem.theta_bounds()``). ``determined``: ``(n,)`` bool, the parameters the data
    determine (the identifiability report's); the others get no ``sd``, and those the data
    do not see are held (:func:`held_parameters`, module docstring).
    """
    start = time.perf_counter()
    theta = theta.detach()
    data = problem.data
    transform = problem.parameterization.transform
    n = int(theta.numel())
    usable = lin is not None and getattr(lin, "r", None) is not None and \
        lin.r.numel() == data.numel() and torch.equal(lin.theta, theta)
    products = 0
    if usable and getattr(lin, "dense", False):
        J, source = lin.jacobian(), "dense Jacobian of the last iteration"
    elif n <= MATRIX_FREE_MAX_PARAMS:
        # where the solver holds none at the fitted point (outputs written again from a
        # checkpoint), a new linearisation there, as the identifiability report makes
        where = "the last linearisation" if usable else "a new linearisation (one simulation)"
        if not usable:
            lin = problem.residual().linearize(theta)
        products = n
        J, source = lin.jacobian(), f"{n} products J e_j at {where}"
    else:
        return Uncertainty(False, reason=f"{n} parameters, matrix-free (no dense Jacobian; "
                           f"more than {MATRIX_FREE_MAX_PARAMS} products J e_j)",
                           transform=transform)
    if not isinstance(J, Tensor):      # rows kept on the ranks of a distributed run
        return Uncertainty(False, reason="the Jacobian's rows are kept on their ranks",
                           transform=transform)
    if free is None:
        free = off_bounds(problem, theta)
    free = free.cpu().bool()
    not_determined = torch.zeros(n, dtype=torch.bool) if determined is None else \
        torch.as_tensor(~np.asarray(determined, bool))
    held = held_parameters(J, free, not_determined)
    gauge = problem.parameterization.scale_direction(theta) if problem.scale_free else None
    anchor = None if gauge is None else parameter_volumes(problem, n)
    noise = problem.noise_level
    sigma = noise / math.sqrt(data.numel()) if noise else None
    L, null, sigma, rank = covariance_factor(J, sigma, gauge, free & ~held, lin.r, anchor)
    undetermined = ((null > NULL_COMPONENT) | not_determined) & free | held
    sd = (L ** 2).sum(1).sqrt().numpy()
    sd[undetermined.numpy()] = math.inf
    sd[~free.cpu().numpy()] = math.nan
    report = Uncertainty(True, source=source, transform=transform, sigma=float(sigma),
                         sigma_source="noise level" if noise else "residual",
                         m=int(data.numel()), rank=rank, gauge=gauge is not None, sd=sd,
                         on_bound=int((~free).sum()), undetermined=int(undetermined.sum()))
    if gauge is not None:
        report.gauge_direction = gauge.detach().double().cpu().numpy()
        report.anchor = None if anchor is None else anchor.numpy()
    Jd = J.detach().double().cpu()
    step = -(L @ (L.T @ (Jd.T @ lin.r.detach().double().cpu()))) / sigma ** 2
    report.step = step.numpy()
    report.short_of_minimum = int((np.abs(report.step) > sd)[np.isfinite(sd)].sum())
    _per_cell(problem, theta, L, np.isinf(sd), report)
    report.cost = {"seconds": time.perf_counter() - start, "products": products,
                   "factorizations": 0}
    return report


def held_parameters(J: Tensor, free: Tensor, not_determined: Tensor) -> Tensor:
    """``(n,)`` bool: the parameters held at their fitted values, the ``not_determined``
    free ones whose column of ``J`` ``(m, n)`` is under ``RANK_TOLERANCE`` of the largest
    free column (the data do not see them); the other undetermined ones stay in the
    covariance, their spread marginalised into the rest (module docstring)."""
    free = free.cpu().bool()
    columns = torch.linalg.vector_norm(J.detach().double().cpu(), dim=0)
    top = float(columns[free].max()) if bool(free.any()) else 0.0
    invisible = columns < RANK_TOLERANCE * top
    return not_determined.cpu().bool() & free & invisible


def off_bounds(problem: InverseProblem, theta: Tensor) -> Tensor:
    """``(n,)`` bool: the parameters not on a bound of ``problem.theta_bounds()``."""
    bounds = problem.theta_bounds()
    free = torch.ones(theta.numel(), dtype=torch.bool)
    if bounds is None:
        return free
    t = theta.detach().double().cpu()
    lower, upper = (b.detach().double().cpu() for b in bounds)
    near_low = torch.isfinite(lower) & (t <= lower + ON_BOUND * lower.abs().clamp(min=1.0))
    near_high = torch.isfinite(upper) & (t >= upper - ON_BOUND * upper.abs().clamp(min=1.0))
    return free & ~near_low & ~near_high


def parameter_volumes(problem: InverseProblem, n: int) -> Tensor | None:
    """``(n,)`` the volume each parameter carries, ``B^T volumes`` (the field elements'
    volumes: a body's tetrahedra, else 1 each), or ``None`` where the parameterisation has
    no plain basis."""
    B = _basis(problem, n)
    if B is None:
        return None
    volumes, _, _ = _cell_geometry(problem, B.shape[0])
    return torch.sparse.mm(B.t(), torch.as_tensor(volumes, dtype=torch.float64)[:, None])[:, 0]


def _basis(problem: InverseProblem, n: int) -> Tensor | None:
    """The parameterisation's basis ``B`` ``(n_field, n)`` as a sparse COO float64 tensor
    on the CPU (the identity without one), or ``None`` where it has no plain basis."""
    parameterization = problem.parameterization
    basis = getattr(parameterization, "basis", None)
    n_field = int(getattr(parameterization, "n_field", -1))
    if basis is None and n_field == n:
        return torch.eye(n, dtype=torch.float64).to_sparse()
    if isinstance(basis, Tensor) and tuple(basis.shape) == (n_field, n):
        return (basis.to_sparse() if basis.layout == torch.strided else basis
                ).to_sparse_coo().coalesce().cpu().double()
    return None


def _cell_geometry(problem: InverseProblem, n_field: int
                   ) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Volumes ``(n_field,)``, region labels and names of the field elements (the body's
    tetrahedra and labels, else unit volumes and one region ``body``)."""
    volumes, labels, names = np.ones(n_field), None, []
    if isinstance(problem, BodyProblem) and len(problem.mesh.cells) == n_field:
        volumes = np.abs(np.asarray(problem.mesh.signed_volumes(), dtype=np.float64))
        labels, names = problem.tet_regions, list(problem.region_names)
    if labels is None or len(labels) != n_field:
        labels, names = np.zeros(n_field, dtype=np.int64), ["body"]
    return volumes, np.asarray(labels), names


def _per_cell(problem: InverseProblem, theta: Tensor, L: Tensor, infinite: np.ndarray,
              report: Uncertainty) -> None:
    """Per field element and per region (module docstring); nothing where the
    parameterisation has no plain basis."""
    n = int(theta.numel())
    t = theta.detach().double().cpu()
    effect = t.exp() if report.relative else torch.ones_like(t)   # d transform / d theta
    B = _basis(problem, n)
    if B is None:
        return
    n_field = int(B.shape[0])
    # d field_c / d theta_j = B_cj effect_j; the cells' field values
    field = torch.sparse.mm(B, (t.exp() if report.relative else t)[:, None])[:, 0]
    BL = torch.sparse.mm(B, effect[:, None] * L)                        # (n_field, k)
    # the share of each cell's field that undetermined parameters make (held at their value)
    held = torch.sparse.mm(B, (effect * torch.as_tensor(infinite, dtype=torch.float64))[:, None]
                           )[:, 0]
    total = torch.sparse.mm(B, effect[:, None])[:, 0].clamp_min(torch.finfo(torch.float64).tiny)
    touches = (held / total).numpy() > HELD_SHARE
    if report.relative:
        BL = BL / field.abs().clamp_min(torch.finfo(torch.float64).tiny)[:, None]
    cell_sd = (BL ** 2).sum(1).sqrt().numpy()
    cell_sd[touches] = math.inf
    report.cell_sd = cell_sd
    volumes, labels, names = _cell_geometry(problem, n_field)
    v = torch.as_tensor(volumes, dtype=torch.float64)
    for r, name in enumerate(names):
        cells = torch.as_tensor(labels == r)
        if not bool(cells.any()):
            continue
        weights = torch.where(cells, v, torch.zeros_like(v))
        mean = float(weights @ field) / float(weights.sum())
        g = (weights[:, None] * BL * (field.abs()[:, None] if report.relative else 1.0)
             ).sum(0) / float(weights.sum())
        sd = float(g.norm()) / (abs(mean) if report.relative and mean else 1.0)
        if float(weights @ held) / max(float(weights @ total), 1e-300) > HELD_SHARE:
            sd = math.inf
        report.regions[name] = {"volume_mean": mean,
                                "sd": sd if math.isfinite(sd) else None,
                                "factor": float(report.factor(sd)) if math.isfinite(sd)
                                else None}


# -- the spread the mesh causes ------------------------------------------------------------------
def second_mesh_settings(problem: BodyProblem) -> Any:
    """The body's settings for another tetrahedralisation of the same surface: the edge
    length times ``MESH_CHECK_EDGE`` (``tet_count`` divided by its cube where given), so
    the mesh is built afresh (another cache key), at nearly the same resolution; no
    validation frames, no second check."""
    settings = getattr(problem, "settings_for_frames", None)
    cfg = settings(list(problem.frame_numbers())) if settings is not None else problem.cfg
    changes: dict[str, Any] = {"mesh_check": False}
    if getattr(cfg, "tet_count", None):
        changes["tet_count"] = int(round(cfg.tet_count / MESH_CHECK_EDGE ** 3))
    else:
        changes["tet_edge_length"] = cfg.tet_edge_length * MESH_CHECK_EDGE
    return dataclasses.replace(cfg, **changes)


def compare_meshes(problem: BodyProblem, field: Tensor,
                   refit: Callable[[InverseProblem], tuple[Tensor, dict[str, Any]]]
                   ) -> dict[str, Any]:
    """The fit repeated on a second mesh of the same surface (``problem.mesh_check``):
    per region the volume-weighted mean modulus on each mesh and their relative
    ``difference`` (second / first - 1; where the data never fix the scale, after the
    second field is scaled to the first's volume mean over the body), the meshes' sizes
    and the cost of the second fit. ``refit``: fits a problem, returns its field and
    ``{"seconds", "factorizations", "solves"}``."""
    start = time.perf_counter()
    other = type(problem)(second_mesh_settings(problem))
    other_field, cost = refit(other)
    mine = problem.report.region_summary(field)
    theirs = other.report.region_summary(other_field)
    scale = 1.0
    if problem.scale_free:
        scale = _body_mean(problem, field) / _body_mean(other, other_field)
    regions = {}
    for name, values in mine.items():
        if name not in theirs:
            continue
        first, second = values["volume_mean"], scale * theirs[name]["volume_mean"]
        regions[name] = {"first": first, "second": second,
                         "difference": second / first - 1.0 if first else math.nan}
    return {"tets": [int(len(problem.mesh.cells)), int(len(other.mesh.cells))],
            "setting": {k: v for k, v in dataclasses.asdict(second_mesh_settings(problem)).items()
                        if k in ("tet_edge_length", "tet_count")},
            "aligned_scale": scale if problem.scale_free else None, "regions": regions,
            "cost": {**cost, "seconds": time.perf_counter() - start}}


def _body_mean(problem: BodyProblem, field: Tensor) -> float:
    volumes = np.abs(np.asarray(problem.mesh.signed_volumes(), dtype=np.float64))
    return float(volumes @ field.detach().double().cpu().numpy() / volumes.sum())


__all__ = ["HELD_SHARE", "MATRIX_FREE_MAX_PARAMS", "MESH_CHECK_EDGE", "NULL_COMPONENT", "RANK_TOLERANCE", "SIGMAS",
           "Uncertainty", "compare_meshes", "covariance_factor", "estimate", "off_bounds",
           "parameter_volumes", "second_mesh_settings"]
