r"""Total-variation regularisation by split Bregman for non-linear forward models.

Minimises

.. math::  \Phi_\mu(\theta) = TV(\theta) + \frac{\mu}{2} \|r(\theta)\|^2,
           \qquad TV(\theta) = \sum_g \|(D\theta + c)_g\|_2

where ``r`` is the residual of any problem (the solver sees only ``r``, ``J v`` and
``J^T w``), ``D`` the sparse difference operator of the parameterisation (rows
``e_j - e_i`` for neighbouring parameters: a chain, a 2-D or 3-D grid of cells, a coarse
grid, the shared faces of an unstructured mesh; handed over by the caller, the solver
never builds it), ``g`` runs over groups of rows of ``D`` (every row its own group:
*anisotropic* TV; the x-, y- (and z-) differences of one cell in one group: *isotropic*
TV, ``groups`` from ``parameterization.difference_groups()``) and ``c`` an optional
constant offset (differences to fixed known values such as ghost cells; zero by
default).

The iteration (Goldstein and Osher's split Bregman, i.e. scaled ADMM on ``d = D theta + c``)::

    theta <- argmin  mu/2 ||r(theta)||^2 + beta/2 ||D theta + c - d + b||^2   (inner solve)
    d     <- shrink(D theta + c + b, 1/beta)                                   (per group)
    b     <- b + D theta + c - d                                               (Bregman update)

Design
------
* **The inner solve is the package's least-squares solver.** The penalised problem is
  itself least squares: the model residual scaled by ``sqrt(mu)`` stacked on the linear
  residual ``sqrt(beta) (D theta + c - d + b)`` (:mod:`.stacked`). ``inner_max_iter``
  Gauss-Newton (default) or Levenberg-Marquardt steps from the current ``theta`` solve it
  matrix-free by CGLS; the ``D`` block costs sparse products, no solve. Its CGLS stops on
  the relative normal-equation residual ``cg_rtol`` (the REGINN rule of the data fit,
  ``||J d + r|| <= eta ||r||``, can never be met by a problem whose minimum is not zero).
  The model residual is wrapped in :class:`~.stacked.CachedResidual`: the first inner
  step of an outer iteration reuses the linearisation at which the previous one ended,
  so every distinct parameter vector is simulated, hence factorised, once (DESIGN.md's
  cost model; the tests check it with the counters).
* **Shrinkage** is the proximal map of the group norm (:class:`GroupTV`),
  ``d_g = max(||t_g|| - 1/beta, 0) t_g / ||t_g||``; for singleton groups the scalar soft
  threshold. ``isotropic=true`` without ``groups`` is anisotropic TV (a chain has no
  groups to join).
* **Weights a user does not tune.** ``theta`` is dimensionless (``log k``); ``r`` has
  data units and ``m`` entries, so ``mu`` scales like ``1 / ||J||^2``:

  - Fixed weight (no noise level, or ``continuation=false``): ``mu`` defaults to
    ``mu_rel / ||J(theta0)||_2^2`` (power iteration on ``J^T J``: products at ``theta0``,
    no factorisation). The largest curvature of the data term is then ``mu_rel`` whatever
    the number of data and their units: dense and sparse data need no retuning.
  - Known noise level ``delta`` (``continuation=true``, the default):
    **discrepancy-driven continuation**. Stages ``mu_k = mu_0 growth^k``, each run by
    split Bregman *to its fixed point*, warm-started from the previous one; the first
    stage whose fixed point has ``||r|| <= tau delta`` is the answer. ``mu_0`` starts
    with strong TV: ``mu_start_rel / (sigma ||J(theta0)||_F)`` with
    ``sigma = delta / sqrt(m)`` (Hutchinson estimate of ``||J||_F``): at the optimum
    ``mu J^T r`` balances a TV subgradient of size one and ``||J^T noise|| ~ sigma
    ||J||_F``, so this is the scale of the answer, from the strong side. It is raised to
    the *critical* weight ``1 / ||w||_*`` (``D^T w = J^T r(theta0)``, minimum-norm ``w``
    by CGLS on ``D``, ``||.||_*`` the dual norm of TV) below which TV keeps the field
    constant (the TV analogue of the Lasso's ``lambda_max``). Should the first stage
    already satisfy the discrepancy, the search walks the other way (``mu / growth``)
    and returns the strongest TV that still satisfies it, so a badly scaled ``mu_0``
    costs stages, not the answer.
  - Why stages rather than stopping split Bregman by the discrepancy rule: its first
    iterates (``d = b = 0``) solve a *quadratic* (H1-type) problem that fits the data to
    the noise level before any shrinkage has acted, so such a stop returns a smooth,
    not a piecewise-constant, field. The discrepancy principle only ever judges
    converged minimisers of ``Phi_mu``: it selects ``mu``. A stage that is clearly above
    the level ends early: when its misfit exceeds ``tau delta`` by more than ten times
    its change over the last 10 iterations, its fixed point cannot reach the level at
    the current rate of convergence (a looser rule, "twice the level and changing
    < 1% per iteration", skipped a stage whose fixed point was below it).
  - ``tau = 1`` (Morozov), not Gauss-Newton's 1.5: here the discrepancy selects a
    regularisation weight; it does not stop a semi-convergent iteration.
  - ``beta`` starts at ``beta_rel mu ||J||_2^2 / ||D||_2^2`` (comparable curvature of the
    two quadratic terms of the inner problem) and is adapted every second iteration,
    keeping the TV subgradient ``beta b``: to a Barzilai-Borwein estimate of the data
    term's curvature along ``D`` when that estimate is reliable (the data half of the
    spectral penalty of adaptive ADMM, Xu, Figueiredo and Goldstein, AISTATS 2017; at
    most a factor 10 per update), otherwise by residual balancing (factor 2 when the
    relative primal and dual residuals differ by more than 10x; Boyd et al. 2011,
    3.4.1). No fixed rule fits: the best fixed ``beta`` is about ``2 mu`` for image
    denoising, about 50 for spring1d at ``mu = 1e4`` (where ``mu ||J||^2 / ||D||^2`` is 9e4)
    and about 10 at ``mu = 2.5e3``. Alone, residual balancing settled 10x too low on
    spring1d, the spectral estimate stalled 50x too high on one spring1d stage, and the
    full spectral rule (with the TV half, unbounded for isotropic groups near zero) went
    to ``100 mu`` in denoising; the combination converged in 97-224 outer iterations on
    all spring1d cases (dense/sparse data, noise 0, 1e-4, 1e-3) and in 75-740 on the
    denoising cross-checks.
* **Safeguards.** Every inner step is safeguarded by the inner solver (Armijo line
  search, or gain-ratio rejection), so no inner step increases the penalised
  objective; a trial point where the simulation fails counts as a failed step. An outer
  iteration whose objective is not finite or exceeds ``divergence_factor`` times the
  best of its stage, or whose inner solve found no descent although its gradient is not
  negligible, is *rejected*: ``theta``, ``d``, ``b`` (and the cached linearisation) are
  restored exactly, ``beta`` is doubled (non-convex ADMM needs ``beta`` large enough;
  a larger ``beta`` also conditions the inner problem better). ``max_rejections`` in a
  row stop the solver (``stalled``).

Other libraries' weights (checked in ``tests/solvers/test_split_bregman.py``):
``skimage.restoration.denoise_tv_bregman(f, weight=w)`` minimises this functional with
``mu = w`` (its docstring's ``weight = lambda / 2`` is off by two; the code's fidelity is
``w/2 ||u - f||^2``) and split weight ``beta = 2 w``, with ghost cells holding the noisy
image at the boundary (``offset`` and two extra residual rows reproduce them); its
*isotropic* variant is not isotropic TV (its d-step is the proximal map of a smoothed
norm). ``denoise_tv_chambolle(f, weight=w_c)`` minimises ``w_c TV + 1/2 ||u - f||^2``:
``mu = 1 / w_c`` (the two ``weight`` arguments run in opposite directions).

A stage has reached its fixed point (ADMM residuals, Boyd et al. 2011, sec. 3.3) when
the primal residual ``||D theta + c - d|| <= stage_tol max(||D theta + c||, ||d||)`` and
either the dual residual ``beta ||D^T (d - d_prev)|| <= stage_tol ||D^T beta b||`` or the
objective changed by less than ``stage_tol^2`` (relative) over the last 10 iterations.

Records (one per outer iteration; iteration 0 is ``theta0``): ``objective`` =
``Phi_mu`` of the current stage, ``misfit`` = ``||r||``, ``cg_iterations`` = CGLS
iterations of the inner solve, ``damping`` = the inner Levenberg-Marquardt damping
(``nan`` for Gauss-Newton), ``accepted`` (``False`` for a rejected iteration) and
``extra``: ``tv``, ``split_residual`` (``||d - D theta - c||``), ``dual_residual``,
``inner_iterations``, ``mu``, ``beta``, ``stage`` (and ``restored = 1`` on the record
that returns to an earlier stage).

Stop reasons: ``discrepancy`` (the selected stage satisfies it), ``tolerance`` (fixed
weight: fixed point reached), ``max_iter`` (outer iterations, stage iterations of a
fixed-weight run, or stages exhausted), ``stalled``, ``interrupted`` (a callback).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Iterable, Optional

import torch
from torch import Tensor

from ..linalg import cgls
from .gauss_newton import GaussNewtonConfig, SolverConfigError, _require, gauss_newton
from .levenberg_marquardt import LevenbergMarquardtConfig, levenberg_marquardt
from ..records import Callback, IterationRecord, SolveResult
from .base import RunClock, emit, finish
from ..residual import ResidualFunction
from .stacked import CachedResidual, LinearResidual, StackedResidual

INNER_SOLVERS = ("gauss_newton", "levenberg_marquardt")


@dataclasses.dataclass
class SplitBregmanConfig:
    """Settings of ``solver=split_bregman`` (see the module docstring for the defaults)."""

    name: str = "split_bregman"
    isotropic: bool = False         # group norm over the groups of D's rows (needs groups)
    mu: Optional[float] = None      # data weight (fixed, or first stage); None: scale-aware
    mu_rel: float = 1e6             # fixed-weight default mu = mu_rel / ||J(theta0)||_2^2
    mu_start_rel: float = 1.0       # first stage: mu_0 = mu_start_rel / (sigma ||J(theta0)||_F)
    beta: Optional[float] = None    # splitting weight at the start; None: scale-aware
    beta_rel: float = 1.0           # beta_0 = beta_rel * mu_0 * ||J||_2^2 / ||D||_2^2
    adapt_beta: bool = True         # spectral penalty update (after Xu et al. 2017) every 2 iters
    continuation: bool = True       # noise level known: discrepancy-driven stages in mu
    tau: float = 1.0                # a stage is accepted when ||r|| <= tau * delta
    growth: float = 4.0             # mu_{k+1} = growth * mu_k
    max_stages: int = 20
    max_iter: int = 2000            # outer (split Bregman) iterations over all stages
    stage_max_iter: int = 400       # outer iterations per stage
    stage_tol: float = 1e-3         # relative ADMM primal and dual residual of a fixed point
    inner_solver: str = "gauss_newton"   # gauss_newton | levenberg_marquardt
    inner_max_iter: int = 2         # inner steps per outer iteration
    cg_max_iter: int = 200          # CGLS iterations per inner step
    cg_rtol: float = 1e-3           # inner CGLS: relative normal-equation residual
    power_iterations: int = 20      # for ||J(theta0)||_2, ||J(theta0)||_F and ||D||_2
    divergence_factor: float = 10.0  # reject an outer step whose objective grows this much
    max_rejections: int = 8

    def validate(self) -> None:
        _require(self.mu is None or (self.mu > 0 and math.isfinite(self.mu)),
                 f"solver.mu must be > 0 (the weight of mu/2 ||r||^2), got {self.mu}")
        _require(self.beta is None or (self.beta > 0 and math.isfinite(self.beta)),
                 f"solver.beta must be > 0 (the split Bregman penalty), got {self.beta}")
        for key in ("mu_rel", "mu_start_rel", "beta_rel"):
            value = getattr(self, key)
            _require(value > 0 and math.isfinite(value), f"solver.{key} must be > 0, got {value}")
        _require(self.tau > 0, f"solver.tau must be > 0 (discrepancy ||r|| <= tau delta), got "
                 f"{self.tau}")
        _require(self.growth > 1, f"solver.growth must be > 1 (mu grows between stages), got "
                 f"{self.growth}")
        _require(self.max_stages >= 1, f"solver.max_stages must be >= 1, got {self.max_stages}")
        _require(self.max_iter >= 0, f"solver.max_iter must be >= 0, got {self.max_iter}")
        _require(self.stage_max_iter >= 1,
                 f"solver.stage_max_iter must be >= 1, got {self.stage_max_iter}")
        _require(0 < self.stage_tol < 1, f"solver.stage_tol must be in (0, 1), got "
                 f"{self.stage_tol}")
        _require(self.inner_solver in INNER_SOLVERS,
                 f"solver.inner_solver={self.inner_solver!r}; choose one of {INNER_SOLVERS}")
        _require(self.inner_max_iter >= 1,
                 f"solver.inner_max_iter must be >= 1, got {self.inner_max_iter}")
        _require(self.cg_max_iter >= 1, f"solver.cg_max_iter must be >= 1, got {self.cg_max_iter}")
        _require(0 < self.cg_rtol < 1, f"solver.cg_rtol must be in (0, 1), got {self.cg_rtol}")
        _require(self.power_iterations >= 1,
                 f"solver.power_iterations must be >= 1, got {self.power_iterations}")
        _require(self.divergence_factor > 1,
                 f"solver.divergence_factor must be > 1, got {self.divergence_factor}")
        _require(self.max_rejections >= 0,
                 f"solver.max_rejections must be >= 0, got {self.max_rejections}")


# -- the difference operator ---------------------------------------------------------------
def check_difference_operator(D: Tensor | None, n_params: int, groups: Tensor | None = None,
                              offset: Tensor | None = None, dtype: torch.dtype | None = None,
                              device: torch.device | str | None = None
                              ) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Validate ``D`` (and ``groups``, ``offset``) for ``n_params`` parameters.

    Returns ``(D, groups, offset)`` with ``D`` a coalesced sparse COO tensor of the given
    dtype/device, ``groups`` a LongTensor ``(n_edges,)`` or ``None``. Raises
    :class:`SolverConfigError` naming the argument at fault.
    """
    if D is None:
        raise SolverConfigError("D (the difference operator) is missing: split Bregman needs the "
                                "parameterisation's difference_operator()")
    if not isinstance(D, Tensor) or D.dim() != 2:
        raise SolverConfigError(f"D (the difference operator) must be a 2-D (sparse) tensor, got "
                                f"{type(D).__name__} of shape {tuple(getattr(D, 'shape', ()))}")
    if D.shape[1] != n_params:
        raise SolverConfigError(f"D (the difference operator) has {D.shape[1]} columns but theta "
                                f"has {n_params} parameters")
    if D.shape[0] == 0:
        raise SolverConfigError("D (the difference operator) is empty: no two parameters are "
                                "neighbours (a single cell?), so TV is zero and split Bregman "
                                "has nothing to regularise")
    if D.layout == torch.strided:
        D = D.to_sparse()
    elif D.layout != torch.sparse_coo:
        D = D.to_sparse_coo()
    D = D.coalesce()
    if dtype is not None or device is not None:
        D = D.to(dtype=dtype or D.dtype, device=device or D.device)
    values = D.values()
    if values.numel() == 0 or not bool((values != 0).any()):
        raise SolverConfigError("D (the difference operator) has no non-zero entry")
    if not bool(torch.isfinite(values).all()):
        raise SolverConfigError("D (the difference operator) contains NaN or infinite values")
    n_edges = D.shape[0]
    if groups is not None:
        groups = torch.as_tensor(groups).to(device=D.device)
        if groups.dtype in (torch.float16, torch.float32, torch.float64) or groups.dim() != 1 \
                or groups.numel() != n_edges:
            raise SolverConfigError(f"groups must be an integer vector with one group index per "
                                    f"row of D ({n_edges}), got shape {tuple(groups.shape)}")
        groups = groups.long()
        if bool((groups < 0).any()):
            raise SolverConfigError("groups must be >= 0 (row -> group index)")
    if offset is not None:
        offset = torch.as_tensor(offset).to(dtype=D.dtype, device=D.device)
        if offset.shape != (n_edges,):
            raise SolverConfigError(f"offset must have shape ({n_edges},) (one per row of D), got "
                                    f"{tuple(offset.shape)}")
        if not bool(torch.isfinite(offset).all()):
            raise SolverConfigError("offset contains NaN or infinite values")
    return D, groups, offset


class GroupTV:
    """``TV(t) = sum_g ||t_g||_2`` over groups of the rows of ``t = D theta + c``.

    Args:
        groups: ``(n_rows,)`` group index per row, or ``None`` (every row its own group:
            anisotropic TV, ``sum |t_i|``).
        n_rows: number of rows of ``D``.

    The split Bregman d-step is :meth:`shrink`, the proximal map of ``threshold * TV``
    (group soft thresholding); :meth:`dual_norm` is the norm dual to ``TV`` (max-abs, or
    the largest group norm). A subclass may replace the penalty by another function of
    the group norms by overriding :meth:`value` and :meth:`shrink` consistently (the
    skimage cross-check does, for the smoothed norm of skimage's isotropic variant).
    """

    def __init__(self, groups: Tensor | None, n_rows: int) -> None:
        if groups is None:
            self.groups = None
            self.n_groups = int(n_rows)
        else:
            _, self.groups = torch.unique(groups, return_inverse=True)
            self.n_groups = int(self.groups.max()) + 1

    def group_norms(self, t: Tensor) -> Tensor:
        """``(n_groups,)`` Euclidean norm of every group of ``t``."""
        if self.groups is None:
            return t.abs()
        sq = t.new_zeros(self.n_groups).index_add_(0, self.groups.to(t.device), t * t)
        return torch.sqrt(sq)

    def value(self, t: Tensor) -> float:
        return float(self.group_norms(t).sum())

    def dual_norm(self, w: Tensor) -> float:
        return float(self.group_norms(w).max())

    def shrink(self, t: Tensor, threshold: float) -> Tensor:
        """``argmin_d threshold * TV(d) + 1/2 ||d - t||^2``."""
        if self.groups is None:
            return torch.sign(t) * torch.clamp(t.abs() - threshold, min=0.0)
        norms = self.group_norms(t)
        factor = torch.clamp(norms - threshold, min=0.0) / torch.where(norms > 0, norms, 1.0)
        return t * factor[self.groups.to(t.device)]


def _power_norm_sq(matvec, rmatvec, v0: Tensor, iterations: int) -> float:
    """Largest eigenvalue of ``A^T A`` by power iteration (products only)."""
    v = v0 / torch.linalg.vector_norm(v0)
    estimate = 0.0
    for _ in range(iterations):
        w = rmatvec(matvec(v))
        norm = float(torch.linalg.vector_norm(w))
        if not math.isfinite(norm) or norm == 0.0:
            return estimate
        estimate = norm
        v = w / norm
    return estimate


def _spectral_beta(beta: float, dH: Tensor, dlam_hat: Tensor, correlation: float = 0.2,
                   max_factor: float = 10.0) -> float | None:
    """Spectral (Barzilai-Borwein) penalty from the data side of adaptive ADMM.

    Xu, Figueiredo and Goldstein (AISTATS 2017, eqs. 23-26) estimate the curvature of
    the theta-subproblem along ``D`` from the change of ``D theta`` (``dH``) and of the
    intermediate multiplier (``dlam_hat``, sign-adjusted so that their inner product is
    positive for a convex data term), with the hybrid steepest-descent/minimum-gradient
    rule, and trust it when the two changes are correlated (> ``correlation``). The paper
    takes the geometric mean with the same estimate for the TV side; that one is left
    out here: TV is piecewise linear (anisotropic: curvature 0 or infinite), and for
    isotropic groups near zero it is unbounded; in tests it drove beta to ~100 mu for
    denoising (best: ~2 mu), where split Bregman crawls. One update changes beta by at most
    ``max_factor``; ``None`` when the estimate is not reliable.
    """
    xy = float(torch.dot(dH, dlam_hat))
    xx = float(torch.dot(dH, dH))
    yy = float(torch.dot(dlam_hat, dlam_hat))
    if xy <= 0 or xx == 0 or yy == 0 or xy / math.sqrt(xx * yy) <= correlation:
        return None
    steepest = yy / xy
    minimum_gradient = xy / xx
    new = minimum_gradient if 2 * minimum_gradient > steepest \
        else steepest - minimum_gradient / 2
    return float(min(max(new, beta / max_factor), beta * max_factor))


def _frobenius_norm_sq(matvec, n: int, like: Tensor, probes: int) -> float:
    """Hutchinson estimate of ``||A||_F^2 = E ||A v||^2`` (Rademacher ``v``, seeded)."""
    generator = torch.Generator().manual_seed(0)
    total = 0.0
    for _ in range(probes):
        v = (torch.randint(0, 2, (n,), generator=generator) * 2 - 1).to(like)
        total += float(torch.linalg.vector_norm(matvec(v))) ** 2
    return total / probes


def _critical_mu(diff: LinearResidual, tv: GroupTV, gradient: Tensor) -> float | None:
    """Weight below which TV keeps the field constant: ``1 / ||w||_*``, ``D^T w = J^T r``.

    ``w`` is the minimum-norm least-squares solution (CGLS on ``D^T`` from zero); the
    component of the gradient along the null space of ``D`` (the mean level) is not
    regularised by TV and drops out. Returns ``None`` when the gradient has no part TV
    acts on.
    """
    n_edges = diff.size
    result = cgls(diff.rmatvec, diff.matvec, gradient, n_edges, residual_target=0.0,
                  max_iter=max(50, min(10 * n_edges, 5000)), normal_rtol=1e-8)
    dual = tv.dual_norm(result.x)
    if not (dual > 0 and math.isfinite(dual)):
        return None
    return 1.0 / dual


@dataclasses.dataclass
class _State:
    """Everything an outer iteration changes (restored exactly by a rejection)."""

    theta: Tensor
    lin: object            # the model's linearisation at theta (kept alive: no refactorisation)
    Dtheta: Tensor         # D theta + c
    d: Tensor
    b: Tensor
    mu: float
    beta: float
    stage: int


def split_bregman(residual: ResidualFunction, theta0: Tensor,
                  config: SplitBregmanConfig | None = None, callbacks: Iterable[Callback] = (),
                  *, D: Tensor | None = None, groups: Tensor | None = None,
                  offset: Tensor | None = None, penalty: GroupTV | None = None) -> SolveResult:
    """Minimise ``TV(theta) + mu/2 ||r(theta)||^2`` by split Bregman (see the module docstring).

    Args:
        residual: the model residual with its products (any problem).
        theta0: ``(n,)`` initial parameters.
        config: :class:`SplitBregmanConfig`.
        callbacks: called with an :class:`IterationRecord` per outer iteration.
        D: ``(n_edges, n)`` sparse difference operator from the parameterisation
            (keyword, required; ``parameterization.difference_operator()``).
        groups: ``(n_edges,)`` group index of every row of ``D`` (used when
            ``config.isotropic``); ``None``: every row its own group (anisotropic).
        offset: ``(n_edges,)`` constant ``c`` in ``TV = sum |D theta + c|`` (default 0).
        penalty: a :class:`GroupTV` (or subclass) to use instead of the one built from
            ``config.isotropic`` and ``groups``.
    Returns:
        :class:`SolveResult`; its records carry ``tv``, ``split_residual``,
        ``dual_residual``, ``inner_iterations``, ``mu``, ``beta`` and ``stage``.
    """
    if isinstance(config, Tensor):
        raise TypeError("split_bregman takes the difference operator as a keyword (the call of "
                        "every solver is solve(residual, theta0, config, callbacks)): "
                        "split_bregman(residual, theta0, config, callbacks, D=D)")
    cfg = config if config is not None else SplitBregmanConfig()
    cfg.validate()
    theta = theta0.detach().clone()
    n = theta.numel()
    D, groups, offset = check_difference_operator(D, n, groups, offset, theta.dtype, theta.device)
    tv = penalty if penalty is not None else GroupTV(groups if cfg.isotropic else None,
                                                     D.shape[0])
    c = offset if offset is not None else theta.new_zeros(D.shape[0])
    callbacks = list(callbacks)
    clock = RunClock()
    model = CachedResidual(residual)
    diff = LinearResidual(D)
    lin = model.linearize(theta)
    if not math.isfinite(lin.norm):
        raise ValueError("the residual at theta0 is not finite")
    noise = residual.noise_level
    staged = bool(cfg.continuation and noise is not None and noise > 0)

    # -- scale-aware weights: Jacobian products at theta0 only, no factorisation -------------
    cache: dict[str, float] = {}

    def gradient0() -> Tensor:
        if "g" not in cache:
            cache["g"] = lin.vjp(lin.r)       # type: ignore[assignment]
        return cache["g"]                    # type: ignore[return-value]

    def j_norm_sq() -> float:
        if "j2" not in cache:
            g = gradient0()
            start = g if float(torch.linalg.vector_norm(g)) > 0 else torch.ones_like(theta)
            cache["j2"] = _power_norm_sq(lin.jvp, lin.vjp, start, cfg.power_iterations)
            if not cache["j2"] > 0:
                raise ValueError("the Jacobian at theta0 is zero (the data do not depend on "
                                 "theta): no scale-aware weight exists; set solver.mu and "
                                 "solver.beta")
        return cache["j2"]

    if cfg.mu is not None:
        mu = float(cfg.mu)
    elif staged:
        assert noise is not None
        sigma = noise / math.sqrt(max(lin.r.numel(), 1))
        j_frob = math.sqrt(_frobenius_norm_sq(lin.jvp, n, theta, cfg.power_iterations))
        if not j_frob > 0:
            j_norm_sq()   # raises the message above
        mu = cfg.mu_start_rel / (sigma * j_frob)
        critical = _critical_mu(diff, tv, gradient0())
        if critical is not None:
            mu = max(mu, critical)   # weaker than critical: the field would stay constant
    else:
        mu = cfg.mu_rel / j_norm_sq()
    if cfg.beta is not None:
        beta = float(cfg.beta)
    else:
        d_norm_sq = _power_norm_sq(diff.matvec, diff.rmatvec,
                                   torch.cos(torch.arange(n, dtype=theta.dtype,
                                                          device=theta.device)) + 2.0,
                                   cfg.power_iterations)
        beta = cfg.beta_rel * mu * j_norm_sq() / max(d_norm_sq, 1e-300)

    Dtheta = diff.matvec(theta) + c
    state = _State(theta, lin, Dtheta, Dtheta.clone(), torch.zeros_like(Dtheta), mu, beta, 0)
    history: list[IterationRecord] = []
    counter = {"iteration": 0}

    def objective(s: _State) -> tuple[float, float]:
        tv_value = tv.value(s.Dtheta)
        return tv_value + 0.5 * s.mu * s.lin.norm ** 2, tv_value   # type: ignore[attr-defined]

    def record(s: _State, step_norm: float, cg_its: int, damping: float, accepted: bool,
               **extra: float) -> bool:
        factorizations, solves = clock.counts()
        obj, tv_value = objective(s)
        rec = IterationRecord(counter["iteration"], s.theta, obj, s.lin.norm,  # type: ignore
                              step_norm, cg_its, damping, accepted, clock.elapsed(),
                              factorizations, solves,
                              {"tv": tv_value,
                               "split_residual": float(torch.linalg.vector_norm(s.Dtheta - s.d)),
                               "mu": s.mu, "beta": s.beta, "stage": float(s.stage), **extra})
        history.append(rec)
        return emit(callbacks, rec)

    if record(state, 0.0, 0, math.nan, True, dual_residual=math.nan, inner_iterations=0):
        return finish(state.theta, False, "interrupted", history, clock)

    inner_solve = gauss_newton if cfg.inner_solver == "gauss_newton" else levenberg_marquardt
    # The inner problem has a non-zero minimum: its CGLS stops on the normal-equation
    # residual (REGINN's ||J d + r|| <= eta ||r|| could never be met there).
    inner_cfg = (GaussNewtonConfig(max_iter=cfg.inner_max_iter, cg_max_iter=cfg.cg_max_iter,
                                   eta_min=1e-14, eta_max=1e-14, cg_rtol=cfg.cg_rtol)
                 if cfg.inner_solver == "gauss_newton" else
                 LevenbergMarquardtConfig(max_iter=cfg.inner_max_iter, cg_max_iter=cfg.cg_max_iter,
                                          cg_rtol=cfg.cg_rtol))

    def run_stage(s: _State) -> tuple[_State, str]:
        """Split Bregman at fixed ``mu`` until its fixed point.

        Returns the new state and ``'converged'``, ``'above'`` (clearly above the
        discrepancy level and no longer moving: the next stage will tell), ``'budget'``
        (stage_max_iter), ``'max_iter'``, ``'stalled'`` or ``'interrupted'``.
        """
        best = objective(s)[0]
        spectral = None
        objectives: list[float] = []
        rejections = 0
        misfits: list[float] = []
        for k in range(cfg.stage_max_iter):
            if counter["iteration"] >= cfg.max_iter:
                return s, "max_iter"
            counter["iteration"] += 1
            diff.target = s.d - s.b - c
            stacked = StackedResidual([model, diff], [s.mu, s.beta], projector_from=0)
            inner = inner_solve(stacked, s.theta, inner_cfg)
            cg_its = sum(r.cg_iterations for r in inner.history[1:])
            damping = (inner.history[-1].damping if cfg.inner_solver != "gauss_newton"
                       else math.nan)
            new_lin = (s.lin if torch.equal(inner.theta, s.theta)
                       else model.linearize(inner.theta))   # cached: the inner end point
            new_Dtheta = diff.matvec(inner.theta) + c
            new_obj = tv.value(new_Dtheta) + 0.5 * s.mu * new_lin.norm ** 2
            # An inner solve whose line search found no descent although the inner
            # gradient is not negligible (against the TV force ||D^T beta b||): the
            # Gauss-Newton model is bad there (non-linearity, a poorly conditioned
            # splitting). At the fixed point itself the gradient is ~0 and this is no
            # failure.
            stuck = inner.iterations == 0 and inner.stop_reason == "line_search" and \
                inner.history[0].extra.get("gradient_norm", math.inf) > cfg.stage_tol * max(
                    s.beta * float(torch.linalg.vector_norm(diff.rmatvec(s.b))), 1e-300)
            if stuck or not math.isfinite(new_obj) or new_obj > cfg.divergence_factor * best:
                # Safeguard (a diverging outer step, or an inner solve that found no
                # descent): keep theta, d, b exactly; stiffen the splitting (keep beta * b),
                # which makes the inner problem better conditioned.
                rejections += 1
                model.restore(s.lin)
                s = dataclasses.replace(s, beta=2.0 * s.beta, b=s.b / 2.0)
                spectral = None
                if record(s, 0.0, cg_its, damping, False, dual_residual=math.nan,
                          inner_iterations=inner.iterations):
                    return s, "interrupted"
                if rejections > cfg.max_rejections:
                    return s, "stalled"
                continue
            rejections = 0
            step_norm = float(torch.linalg.vector_norm(inner.theta - s.theta))
            lam_hat = s.beta * (s.b + new_Dtheta - s.d)    # intermediate multiplier
            d = tv.shrink(new_Dtheta + s.b, 1.0 / s.beta)      # shrinkage
            b = s.b + new_Dtheta - d                            # Bregman update
            dual = s.beta * float(torch.linalg.vector_norm(diff.rmatvec(d - s.d)))
            s = dataclasses.replace(s, theta=inner.theta, lin=new_lin, Dtheta=new_Dtheta, d=d, b=b)
            best = min(best, new_obj)
            primal = float(torch.linalg.vector_norm(new_Dtheta - d))
            primal_rel = primal / max(float(torch.linalg.vector_norm(new_Dtheta)),
                                      float(torch.linalg.vector_norm(d)), 1e-300)
            dual_rel = dual / max(s.beta * float(torch.linalg.vector_norm(diff.rmatvec(b))),
                                  1e-300)
            if record(s, step_norm, cg_its, damping, True, dual_residual=dual,
                      inner_iterations=inner.iterations):
                return s, "interrupted"
            objectives.append(new_obj)
            stagnant = len(objectives) > 10 and \
                abs(objectives[-11] - new_obj) <= cfg.stage_tol ** 2 * abs(new_obj)
            if primal_rel <= cfg.stage_tol and (dual_rel <= cfg.stage_tol or stagnant):
                return s, "converged"
            if primal == 0.0 and step_norm == 0.0:
                return s, "converged"           # nothing moves (e.g. a constant field)
            misfits.append(s.lin.norm)           # type: ignore[attr-defined]
            if staged and len(misfits) > 10 and misfits[-1] - cfg.tau * noise > \
                    10.0 * abs(misfits[-1] - misfits[-11]):
                return s, "above"
            if cfg.adapt_beta and (spectral is None or k % 2 == 1):
                beta_new = None
                if spectral is not None:
                    beta_new = _spectral_beta(s.beta, new_Dtheta - spectral[0],
                                              -(lam_hat - spectral[1]))
                    if beta_new is None and max(primal_rel, dual_rel) > 10.0 * min(
                            primal_rel, dual_rel):
                        # No reliable curvature: residual balancing (Boyd et al. 2011,
                        # 3.4.1, on relative residuals as Wohlberg 2017).
                        beta_new = s.beta * (2.0 if primal_rel > dual_rel else 0.5)
                if beta_new is not None and beta_new != s.beta:
                    s = dataclasses.replace(s, beta=beta_new, b=s.b * (s.beta / beta_new))
                spectral = (new_Dtheta, lam_hat)
        return s, "budget"

    if not staged:
        state, status = run_stage(state)
        if status == "converged":
            return finish(state.theta, True, "tolerance", history, clock)
        reason = {"budget": "max_iter"}.get(status, status)
        return finish(state.theta, False, reason, history, clock)

    assert noise is not None
    level = cfg.tau * noise
    direction: str | None = None
    accepted: _State | None = None     # strongest-TV stage meeting the discrepancy (downwards)
    for _ in range(cfg.max_stages):
        state, status = run_stage(state)
        if status in ("interrupted", "stalled", "max_iter"):
            return finish(state.theta, False, status, history, clock)
        ok = state.lin.norm <= level         # type: ignore[attr-defined]
        if direction is None:
            direction = "weaker" if not ok else "stronger"
        if direction == "weaker":
            if ok:
                return finish(state.theta, True, "discrepancy", history, clock)
            mu_next = state.mu * cfg.growth
        else:
            if not ok:
                break
            accepted = state
            mu_next = state.mu / cfg.growth
        if state.stage + 1 >= cfg.max_stages:
            break
        state = dataclasses.replace(state, mu=mu_next, stage=state.stage + 1)
    if direction == "stronger" and accepted is not None:
        if accepted is not state:
            # The last stage fitted the data worse than the noise: go back to the one before.
            counter["iteration"] += 1
            step_norm = float(torch.linalg.vector_norm(accepted.theta - state.theta))
            model.restore(accepted.lin)
            state = accepted
            if record(state, step_norm, 0, math.nan, True, dual_residual=math.nan,
                      inner_iterations=0, restored=1.0):
                return finish(state.theta, False, "interrupted", history, clock)
        return finish(state.theta, True, "discrepancy", history, clock)
    return finish(state.theta, False, "max_iter", history, clock)


#: experiments/fit.py hands this solver the parameterisation's ``D`` (and TV groups).
split_bregman.needs_difference_operator = True  # type: ignore[attr-defined]

__all__ = ["GroupTV", "SplitBregmanConfig", "check_difference_operator", "split_bregman"]
