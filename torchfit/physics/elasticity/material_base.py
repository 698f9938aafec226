"""The constitutive-model contract (:class:`Material`) and the tensor algebra the models share.

Shapes: deformation gradients ``F`` ``(..., d, d)``; fourth-order tangents ``(..., d, d, d, d)``;
Lame parameters broadcast against the batch shape. :func:`project_psd` is the generic PSD
projection of a tangent (the package's models project in closed form instead).
"""
from __future__ import annotations

import torch
from torch import Tensor

from ...errors import SimulationError


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


def eye(d: int, like: Tensor) -> Tensor:
    return torch.eye(d, dtype=like.dtype, device=like.device)


def trace(M: Tensor) -> Tensor:
    return M.diagonal(dim1=-2, dim2=-1).sum(-1)


def ddot(A: Tensor, B: Tensor) -> Tensor:
    return (A * B).sum(dim=(-2, -1))


def outer(A: Tensor, B: Tensor) -> Tensor:
    """``A_ij B_kl`` ``(..., d, d, d, d)``."""
    return A[..., :, :, None, None] * B[..., None, None, :, :]


def basis(d: int, like: Tensor) -> Tensor:
    """``(d^2, d, d)``: the matrices ``E_kl`` in the order ``k * d + l``."""
    return torch.eye(d * d, dtype=like.dtype, device=like.device).reshape(d * d, d, d)


def identity4(d: int, like: Tensor) -> Tensor:
    """``delta_ik delta_jl`` ``(d, d, d, d)``."""
    return basis(d, like).reshape(d, d, d, d).permute(2, 3, 0, 1).contiguous()


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
