"""Isotropic hyperelastic constitutive models, parameterised by ``E`` and ``nu``.

Each model gives, for deformation gradients ``F`` ``(..., d, d)`` (d = 2 plane strain,
or 3) and Lame parameters ``mu``, ``lam`` broadcast against the batch shape:

* ``energy_density(F, mu, lam)``: ``Psi`` (zero at the rest shape);
* ``stress(F, mu, lam)``: the first Piola-Kirchhoff stress ``P = dPsi/dF``;
* ``stress_derivative(F, mu, lam)``: the exact ``A_ijkl = dP_ij / dF_kl``
  ``(..., d, d, d, d)`` (symmetric in ``(ij) <-> (kl)``);
* :func:`project_psd`: ``A`` with its negative eigenvalues (as a ``d^2 x d^2``
  matrix) clamped to zero, the positive semi-definite tangent Newton may use.

Models (``MATERIALS``):

``linear``
    ``Psi = mu eps:eps + lam/2 tr(eps)^2`` with ``eps = sym(F) - I`` (small-strain
    elasticity; linear in the positions).
``corotated``
    PhysBAM's rotated linear model: ``Psi = mu ||F - R||^2 + lam/2 (tr(R^T F) - d)^2``
    with ``R`` the rotation of the polar decomposition (:mod:`.kinematics`);
    ``P = 2 mu (F - R) + lam (tr(R^T F) - d) R``. PhysBAM's default Poisson ratio for it
    is ``nu = 0.475`` (``default_nu``). Its exact tangent includes the derivative of
    ``R`` (a ``1 / (sigma_i + sigma_j)`` term), which vanishes at the rest shape.
``stable_neo_hookean`` (alias ``neo_hookean``)
    Smith, de Goes and Kim (2018): ``Psi = mu'/2 (I_C - 3) + lam'/2 (J - alpha)^2
    - mu'/2 log(I_C + 1)`` with ``alpha = 1 + 3 mu' / (4 lam')`` and the Lame
    reparameterisation ``mu' = 4/3 mu``, ``lam' = lam + 5/6 mu`` that makes its rest
    tangent that of linear elasticity. Defined for inverted elements (``J <= 0``).

Plane strain (d = 2): the 2-D deformation is embedded as ``diag(F, 1)``, so the models
use the 3-D Lame parameters; for ``linear`` and ``corotated`` that is their 2-D formula,
for stable neo-Hookean ``I_C = ||F||^2 + 1`` and ``J = det F``.

All three are linear in ``E`` at fixed ``nu`` (``P(E) = E P(1)``), which the parameter
derivative of :mod:`.fem` exploits.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from ...errors import SimulationError
from .kinematics import polar_rotation, rotation_differential


class MaterialError(ValueError):
    """An invalid material setting (unknown model, Poisson ratio, Young's modulus)."""


class InvalidModulusError(MaterialError, SimulationError):
    """A Young's modulus that is not positive and finite (names the element).

    Also a :class:`~torchfit.errors.SimulationError`: at a solver's trial point (an
    identity parameterisation stepping below zero) it is a failed step.
    """


def check_poisson_ratio(nu: float) -> float:
    nu = float(nu)
    if not (-1.0 < nu < 0.5):
        raise MaterialError(f"Poisson ratio nu = {nu} is outside (-1, 0.5): an isotropic "
                            "material needs -1 < nu < 0.5 (0.5 is incompressible, which these "
                            "displacement elements cannot represent)")
    return nu


def lame_parameters(E: Tensor | float, nu: float) -> tuple[Tensor | float, Tensor | float]:
    """``(mu, lam)`` of Young's modulus ``E`` and Poisson ratio ``nu`` (3-D / plane strain)."""
    nu = check_poisson_ratio(nu)
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


def _eye(d: int, like: Tensor) -> Tensor:
    return torch.eye(d, dtype=like.dtype, device=like.device)


def _trace(M: Tensor) -> Tensor:
    return M.diagonal(dim1=-2, dim2=-1).sum(-1)


def _ddot(A: Tensor, B: Tensor) -> Tensor:
    return (A * B).sum(dim=(-2, -1))


def _outer(A: Tensor, B: Tensor) -> Tensor:
    """``A_ij B_kl`` ``(..., d, d, d, d)``."""
    return A[..., :, :, None, None] * B[..., None, None, :, :]


def _basis(d: int, like: Tensor) -> Tensor:
    """``(d^2, d, d)``: the matrices ``E_kl`` in the order ``k * d + l``."""
    return torch.eye(d * d, dtype=like.dtype, device=like.device).reshape(d * d, d, d)


def _identity4(d: int, like: Tensor) -> Tensor:
    """``delta_ik delta_jl`` ``(d, d, d, d)``."""
    return _basis(d, like).reshape(d, d, d, d).permute(2, 3, 0, 1).contiguous()


def _symmetrize(A: Tensor) -> Tensor:
    d = A.shape[-1]
    M = A.reshape(*A.shape[:-4], d * d, d * d)
    M = 0.5 * (M + M.transpose(-1, -2))
    return M.reshape(A.shape)


def project_psd(A: Tensor) -> Tensor:
    """``A`` ``(..., d, d, d, d)`` with negative eigenvalues (as ``d^2 x d^2``) set to 0.

    Matrices whose eigenvalues are all above ``-1e-12`` times their largest diagonal entry
    are returned unchanged (up to symmetrisation).
    """
    d = A.shape[-1]
    M = A.reshape(-1, d * d, d * d)
    M = 0.5 * (M + M.transpose(-1, -2))
    # Only matrices with a negative eigenvalue beyond round-off need the eigensolver:
    # Cholesky of M + tol I succeeds for the others (rotation-invariant energies have a
    # zero eigenvalue at rest, which must not send every element to ``eigh``).
    scale = M.diagonal(dim1=-2, dim2=-1).abs().amax(dim=-1)
    tol = 1e-12 * torch.where(scale > 0, scale, torch.ones_like(scale))
    eye = torch.eye(d * d, dtype=M.dtype, device=M.device)
    _, info = torch.linalg.cholesky_ex(M + tol[:, None, None] * eye)
    bad = torch.nonzero(info != 0).reshape(-1)
    if bad.numel() == 0:
        return A
    eigenvalues, vectors = torch.linalg.eigh(M[bad])
    projected = (vectors * eigenvalues.clamp(min=0.0)[..., None, :]) @ vectors.transpose(-1, -2)
    M = M.clone()
    M[bad] = projected
    return M.reshape(A.shape)


class Material:
    """Base class; see the module docstring for the methods."""

    name = "material"
    linear = False          # P affine in F (the equilibrium is then one linear solve)
    default_nu = 0.3

    def energy_density(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        raise NotImplementedError

    def stress(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        raise NotImplementedError

    def stress_derivative(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


class LinearElastic(Material):
    name = "linear"
    linear = True

    def _strain(self, F: Tensor) -> Tensor:
        return 0.5 * (F + F.transpose(-1, -2)) - _eye(F.shape[-1], F)

    def energy_density(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        eps = self._strain(F)
        return mu * _ddot(eps, eps) + 0.5 * lam * _trace(eps) ** 2

    def stress(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        eps = self._strain(F)
        d = F.shape[-1]
        return 2.0 * mu[..., None, None] * eps + (lam * _trace(eps))[..., None, None] * _eye(d, F)

    def stress_derivative(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        d = F.shape[-1]
        I4 = _identity4(d, F)                                   # delta_ik delta_jl
        I4t = I4.permute(0, 1, 3, 2)                            # delta_il delta_jk
        II = _outer(_eye(d, F), _eye(d, F))
        A = mu[..., None, None, None, None] * (I4 + I4t) + lam[..., None, None, None, None] * II
        return A.expand(*F.shape[:-2], d, d, d, d)


class Corotated(Material):
    """PhysBAM's rotated linear model (see the module docstring)."""

    name = "corotated"
    default_nu = 0.475      # PhysBAM ROTATED_LINEAR's default Poisson ratio

    def energy_density(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        R = polar_rotation(F)
        stretch = _trace(R.transpose(-1, -2) @ F) - F.shape[-1]
        return mu * _ddot(F - R, F - R) + 0.5 * lam * stretch ** 2

    def stress(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        R = polar_rotation(F)
        stretch = _trace(R.transpose(-1, -2) @ F) - F.shape[-1]
        return 2.0 * mu[..., None, None] * (F - R) + (lam * stretch)[..., None, None] * R

    def stress_derivative(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        d = F.shape[-1]
        F = F.detach()
        R = polar_rotation(F)
        stretch = _trace(R.transpose(-1, -2) @ F) - d
        basis = _basis(d, F)                                     # dF = E_kl
        Rb, Fb = R[..., None, :, :], F[..., None, :, :]
        dR = rotation_differential(Rb, Fb, basis)                # (..., d^2, d, d)
        R_dot_dF = R.reshape(*R.shape[:-2], d * d)               # R : E_kl = R_kl
        mu_, lam_ = mu[..., None, None, None], lam[..., None, None, None]
        dP = (2.0 * mu_ * (basis - dR) + lam_ * R_dot_dF[..., None, None] * Rb
              + (lam * stretch)[..., None, None, None] * dR)
        A = dP.reshape(*dP.shape[:-3], d, d, d, d).permute(
            *range(dP.dim() - 3), -2, -1, -4, -3)               # (..., i, j, k, l)
        return _symmetrize(A)


def cofactor(F: Tensor) -> Tensor:
    """``cof(F) = det(F) F^{-T}`` (defined for singular ``F`` too), ``(..., d, d)``."""
    d = F.shape[-1]
    if d == 2:
        return torch.stack([torch.stack([F[..., 1, 1], -F[..., 1, 0]], -1),
                            torch.stack([-F[..., 0, 1], F[..., 0, 0]], -1)], -2)
    c0, c1, c2 = F[..., :, 0], F[..., :, 1], F[..., :, 2]
    return torch.stack([torch.linalg.cross(c1, c2), torch.linalg.cross(c2, c0),
                        torch.linalg.cross(c0, c1)], dim=-1)


def _levi_civita(like: Tensor) -> Tensor:
    eps = torch.zeros(3, 3, 3, dtype=like.dtype, device=like.device)
    for (i, j, k), s in (((0, 1, 2), 1), ((1, 2, 0), 1), ((2, 0, 1), 1),
                         ((0, 2, 1), -1), ((2, 1, 0), -1), ((1, 0, 2), -1)):
        eps[i, j, k] = s
    return eps


def cofactor_derivative(F: Tensor) -> Tensor:
    """``H_ijkl = d cof(F)_ij / dF_kl`` ``(..., d, d, d, d)``."""
    d = F.shape[-1]
    if d == 2:
        H = torch.zeros(2, 2, 2, 2, dtype=F.dtype, device=F.device)
        H[0, 0, 1, 1], H[1, 1, 0, 0], H[0, 1, 1, 0], H[1, 0, 0, 1] = 1.0, 1.0, -1.0, -1.0
        return H.expand(*F.shape[:-2], 2, 2, 2, 2)
    eps = _levi_civita(F)
    return torch.einsum("ikn,jlq,...nq->...ijkl", eps, eps, F)


class StableNeoHookean(Material):
    """Smith, de Goes and Kim (2018), with their rest-consistent Lame parameters."""

    name = "stable_neo_hookean"

    @staticmethod
    def _constants(mu: Tensor, lam: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        mu_s = 4.0 / 3.0 * mu
        lam_s = lam + 5.0 / 6.0 * mu
        alpha = 1.0 + 0.75 * mu_s / lam_s
        return mu_s, lam_s, alpha

    @staticmethod
    def _invariants(F: Tensor) -> tuple[Tensor, Tensor]:
        I_C = _ddot(F, F) + (3 - F.shape[-1])      # plane strain: F33 = 1
        return I_C, torch.linalg.det(F)

    def energy_density(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        mu_s, lam_s, alpha = self._constants(mu, lam)
        I_C, J = self._invariants(F)
        rest = 0.5 * lam_s * (1.0 - alpha) ** 2 - 0.5 * mu_s * math.log(4.0)
        return (0.5 * mu_s * (I_C - 3.0) + 0.5 * lam_s * (J - alpha) ** 2
                - 0.5 * mu_s * torch.log(I_C + 1.0) - rest)

    def stress(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        mu_s, lam_s, alpha = self._constants(mu, lam)
        I_C, J = self._invariants(F)
        a = mu_s * (1.0 - 1.0 / (I_C + 1.0))
        return a[..., None, None] * F + (lam_s * (J - alpha))[..., None, None] * cofactor(F)

    def stress_derivative(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        d = F.shape[-1]
        F = F.detach()
        mu_s, lam_s, alpha = self._constants(mu, lam)
        I_C, J = self._invariants(F)
        C = cofactor(F)

        def s(x: Tensor) -> Tensor:
            return x[..., None, None, None, None]

        A = (s(mu_s * (1.0 - 1.0 / (I_C + 1.0))) * _identity4(d, F)
             + s(2.0 * mu_s / (I_C + 1.0) ** 2) * _outer(F, F)
             + s(lam_s) * _outer(C, C)
             + s(lam_s * (J - alpha)) * cofactor_derivative(F))
        return _symmetrize(A)


MATERIALS: dict[str, type[Material]] = {
    "linear": LinearElastic,
    "corotated": Corotated,
    "stable_neo_hookean": StableNeoHookean,
}
ALIASES = {"neo_hookean": "stable_neo_hookean", "rotated_linear": "corotated"}


def get_material(name: str | Material) -> Material:
    """A material by name (``linear``, ``corotated``, ``stable_neo_hookean``)."""
    if isinstance(name, Material):
        return name
    key = ALIASES.get(str(name), str(name))
    if key not in MATERIALS:
        raise MaterialError(f"unknown constitutive model {name!r}; choose one of "
                            f"{sorted(MATERIALS)} (alias: {sorted(ALIASES)})")
    return MATERIALS[key]()
