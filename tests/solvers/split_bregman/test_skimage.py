"""Split Bregman TV cross-checked with scikit-image's denoisers.

The denoising cross-checks map torchfit's functional onto scikit-image's exactly:

* ``skimage.restoration.denoise_tv_bregman(f, weight=w)`` runs split Bregman on a
  padded image whose ghost cells hold the *noisy* data and never change: the right
  column / bottom row ghosts are ``f[:, -1]`` / ``f[-1, :]``, the left column / top row
  ghosts are ``f[:, 1]`` / ``f[1, :]``; its splitting weight is ``lambda = 2 w`` and the
  left/top ghost differences have no ``d``/``b`` (they stay in the quadratic term). Its
  Gauss-Seidel sweep is the optimality condition of (read from ``_denoise_cy.pyx`` of
  scikit-image 0.26, reproduced bit for bit by a Python transcription)::

      E(u) = sum_cells TV_cell(u_x, u_y) + w/2 ||u - f||^2
             + w ||u[:, 0] - f[:, 1]||^2 + w ||u[0, :] - f[1, :]||^2

  with forward differences ``u_x = u[r, c+1] - u[r, c]`` (at the last column
  ``f[r, -1] - u[r, -1]``), likewise ``u_y``. So **torchfit's ``mu`` equals skimage's
  ``weight``** (skimage's docstring says ``weight = lambda/2`` for a fidelity
  ``lambda/2 ||f - u||^2``; its code has ``w/2 ||f - u||^2``), ``D`` holds the interior and
  ghost differences with the ghost values as ``offset``, and the left/top terms are two
  more rows ``sqrt(2) (u - f_ghost)`` of the (linear) residual.
* Anisotropic ``TV_cell = |u_x| + |u_y|``: the same functional, same minimiser.
* Isotropic: skimage's d-step is ``d = t s lambda / (s lambda + 1)`` (``s = |t|``), not the
  isotropic shrinkage ``t max(s - 1/lambda, 0) / s``. It is the proximal map of a smoothed
  norm ``phi_lambda`` with ``phi'(rho) = (sqrt(lambda^2 rho^2 + 4 lambda rho) - lambda rho) / 2``,
  so ``denoise_tv_bregman(isotropic=True)`` minimises ``sum phi_{2w}(|grad u|) + ...``, not
  isotropic TV (its result is ~5% above the isotropic-TV minimum at ``w = 10``). The test
  gives torchfit's split Bregman skimage's d-step (a :class:`GroupTV` subclass) and checks
  both reach the same minimiser of that functional; torchfit's exact isotropic TV is
  checked against ``denoise_tv_chambolle`` (Chambolle's projection algorithm, exact
  isotropic ROF with Neumann forward differences) instead.
* Weight conventions: Chambolle's ``weight`` multiplies TV (``weight TV + 1/2 ||u - f||^2``),
  the Bregman ``weight`` multiplies the fidelity: ``mu = weight_bregman = 1 / weight_chambolle``
  (they run in opposite directions: more denoising is a larger Chambolle weight and a
  smaller Bregman weight).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchfit.params import per_grid_cell
from torchfit.solvers import GroupTV, ResidualFunction, SplitBregmanConfig, split_bregman





@pytest.fixture
def skimage_restoration():
    return pytest.importorskip("skimage.restoration")


def noisy_image(shape=(32, 28), sigma=0.1, seed=0):
    rows, cols = shape
    u = np.zeros(shape)
    u[5:20, 4:14] = 1.0
    u[14:28, 17:25] = 0.5
    u[23:30, 3:10] = -0.5
    return u + sigma * np.random.default_rng(seed).standard_normal(shape)


def skimage_bregman_problem(f: np.ndarray):
    """torchfit's residual, D, offset and groups for skimage's denoise_tv_bregman functional."""
    rows, cols = f.shape
    index = np.arange(rows * cols).reshape(rows, cols)
    r_idx, c_idx, values, offset = [], [], [], []
    row = 0
    for axis in (1, 0):                                  # x (along a row), then y
        for r in range(rows):
            for c in range(cols):
                last = c == cols - 1 if axis == 1 else r == rows - 1
                if last:                                  # difference to the fixed ghost
                    r_idx += [row]
                    c_idx += [index[r, c]]
                    values += [-1.0]
                    offset.append(f[r, cols - 1] if axis == 1 else f[rows - 1, c])
                else:
                    nxt = index[r, c + 1] if axis == 1 else index[r + 1, c]
                    r_idx += [row, row]
                    c_idx += [nxt, index[r, c]]
                    values += [1.0, -1.0]
                    offset.append(0.0)
                row += 1
    D = torch.sparse_coo_tensor(torch.tensor([r_idx, c_idx]), torch.tensor(values),
                                (row, rows * cols), check_invariants=False).coalesce()
    groups = torch.as_tensor(np.concatenate([index.reshape(-1), index.reshape(-1)]))
    left, top = torch.as_tensor(index[:, 0]), torch.as_tensor(index[0, :])
    s2 = math.sqrt(2.0)
    data = torch.cat([torch.as_tensor(f.reshape(-1)), s2 * torch.as_tensor(f[:, 1]),
                      s2 * torch.as_tensor(f[1, :])])

    def forward(theta):
        return torch.cat([theta, s2 * theta[left], s2 * theta[top]])

    return ResidualFunction(forward, data), D, torch.tensor(offset), groups


def bregman_gradient(u: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ext = np.zeros((u.shape[0] + 1, u.shape[1] + 1))
    ext[:-1, :-1] = u
    ext[:-1, -1] = f[:, -1]
    ext[-1, :-1] = f[-1, :]
    return ext[:-1, 1:] - u, ext[1:, :-1] - u


def bregman_functional(u, f, w, cell_penalty) -> float:
    ux, uy = bregman_gradient(u, f)
    fidelity = 0.5 * w * ((u - f) ** 2).sum() + w * ((u[:, 0] - f[:, 1]) ** 2).sum() \
        + w * ((u[0, :] - f[1, :]) ** 2).sum()
    return float(cell_penalty(ux, uy).sum() + fidelity)


def anisotropic(ux, uy):
    return np.abs(ux) + np.abs(uy)


def isotropic(ux, uy):
    return np.sqrt(ux ** 2 + uy ** 2)


def smoothed_norm(lam: float):
    """``phi_lam(rho) = F(lam rho) / lam``, ``F(x) = int_0^x (sqrt(y^2 + 4y) - y) / 2 dy``:
    the function whose proximal map is skimage's isotropic d-step."""
    def F(x):
        z = x + 2.0
        root = np.sqrt(np.maximum(z * z - 4.0, 0.0))
        return 0.5 * (0.5 * z * root - 2.0 * np.log(z + root) + 2.0 * np.log(2.0) - 0.5 * x * x)

    return lambda rho: F(lam * np.asarray(rho)) / lam


class SkimageIsotropicStep(GroupTV):
    """skimage's isotropic d-step ``d = t s / (s + 1/lam)`` and the penalty it minimises."""

    def __init__(self, groups, n_rows, lam):
        super().__init__(groups, n_rows)
        self.lam = lam
        self.phi = smoothed_norm(lam)

    def shrink(self, t, threshold):
        assert threshold == pytest.approx(1.0 / self.lam)   # beta is skimage's lambda
        norms = self.group_norms(t)
        return t * (norms / (norms + threshold))[self.groups]

    def value(self, t):
        return float(self.phi(self.group_norms(t).numpy()).sum())


def run_torchfit_bregman(f, w, config, penalty=None, isotropic_tv=False):
    residual, D, offset, groups = skimage_bregman_problem(f)
    theta0 = torch.as_tensor(f.reshape(-1)).clone()
    if penalty is not None:
        penalty = penalty(groups, D.shape[0])
    result = split_bregman(residual, theta0, config, D=D, groups=groups, offset=offset,
                           penalty=penalty)
    return result, result.theta.numpy().reshape(f.shape)


def test_anisotropic_matches_skimage_denoise_tv_bregman(skimage_restoration):
    f, w = noisy_image(), 10.0
    sk = skimage_restoration.denoise_tv_bregman(f, weight=w, max_num_iter=20000, eps=1e-13,
                                                isotropic=False)
    result, u = run_torchfit_bregman(f, w, SplitBregmanConfig(mu=w, stage_tol=1e-5,
                                                              max_iter=600, stage_max_iter=600))
    e_tf = bregman_functional(u, f, w, anisotropic)
    e_sk = bregman_functional(sk, f, w, anisotropic)
    print(f"\nanisotropic: E torchfit {e_tf:.10f}, E skimage {e_sk:.10f}, relative "
          f"{(e_tf - e_sk) / e_sk:.2e}, max |u - u_sk| {np.abs(u - sk).max():.2e}, "
          f"{result.iterations} iterations")
    assert result.stop_reason == "tolerance"
    assert result.history[-1].objective == pytest.approx(e_tf, rel=1e-12)  # same functional
    assert abs(e_tf - e_sk) <= 1e-3 * e_sk
    assert np.abs(u - sk).max() <= 1e-3


def test_isotropic_matches_skimage_denoise_tv_bregman_given_its_d_step(skimage_restoration):
    f, w = noisy_image(), 10.0
    lam = 2.0 * w
    sk = skimage_restoration.denoise_tv_bregman(f, weight=w, max_num_iter=20000, eps=1e-13,
                                                isotropic=True)
    config = SplitBregmanConfig(mu=w, beta=lam, adapt_beta=False, stage_tol=1e-5,
                                max_iter=600, stage_max_iter=600)
    result, u = run_torchfit_bregman(
        f, w, config, penalty=lambda g, n: SkimageIsotropicStep(g, n, lam))
    phi = smoothed_norm(lam)
    smoothed = lambda ux, uy: phi(np.sqrt(ux ** 2 + uy ** 2))  # noqa: E731
    e_tf = bregman_functional(u, f, w, smoothed)
    e_sk = bregman_functional(sk, f, w, smoothed)
    print(f"\nisotropic (skimage's d-step): E_phi torchfit {e_tf:.10f}, skimage {e_sk:.10f}, "
          f"relative {(e_tf - e_sk) / e_sk:.2e}, max |u - u_sk| {np.abs(u - sk).max():.2e}, "
          f"{result.iterations} iterations")
    assert result.history[-1].objective == pytest.approx(e_tf, rel=1e-10)
    assert abs(e_tf - e_sk) <= 1e-3 * e_sk
    assert np.abs(u - sk).max() <= 1e-3

    # ... and that functional is not isotropic TV: the exact isotropic minimiser is lower.
    exact, u_iso = run_torchfit_bregman(f, w, SplitBregmanConfig(mu=w, isotropic=True,
                                                                 stage_tol=1e-4, max_iter=600))
    e_iso_tf = bregman_functional(u_iso, f, w, isotropic)
    e_iso_sk = bregman_functional(sk, f, w, isotropic)
    print(f"isotropic TV: E torchfit {e_iso_tf:.6f}, E at skimage's isotropic result "
          f"{e_iso_sk:.6f} (+{(e_iso_sk - e_iso_tf) / e_iso_tf:.1%})")
    assert e_iso_sk > 1.01 * e_iso_tf


def test_isotropic_matches_skimage_denoise_tv_chambolle(skimage_restoration):
    f = noisy_image()
    weight = 0.1                                     # Chambolle: weight * TV + 1/2 ||u - f||^2
    mu = 1.0 / weight
    sk = skimage_restoration.denoise_tv_chambolle(f, weight=weight, eps=1e-12,
                                                  max_num_iter=20000)
    param = per_grid_cell(f.shape, transform="identity")
    data = torch.as_tensor(f.reshape(-1))
    result = split_bregman(ResidualFunction(lambda theta: theta, data), data.clone(),
                           SplitBregmanConfig(mu=mu, isotropic=True, stage_tol=1e-5,
                                              max_iter=800, stage_max_iter=800),
                           D=param.difference_operator(), groups=param.difference_groups())
    u = result.theta.numpy().reshape(f.shape)

    def energy(v):
        gx = np.zeros_like(v)
        gy = np.zeros_like(v)
        gx[:, :-1] = np.diff(v, axis=1)
        gy[:-1, :] = np.diff(v, axis=0)
        return float(np.sqrt(gx ** 2 + gy ** 2).sum() + 0.5 * mu * ((v - f) ** 2).sum())

    e_tf, e_sk = energy(u), energy(sk)
    print(f"\nisotropic vs Chambolle: E torchfit {e_tf:.10f}, E skimage {e_sk:.10f}, "
          f"relative {(e_tf - e_sk) / e_sk:.2e}, max |u - u_sk| {np.abs(u - sk).max():.2e}, "
          f"{result.iterations} iterations")
    assert result.history[-1].objective == pytest.approx(e_tf, rel=1e-12)
    assert abs(e_tf - e_sk) <= 1e-3 * e_sk
    assert np.abs(u - sk).max() <= 5e-3
