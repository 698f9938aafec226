"""Stable neo-Hookean (Smith, de Goes and Kim 2018): energy, stress, exact and projected tangent.

Also the closed-form determinant and cofactor of ``(..., d, d)`` matrices (d = 2, 3) and the
derivative of the cofactor, which its stress and tangent use.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from .kinematics import det2, det3, rotation_variant_svd, sym_eig2, sym_eig3
from .material_base import Material, ddot


def determinant(F: Tensor) -> Tensor:
    """``det F`` of ``(..., d, d)``, d = 2 or 3, in closed form (no batched LU)."""
    return det3(F) if F.shape[-1] == 3 else det2(F)


def cofactor(F: Tensor) -> Tensor:
    """``cof(F) = det(F) F^{-T}`` (defined for singular ``F`` too), ``(..., d, d)``."""
    d = F.shape[-1]
    if d == 2:
        return torch.stack([torch.stack([F[..., 1, 1], -F[..., 1, 0]], -1),
                            torch.stack([-F[..., 0, 1], F[..., 0, 0]], -1)], -2)
    c0, c1, c2 = F[..., :, 0], F[..., :, 1], F[..., :, 2]
    return torch.stack([torch.linalg.cross(c1, c2), torch.linalg.cross(c2, c0),
                        torch.linalg.cross(c0, c1)], dim=-1)


def _cofactor_derivative_flat(f: Tensor, d: int) -> Tensor:
    """``d cof(F) / dF`` as ``(N, d^2, d^2)`` matrices (row ``i d + j``, column ``k d + l``)
    for ``f = vec(F)`` ``(N, d^2)``: constant in 2-D, linear in ``F`` in 3-D (one matmul
    with the ``(9, 81)`` tensor ``eps_ikn eps_jlq``)."""
    like = f
    if d == 2:
        return cofactor_derivative(torch.zeros(2, 2, dtype=f.dtype, device=f.device)
                                   ).reshape(1, 4, 4).expand(f.shape[0], 4, 4)
    eps = _levi_civita(like)
    K = torch.einsum("ikn,jlq->nqijkl", eps, eps).reshape(9, 81)
    return (f @ K).reshape(-1, 9, 9)


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
        I_C = ddot(F, F) + (3 - F.shape[-1])      # plane strain: F33 = 1
        return I_C, determinant(F)

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

    #: ``stress_derivative`` takes ``projected`` (its PSD projection is analytic)
    projects_tangent = True

    def stress_derivative(self, F: Tensor, mu: Tensor, lam: Tensor,
                          projected: bool = False) -> Tensor:
        """The exact ``A = dP/dF`` ``(..., d, d, d, d)``; ``projected=True``: its projection
        onto the positive semi-definite cone from the analytic eigensystem
        (:meth:`eigensystem`), for the elements with an eigenvalue below ``-1e-12`` times
        the largest diagonal entry of ``A`` (the others are returned exactly as the exact
        ``A``, as :func:`project_psd` does). The eigenvalues of every element are computed,
        the eigenmatrices only for those indefinite ones."""
        d, d2 = F.shape[-1], F.shape[-1] ** 2
        F = F.detach()
        batch = F.shape[:-2]
        mu_s, lam_s, alpha = self._constants(mu, lam)
        I_C, J = self._invariants(F)

        def flat(x: Tensor | float) -> Tensor:
            return torch.broadcast_to(torch.as_tensor(x, dtype=F.dtype, device=F.device),
                                      batch).reshape(-1)

        # A = a I + b vec(F) vec(F)^T + lam' vec(C) vec(C)^T + e dcof(F)/dF as d^2 x d^2
        # matrices: one batched (d^2 x 2) (2 x d^2) product and one (d^2 -> d^4) matmul
        # for the cofactor derivative, which is linear in F (no d^4 einsum chain)
        f = F.reshape(-1, d2)
        vectors = torch.stack([f, cofactor(F).reshape(-1, d2)], dim=-1)    # (N, d^2, 2)
        weights = torch.stack([flat(2.0 * mu_s / (I_C + 1.0) ** 2), flat(lam_s)], dim=-1)
        A = (vectors * weights[:, None, :]) @ vectors.transpose(-1, -2)
        A = A + flat(lam_s * (J - alpha))[:, None, None] * _cofactor_derivative_flat(f, d)
        A.diagonal(dim1=-2, dim2=-1).add_(flat(mu_s * (1.0 - 1.0 / (I_C + 1.0)))[:, None])
        A = 0.5 * (A + A.transpose(-1, -2))
        A = A.reshape(*batch, d, d, d, d)
        if not projected:
            return A
        # eigenvalues of every element (cheap), eigenmatrices of the indefinite ones only
        flat = A.reshape(-1, d * d, d * d)
        F_flat = F.reshape(-1, d, d)
        mu_flat = torch.broadcast_to(torch.as_tensor(mu, dtype=F.dtype, device=F.device),
                                     F.shape[:-2]).reshape(-1)
        lam_flat = torch.broadcast_to(torch.as_tensor(lam, dtype=F.dtype, device=F.device),
                                      F.shape[:-2]).reshape(-1)
        eigenvalues, _ = self.eigensystem(F_flat, mu_flat, lam_flat, with_modes=False)
        tol = 1e-12 * flat.diagonal(dim1=-2, dim2=-1).abs().amax(dim=-1)
        tol = torch.where(tol > 0, tol, torch.full_like(tol, 1e-12))
        bad = torch.nonzero(eigenvalues.amin(dim=-1) < -tol).reshape(-1)
        if bad.numel() == 0:
            return A
        values, modes = self.eigensystem(F_flat[bad], mu_flat[bad], lam_flat[bad])
        vectors = modes.reshape(-1, d * d, d * d)           # rows: vec(M_m)
        flat = flat.clone()
        flat[bad] = (vectors.transpose(-1, -2) * values.clamp(min=0.0)[:, None, :]) @ vectors
        return flat.reshape(A.shape)

    def eigensystem(self, F: Tensor, mu: Tensor, lam: Tensor, with_modes: bool = True
                    ) -> tuple[Tensor, Tensor | None]:
        """Eigenvalues ``(..., d^2)`` and orthonormal eigenmatrices ``(..., d^2, d, d)`` of
        ``dP/dF`` (as a ``d^2 x d^2`` matrix), in closed form (Smith, de Goes, Kim 2018,
        Sec. 4.4 and appendix; Teran et al. 2005).

        In the rotation-variant SVD ``F = U diag(sigma) V^T`` (:func:`rotation_variant_svd`)
        ``Psi`` depends on ``sigma`` only, through ``I_C = |sigma|^2 (+1 in plane strain)``
        and ``J = prod sigma``. With ``mu1 = mu' (1 - 1/(I_C + 1))`` and ``s = lam' (J -
        alpha)``, for every pair ``j < k`` (third index ``l``; ``sigma_l = 1`` in plane
        strain) the twist ``U (E_jk - E_kj) V^T / sqrt 2`` has eigenvalue ``mu1 + s
        sigma_l`` and the flip ``U (E_jk + E_kj) V^T / sqrt 2`` has ``mu1 - s sigma_l``
        (no division: exact at repeated singular values), and the scaling modes ``U
        diag(q) V^T`` have the eigenpairs ``(h, q)`` of the ``d x d`` Hessian of ``Psi(sigma)``,
        ``mu1 I + 2 mu' / (I_C + 1)^2 sigma sigma^T + lam' g g^T + s O`` with ``g = dJ/dsigma``
        and ``O_jk = sigma_l`` off the diagonal (:func:`~.kinematics.sym_eig3` by Jacobi in
        3-D, :func:`~.kinematics.sym_eig2` in closed form in 2-D). Elementwise tensor
        operations only: any batch size on any device. Order: the ``d`` scaling modes,
        then twist and flip of every pair. ``with_modes=False``: eigenvalues only (the
        modes are ``None``).
        """
        d = F.shape[-1]
        F = F.detach()
        mu_s, lam_s, alpha = self._constants(mu, lam)
        U, sigma, Vh = rotation_variant_svd(F)
        I_C = (sigma * sigma).sum(-1) + (3 - d)
        J = sigma.prod(-1)
        batch = I_C.shape
        mu1 = torch.broadcast_to(mu_s * (1.0 - 1.0 / (I_C + 1.0)), batch)
        stretch = torch.broadcast_to(lam_s * (J - alpha), batch)
        lam_b = torch.broadcast_to(torch.as_tensor(lam_s, dtype=F.dtype, device=F.device), batch)
        log_term = torch.broadcast_to(2.0 * mu_s / (I_C + 1.0) ** 2, batch)
        if d == 3:
            pairs = ((0, 1, 2), (0, 2, 1), (1, 2, 0))
            g = torch.stack([sigma[..., 1] * sigma[..., 2], sigma[..., 0] * sigma[..., 2],
                             sigma[..., 0] * sigma[..., 1]], dim=-1)
            third = torch.zeros(*batch, 3, 3, dtype=F.dtype, device=F.device)
            for j, k, l in pairs:
                third[..., j, k] = third[..., k, j] = sigma[..., l]
        else:
            pairs = ((0, 1, None),)
            g = torch.stack([sigma[..., 1], sigma[..., 0]], dim=-1)
            third = torch.tensor([[0.0, 1.0], [1.0, 0.0]], dtype=F.dtype,
                                 device=F.device).expand(*batch, 2, 2)
        eye = torch.eye(d, dtype=F.dtype, device=F.device)
        hessian = (mu1[..., None, None] * eye
                   + log_term[..., None, None] * sigma[..., :, None] * sigma[..., None, :]
                   + lam_b[..., None, None] * g[..., :, None] * g[..., None, :]
                   + stretch[..., None, None] * third)
        scaling_values, q = sym_eig3(hessian) if d == 3 else sym_eig2(hessian)
        values = [scaling_values[..., m] for m in range(d)]
        for j, k, l in pairs:
            sigma_l = sigma[..., l] if l is not None else torch.ones_like(mu1)
            values += [mu1 + stretch * sigma_l, mu1 - stretch * sigma_l]
        if not with_modes:
            return torch.stack(values, dim=-1), None
        # U diag(q_m) V^T = sum_i q_im u_i v_i^T
        modes = [torch.einsum("...ai,...i,...ib->...ab", U, q[..., :, m], Vh) for m in range(d)]
        root_half = 1.0 / math.sqrt(2.0)
        for j, k, _ in pairs:
            outer_jk = U[..., :, j, None] * Vh[..., None, k, :]
            outer_kj = U[..., :, k, None] * Vh[..., None, j, :]
            modes += [root_half * (outer_jk - outer_kj), root_half * (outer_jk + outer_kj)]
        return torch.stack(values, dim=-1), torch.stack(modes, dim=-3)
