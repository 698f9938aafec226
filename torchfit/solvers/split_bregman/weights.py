"""Split Bregman's weights: the data weight ``mu`` and splitting weight ``beta`` at the
start, and how ``beta`` adapts.

Start (:func:`initial_weights`, Jacobian products at ``theta0``, no factorisation):

* ``mu`` set: that. With a noise level ``delta`` and stages (``staged``):
  ``mu_0 = mu_start_rel / (sigma ||J||_F)``, ``sigma = delta / sqrt(m)``, raised to
  :func:`critical_mu` (below it TV keeps the field constant). Otherwise
  ``mu = mu_rel / ||J||_2^2`` (``mu_rel_bregman`` in a data-Bregman run).
* ``beta`` set: that; else ``beta_0 = beta_rel mu ||J||_2^2 / ||D||_2^2``.

``||J||_2^2`` and ``||D||_2^2`` by power iteration, ``||J||_F^2`` by Hutchinson's
estimate (:mod:`torchfit.linalg.estimators`, ``power_iterations`` products each).

Adaptation (``adapt_beta``; after accepted outer iterations; the solver rescales ``b`` to
keep ``beta b``): :func:`adapted_beta` every second iteration of a stage (spectral
estimate, else residual balancing), and in a data-Bregman run :func:`admm_stalled`
(double ``beta`` when the ADMM residual has not decreased over ``stall_window``
iterations). A rejected iteration doubles ``beta`` too. Reasons and figures:
``docs/notes/split_bregman.md``.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from ...linalg import cgls, frobenius_norm_sq, power_norm_sq
from .settings import SplitBregmanConfig
from ..stacked import LinearResidual
from ..total_variation import GroupTV


class StartScales:
    """``J^T r`` and ``||J(theta0)||_2^2`` of the linearisation at ``theta0``, each made
    once, when first asked (products only)."""

    def __init__(self, lin, iterations: int) -> None:
        self.lin = lin
        self.iterations = iterations
        self._gradient: Tensor | None = None
        self._j_norm_sq: float | None = None

    def gradient(self) -> Tensor:
        if self._gradient is None:
            self._gradient = self.lin.vjp(self.lin.r)
        return self._gradient

    def jacobian_norm_sq(self) -> float:
        """``||J(theta0)||_2^2`` by power iteration from ``J^T r`` (a ``ValueError`` when
        ``J`` is zero: no scale-aware weight exists)."""
        if self._j_norm_sq is None:
            g = self.gradient()
            start = g if float(torch.linalg.vector_norm(g)) > 0 else torch.ones_like(g)
            self._j_norm_sq = power_norm_sq(self.lin.jvp, self.lin.vjp, start, self.iterations)
            if not self._j_norm_sq > 0:
                raise ValueError("the Jacobian at theta0 is zero (the data do not depend on "
                                 "theta): no scale-aware weight exists; set solver.mu and "
                                 "solver.beta")
        return self._j_norm_sq


def initial_weights(cfg: SplitBregmanConfig, lin, theta: Tensor, diff: LinearResidual,
                    tv: GroupTV, noise_level: float | None, staged: bool,
                    data_bregman: bool) -> tuple[float, float]:
    """Scale-aware ``(mu, beta)`` at ``theta0`` (see the module docstring)."""
    scales = StartScales(lin, cfg.power_iterations)
    if cfg.mu is not None:
        mu = float(cfg.mu)
    elif staged:
        assert noise_level is not None
        sigma = noise_level / math.sqrt(max(lin.r.numel(), 1))
        j_frob = math.sqrt(frobenius_norm_sq(lin.jvp, theta.numel(), theta,
                                             cfg.power_iterations))
        if not j_frob > 0:
            scales.jacobian_norm_sq()   # raises: the Jacobian is zero
        mu = cfg.mu_start_rel / (sigma * j_frob)
        critical = critical_mu(diff, tv, scales.gradient())
        if critical is not None:
            mu = max(mu, critical)   # weaker than critical: the field would stay constant
    else:
        mu = (cfg.mu_rel_bregman if data_bregman else cfg.mu_rel) / scales.jacobian_norm_sq()
    if cfg.beta is not None:
        beta = float(cfg.beta)
    else:
        d_norm_sq = power_norm_sq(diff.matvec, diff.rmatvec,
                                  torch.cos(torch.arange(theta.numel(), dtype=theta.dtype,
                                                         device=theta.device)) + 2.0,
                                  cfg.power_iterations)
        beta = cfg.beta_rel * mu * scales.jacobian_norm_sq() / max(d_norm_sq, 1e-300)
    return mu, beta


def critical_mu(diff: LinearResidual, tv: GroupTV, gradient: Tensor) -> float | None:
    """Weight below which TV keeps the field constant: ``1 / ||w||_*``, ``D^T w = J^T r``.

    ``w`` is the minimum-norm least-squares solution (CGLS on ``D^T`` from zero, to a
    relative normal residual of 1e-3: a floor needs a few digits only); the component of
    the gradient along the null space of ``D`` (the mean level) is not regularised by TV
    and drops out. ``None`` when the gradient has no part TV acts on.
    """
    n_edges = diff.size
    result = cgls(diff.rmatvec, diff.matvec, gradient, n_edges, residual_target=0.0,
                  max_iter=max(50, min(10 * n_edges, 5000)), normal_rtol=1e-3)
    dual = tv.dual_norm(result.x)
    if not (dual > 0 and math.isfinite(dual)):
        return None
    return 1.0 / dual


def spectral_beta(beta: float, dH: Tensor, dlam_hat: Tensor, correlation: float = 0.2,
                  max_factor: float = 10.0) -> float | None:
    """Spectral (Barzilai-Borwein) penalty from the data side of adaptive ADMM.

    Xu, Figueiredo and Goldstein (AISTATS 2017, eqs. 23-26): the curvature of the
    theta-subproblem along ``D`` from the change of ``D theta`` (``dH``) and of the
    intermediate multiplier (``dlam_hat``, sign-adjusted so that their inner product is
    positive for a convex data term), hybrid steepest-descent/minimum-gradient rule,
    trusted when the two changes are correlated (> ``correlation``). The TV side's
    estimate is left out (``docs/notes/split_bregman.md``). One update changes ``beta``
    by at most ``max_factor``; ``None`` when the estimate is not reliable.
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


def adapted_beta(beta: float, spectral: tuple[Tensor, Tensor] | None, Dtheta: Tensor,
                 lam_hat: Tensor, primal_rel: float, dual_rel: float) -> float | None:
    """The next ``beta`` after an accepted iteration, or ``None`` (keep it).

    ``spectral`` is the ``(D theta + c, intermediate multiplier)`` pair of the last
    update (``None``: the first of a stage, no estimate yet). The spectral estimate
    (:func:`spectral_beta`); where it is not reliable and one relative ADMM residual
    exceeds the other tenfold, residual balancing (Boyd et al. 2011, 3.4.1, on relative
    residuals as Wohlberg 2017): ``beta`` doubles or halves.
    """
    beta_new = None
    if spectral is not None:
        beta_new = spectral_beta(beta, Dtheta - spectral[0], -(lam_hat - spectral[1]))
        if beta_new is None and max(primal_rel, dual_rel) > 10.0 * min(primal_rel, dual_rel):
            beta_new = beta * (2.0 if primal_rel > dual_rel else 0.5)
    return beta_new


def admm_stalled(admm_window: list[float], window: int) -> bool:
    """The last ADMM residual of ``admm_window`` is no lower than the one ``window``
    accepted iterations before (the stall rule of a data-Bregman run: ``beta`` doubles).

    ADMM on a non-convex data term converges for a large enough penalty (Wang, Yin and
    Zeng 2019); a too small ``beta`` that neither the spectral estimate nor residual
    balancing moves lets the iteration drift (``docs/notes/split_bregman.md``)."""
    return len(admm_window) > window and admm_window[-1] >= admm_window[-1 - window]


__all__ = ["StartScales", "adapted_beta", "admm_stalled", "critical_mu", "initial_weights",
           "spectral_beta"]
