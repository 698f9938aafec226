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
from .kinematics import det2, det3, polar_rotation, svd2, svd3, sym_eig2, sym_eig3


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


#: matrices per batched Cholesky/``eigh`` call in :func:`project_psd` (cuSOLVER's batched
#: ``syevj`` fails or asks for hundreds of GiB at 10^5..10^6 matrices)
PROJECT_PSD_CHUNK = 16384


def project_psd(A: Tensor) -> Tensor:
    """``A`` ``(..., d, d, d, d)`` with negative eigenvalues (as ``d^2 x d^2``) set to 0.

    Matrices whose eigenvalues are all above ``-1e-12`` times their largest diagonal entry
    are returned unchanged (up to symmetrisation).

    The generic route (batched Cholesky test, ``torch.linalg.eigh`` on the matrices that
    fail it, in chunks of :data:`PROJECT_PSD_CHUNK`), for a material without an analytic
    eigensystem; the package's materials project in closed form instead
    (:meth:`Corotated.stiffness_terms`, :meth:`StableNeoHookean.stress_derivative`).
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
    info = torch.cat([torch.linalg.cholesky_ex(M[i:i + PROJECT_PSD_CHUNK]
                                               + tol[i:i + PROJECT_PSD_CHUNK, None, None] * eye)[1]
                      for i in range(0, M.shape[0], PROJECT_PSD_CHUNK)]) if M.shape[0] else \
        torch.zeros(0, dtype=torch.int32, device=M.device)
    bad = torch.nonzero(info != 0).reshape(-1)
    if bad.numel() == 0:
        return A
    M = M.clone()
    for i in range(0, bad.numel(), PROJECT_PSD_CHUNK):
        rows = bad[i:i + PROJECT_PSD_CHUNK]
        eigenvalues, vectors = torch.linalg.eigh(M[rows])
        M[rows] = (vectors * eigenvalues.clamp(min=0.0)[..., None, :]) @ vectors.transpose(-1, -2)
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


class SVDMemo:
    """The rotation-variant SVDs of recently decomposed deformation gradients, per frame.

    Newton evaluates the residual at a trial point and, once the trial is accepted, the
    tangent at that same point; at the solution the adjoint's factorisation takes the
    tangent once more. Each is one SVD of the same ``F``: the most expensive part of a
    corotated Newton iteration (about a third of its time on the arm). A batch
    ``(B, n_cells, d, d)`` (or one frame ``(n_cells, d, d)``) is looked up frame by
    frame: a fingerprint (the sum of the frame's entries) finds the candidate and
    ``torch.equal`` confirms it bit for bit, so a hit returns exactly what
    :func:`rotation_variant_svd` returned for that frame; the frames that miss are
    decomposed together. At most ``capacity`` times the largest batch seen is kept
    (least recently used dropped); only detached tensors are stored. One batch
    (``capacity=1``) already serves nearly every repeat of Newton's pattern; its cost and
    hit counts on the arm are in ``docs/problems/arm3d.md``.
    """

    def __init__(self, capacity: int = 1) -> None:
        self.capacity = capacity
        self._frames: dict[tuple, tuple[Tensor, Tensor, Tensor, Tensor]] = {}
        self._largest = 1
        self.hits = 0               # frames served from the memo (counted for the tests)
        self.misses = 0

    def __call__(self, F: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        if F.dim() not in (3, 4) or F.requires_grad:
            return rotation_variant_svd(F)
        batch = F if F.dim() == 4 else F[None]
        keys = [(batch.shape[1:], batch.dtype, batch.device, float(total))
                for total in batch.sum(dim=(1, 2, 3)).tolist()]
        found: list[tuple[Tensor, Tensor, Tensor] | None] = []
        for key, frame in zip(keys, batch):
            entry = self._frames.pop(key, None)
            if entry is not None and torch.equal(entry[0], frame):
                self._frames[key] = entry          # most recently used last
                found.append(entry[1:])
            else:
                found.append(None)
        missing = [i for i, entry in enumerate(found) if entry is None]
        self.hits += len(found) - len(missing)
        self.misses += len(missing)
        if missing:
            U, sigma, Vh = rotation_variant_svd(batch[missing])
            for j, i in enumerate(missing):
                found[i] = (U[j], sigma[j], Vh[j])
                # copies: a view would keep the whole batch alive after eviction
                self._frames[keys[i]] = (batch[i].clone(), U[j].clone(), sigma[j].clone(),
                                         Vh[j].clone())
        self._largest = max(self._largest, batch.shape[0])
        while len(self._frames) > self.capacity * self._largest:
            self._frames.pop(next(iter(self._frames)))
        if len(missing) == batch.shape[0]:
            out = (U, sigma, Vh)
        else:
            out = tuple(torch.stack([entry[k] for entry in found]) for k in range(3))
        return out if F.dim() == 4 else tuple(t[0] for t in out)


class Corotated(Material):
    """PhysBAM's rotated linear model (see the module docstring).

    Newton's no-graph evaluations (:meth:`stress_and_energy`, :meth:`stiffness_terms`)
    share one :class:`SVDMemo` per instance, so the tangent at an accepted trial point
    reuses the decomposition the line search made there."""

    name = "corotated"
    default_nu = 0.475      # PhysBAM ROTATED_LINEAR's default Poisson ratio

    def __init__(self) -> None:
        self.svd_memo = SVDMemo()

    def energy_density(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        R = polar_rotation(F)
        stretch = _trace(R.transpose(-1, -2) @ F) - F.shape[-1]
        return mu * _ddot(F - R, F - R) + 0.5 * lam * stretch ** 2

    def stress(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        R = polar_rotation(F)
        stretch = _trace(R.transpose(-1, -2) @ F) - F.shape[-1]
        return 2.0 * mu[..., None, None] * (F - R) + (lam * stretch)[..., None, None] * R

    def stress_and_energy(self, F: Tensor, mu: Tensor, lam: Tensor) -> tuple[Tensor, Tensor]:
        """``(P, Psi)`` from one rotation-variant SVD (no gradient: Newton's line search):
        ``Psi = mu sum (sigma_i - 1)^2 + lam/2 (sum sigma_i - d)^2``."""
        d = F.shape[-1]
        with torch.no_grad():
            U, sigma, Vh = self.svd_memo(F.detach())
            R = U @ Vh
            stretch = sigma.sum(-1) - d
            psi = mu * ((sigma - 1.0) ** 2).sum(-1) + 0.5 * lam * stretch ** 2
            P = 2.0 * mu[..., None, None] * (F - R) + (lam * stretch)[..., None, None] * R
        return P, psi

    #: the twist modes ``T_jk`` of :meth:`stiffness_terms`, by dimension
    TWIST_PAIRS = {3: ((0, 1), (1, 2), (0, 2)), 2: ((0, 1),)}

    def stiffness_terms(self, F: Tensor, mu: Tensor, lam: Tensor, projected: bool = False
                        ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The exact (or PSD-projected) ``dP/dF`` in closed form (Smith, de Goes, Kim 2019,
        "Analytic eigensystems for isotropic distortion energies"):
        ``A = c0 I + sum_m c_m vec(V_m) vec(V_m)^T``.

        With ``I1 = tr(R^T F)`` (the signed singular values' sum) and ``I2 = ||F||^2``,
        ``Psi = mu (I2 - 2 I1 + d) + lam/2 (I1 - d)^2``, so
        ``A = 2 mu I + (lam (I1 - d) - 2 mu) d2I1/dF2 + lam vec(R) vec(R)^T``; the Hessian
        of ``I1`` lives on the twist modes ``V_m = U (E_kj - E_jk) V^T / sqrt 2`` (pairs
        :attr:`TWIST_PAIRS`) with eigenvalues ``2 / (sigma_j + sigma_k)``. Twist modes are
        orthonormal and orthogonal to ``R``, so the eigenvalues of ``A`` are ``2 mu +
        c_twist`` on them, ``2 mu + d lam`` along ``R`` and ``2 mu`` elsewhere: projecting
        ``A`` onto the PSD cone clamps the twist eigenvalues only.

        Returns ``c0`` ``(...)``, ``c`` ``(..., m)`` (the twists, then ``R = U V^T``) and the
        rotation-variant SVD factors ``U``, ``Vh`` ``(..., d, d)`` defining the ``V_m``.
        """
        d = F.shape[-1]
        U, sigma, Vh = self.svd_memo(F.detach())
        I1 = sigma.sum(-1)
        pairs = self.TWIST_PAIRS[d]
        denominator = torch.stack([sigma[..., j] + sigma[..., k] for j, k in pairs], dim=-1)
        # sigma_j + sigma_k >= 0 in the rotation-variant SVD; 0 only for a collapsed element
        tiny = 1e-12 * sigma.abs().amax(dim=-1, keepdim=True).clamp(min=1e-300)
        mu_b = torch.broadcast_to(mu, I1.shape)
        lam_b = torch.broadcast_to(lam, I1.shape)
        twist = (lam_b * (I1 - d) - 2.0 * mu_b)[..., None] * 2.0 / denominator.clamp(min=tiny)
        if projected:
            # clamp the twist eigenvalues 2 mu + twist that are negative beyond round-off:
            # at rest they are 0 (rotation invariance) up to the SVD's last bit, and those
            # elements must keep their exact tangent (as project_psd leaves them)
            eigenvalue = 2.0 * mu_b[..., None] + twist
            negative = eigenvalue < -1e-12 * (2.0 * mu_b[..., None]).abs()
            twist = torch.where(negative, -2.0 * mu_b[..., None], twist)
        c = torch.cat([twist, lam_b[..., None]], dim=-1)
        return 2.0 * mu_b, c, U, Vh

    def stiffness_modes(self, U: Tensor, Vh: Tensor) -> Tensor:
        """The ``V_m`` of :meth:`stiffness_terms` ``(..., m, d, d)``."""
        d = U.shape[-1]
        modes = []
        for j, k in self.TWIST_PAIRS[d]:
            T = torch.zeros(d, d, dtype=U.dtype, device=U.device)
            T[j, k], T[k, j] = -1.0 / math.sqrt(2.0), 1.0 / math.sqrt(2.0)
            modes.append(U @ T @ Vh)
        return torch.stack(modes + [U @ Vh], dim=-3)

    def stress_derivative(self, F: Tensor, mu: Tensor, lam: Tensor,
                          projected: bool = False) -> Tensor:
        d = F.shape[-1]
        c0, c, U, Vh = self.stiffness_terms(F, mu, lam, projected)
        V = self.stiffness_modes(U, Vh)
        A = torch.einsum("...m,...mij,...mkl->...ijkl", c, V, V)
        return A + c0[..., None, None, None, None] * _identity4(d, F)


def rotation_variant_svd(F: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``F = U diag(sigma) V^T`` with ``det U = det V = +1`` (``(..., d, d)``): the last
    singular value carries the sign of ``det F`` (negative for an inverted element).
    3-D: :func:`~.kinematics.svd3` (vectorised Jacobi); 2-D: :func:`~.kinematics.svd2`
    (closed form). Neither calls LAPACK or cuSOLVER (any batch size, any device)."""
    if F.shape[-1] == 3:
        return svd3(F)
    if F.shape[-1] == 2:
        return svd2(F)
    raise ValueError(f"rotation-variant SVD of {F.shape[-1]}x{F.shape[-1]} matrices is not "
                     "implemented (d = 2 or 3)")


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
        I_C = _ddot(F, F) + (3 - F.shape[-1])      # plane strain: F33 = 1
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
