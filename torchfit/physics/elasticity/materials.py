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

from .kinematics import polar_rotation, rotation_variant_svd
from .material_base import Material, MaterialError, ddot, eye, identity4, outer, trace
from .stable_neo_hookean import StableNeoHookean


class LinearElastic(Material):
    name = "linear"
    linear = True

    def _strain(self, F: Tensor) -> Tensor:
        return 0.5 * (F + F.transpose(-1, -2)) - eye(F.shape[-1], F)

    def energy_density(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        eps = self._strain(F)
        return mu * ddot(eps, eps) + 0.5 * lam * trace(eps) ** 2

    def stress(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        eps = self._strain(F)
        d = F.shape[-1]
        return 2.0 * mu[..., None, None] * eps + (lam * trace(eps))[..., None, None] * eye(d, F)

    def stress_derivative(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        d = F.shape[-1]
        I4 = identity4(d, F)                                   # delta_ik delta_jl
        I4t = I4.permute(0, 1, 3, 2)                            # delta_il delta_jk
        II = outer(eye(d, F), eye(d, F))
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
    hit counts on the arm are in ``docs/notes/arm3d.md``.
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
        stretch = trace(R.transpose(-1, -2) @ F) - F.shape[-1]
        return mu * ddot(F - R, F - R) + 0.5 * lam * stretch ** 2

    def stress(self, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
        R = polar_rotation(F)
        stretch = trace(R.transpose(-1, -2) @ F) - F.shape[-1]
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
        return A + c0[..., None, None, None, None] * identity4(d, F)


#: config name (``problem.model``) -> material class
MATERIALS: dict[str, type[Material]] = {
    "linear": LinearElastic,
    "corotated": Corotated,
    "stable_neo_hookean": StableNeoHookean,
}
#: other names a config may give a material -> its name in :data:`MATERIALS`
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
