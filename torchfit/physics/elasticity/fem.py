"""Simplicial finite elements for hyperelasticity, vectorised over elements and frames.

:class:`SimplicialElasticity` is an :class:`~torchfit.physics.EquilibriumModel`: for
positions ``x`` ``(F, n_vertices * d)`` (vertex-major dofs ``v * d + i``) and one
Young's modulus per element ``E`` ``(n_cells,)`` it gives

* ``energy(x, E)`` ``(F,)``: ``sum_e vol_e Psi(F_e)``;
* ``residual(x, E)``: the energy gradient ``dEnergy/dx`` (internal forces with the sign
  of a residual; ``forces = -residual``), ``R_a = sum_e vol_e P_e g_a``;
* ``tangent_values(x, E, projected=False)``: contributions ``vol G^T A G`` of the exact
  Hessian on a pattern built once (every element's ``(d + 1) d`` local dofs, all
  pairs); ``projected=True`` clamps each element's ``A`` to be positive semi-definite
  (for Newton's search direction; the adjoint always gets the exact one);
* ``param_derivative(x, E)``: ``dR/dE`` as products (``R`` is linear in ``E``), including
  the all-frames, many-directions ``matmul`` that ``Equilibrium.jacobian`` uses.
"""
from __future__ import annotations

import math
import warnings

import torch
from torch import Tensor

from ...linalg import SparsePattern
from .kinematics import RestShape
from .material_base import (InvalidModulusError, Material, MaterialError, check_poisson_ratio,
                            project_psd)
from .materials import get_material


class ElasticParamDerivative:
    """``dR/dE`` at fixed positions: element forces of unit modulus, ``(F, n_cells, d+1, d)``.

    ``R`` is linear in ``E``, so ``dR/dE_e`` is the element force of element ``e`` at unit
    modulus. Products: :meth:`jvp` (one direction), :meth:`vjp` (summed over frames) and
    :meth:`matmul` (many directions at once, every frame).
    """

    def __init__(self, rest: RestShape, unit_contributions: Tensor) -> None:
        self.rest = rest
        n_frames, n_cells = unit_contributions.shape[:2]
        self.n_frames, self.n_cells = int(n_frames), int(n_cells)
        self.n_dofs = rest.n_vertices * rest.dim
        self.unit = unit_contributions.contiguous()
        # (m, (d+1) d, F): the layout of w^T gathered at the element dofs (fastest vjp)
        self._unit_local = self.unit.reshape(n_frames, n_cells, -1).permute(1, 2, 0).contiguous()
        self._dofs = rest.element_dofs().to(unit_contributions.device)
        self._stacked: Tensor | None = None

    def jvp(self, v: Tensor) -> Tensor:
        """``(dR/dE) v`` ``(F, n_dofs)`` for ``v`` ``(n_cells,)``."""
        return self.rest.scatter(self.unit * v.to(self.unit)[:, None, None])

    def vjp(self, w: Tensor) -> Tensor:
        """``(dR/dE)^T w`` ``(n_cells,)`` for ``w`` ``(F, n_dofs)`` (summed over frames)."""
        local = w.to(self.unit).T[self._dofs]                     # (m, k, F)
        return (local * self._unit_local).sum(dim=(1, 2))

    def matmul(self, V: Tensor) -> Tensor:
        """``(dR/dE) V`` of every frame, ``(F, n_dofs, k)``, for ``V`` ``(n_cells, k)``.

        One product of a sparse CSR matrix ``(F n_dofs, n_cells)`` (frame-major rows; its
        entries are the unit element forces, ``F n_cells (d+1) d`` of them, built on the
        first call and kept) with ``V``: memory ``O(F n_cells (d+1) d + F n_dofs k)``, no
        ``(F, n_cells, (d+1) d, k)`` intermediate.
        """
        if V.dim() != 2 or V.shape[0] != self.n_cells:
            raise ValueError(f"directions must have shape ({self.n_cells}, k), got "
                             f"{tuple(V.shape)}")
        with warnings.catch_warnings():   # "sparse CSR tensor support is in beta state"
            warnings.simplefilter("ignore", UserWarning)
            out = torch.sparse.mm(self._matrix(), V.to(self.unit).contiguous())
        return out.reshape(self.n_frames, self.n_dofs, V.shape[1])

    def _matrix(self) -> Tensor:
        """The sparse ``(F n_dofs, n_cells)`` CSR matrix of :meth:`matmul` (made once)."""
        if self._stacked is None:
            device = self.unit.device
            dofs = self._dofs.reshape(-1)                        # (n_cells (d+1) d,)
            order = torch.argsort(dofs, stable=True)             # CSR order within a frame
            cells = torch.arange(self.n_cells, device=device).repeat_interleave(
                self._dofs.shape[1])[order]
            per_frame = dofs.numel()
            counts = torch.bincount(dofs, minlength=self.n_dofs)
            crow_frame = torch.cumsum(counts, 0)
            starts = torch.arange(self.n_frames, device=device)[:, None] * per_frame
            crow = torch.cat([torch.zeros(1, dtype=torch.long, device=device),
                              (starts + crow_frame[None, :]).reshape(-1)])
            values = self.unit.reshape(self.n_frames, -1)[:, order].reshape(-1)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                self._stacked = torch.sparse_csr_tensor(
                    crow, cells.repeat(self.n_frames), values,
                    size=(self.n_frames * self.n_dofs, self.n_cells), check_invariants=False)
        return self._stacked


class SimplicialElasticity:
    """Linear triangles (d = 2, plane strain) or tetrahedra (d = 3) of one material.

    Args:
        points: ``(n_vertices, d)`` rest positions.
        cells: ``(n_cells, d + 1)`` positively oriented simplices.
        material: ``'linear'``, ``'corotated'``, ``'stable_neo_hookean'`` (or a
            :class:`~.materials.Material`).
        nu: Poisson ratio in ``(-1, 0.5)``; default the material's (``0.475`` for
            corotated, as PhysBAM; ``0.3`` otherwise).

    Raises :class:`~torchfit.mesh.MeshError` naming inverted or degenerate rest elements
    and :class:`~.materials.MaterialError` for an invalid ``nu``.
    """

    symmetric = True
    #: frames differ only in their positions (no per-frame loads): see ``Equilibrium``
    frame_independent = True

    def __init__(self, points: Tensor, cells: Tensor, material: str | Material = "corotated",
                 nu: float | None = None, dtype: torch.dtype = torch.float64,
                 device: torch.device | str = "cpu") -> None:
        self.material = get_material(material)
        self.nu = check_poisson_ratio(self.material.default_nu if nu is None else nu)
        self.rest = RestShape(points, cells, dtype=dtype, device=device)
        self.dim = self.rest.dim
        self.n_cells = self.rest.n_cells
        self.n_vertices = self.rest.n_vertices
        self.n_dofs = self.n_vertices * self.dim
        self.linear = bool(self.material.linear)
        # Lame parameters per unit Young's modulus (everything is linear in E).
        self.mu_per_E = 1.0 / (2.0 * (1.0 + self.nu))
        self.lam_per_E = self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))
        # every element couples its d + 1 vertices' d x d blocks (local dof a * d + i):
        # built on the device of the mesh, sorting only the (d + 1)^2 vertex pairs
        self.tangent_pattern = SparsePattern.from_dense_blocks(self.rest.cells, self.dim,
                                                               self.n_vertices)
        self.local_dofs = (self.dim + 1) * self.dim

    # -- inputs ---------------------------------------------------------------------------
    def check_modulus(self, E: Tensor) -> None:
        """Raise naming the first element whose Young's modulus is not positive and finite."""
        if E.shape != (self.n_cells,):
            raise MaterialError(f"Young's modulus must have one value per element, shape "
                                f"({self.n_cells},), got {tuple(E.shape)}")
        values = E.detach()
        bad = ~(torch.isfinite(values) & (values > 0))
        if bool(bad.any()):
            e = int(torch.nonzero(bad)[0])
            raise InvalidModulusError(
                f"Young's modulus must be positive and finite: element {e} has E = "
                f"{float(values[e])} ({int(bad.sum())} bad element(s) in all); with an "
                "identity parameterisation keep E > 0 or use transform=exp")

    def positions(self, x: Tensor) -> Tensor:
        """Flat dofs ``(F, n_dofs)`` as positions ``(F, n_vertices, d)``."""
        if x.shape[-1] != self.n_dofs:
            raise ValueError(f"expected {self.n_dofs} dofs ({self.n_vertices} vertices x "
                             f"{self.dim}), got {x.shape[-1]}")
        return x.reshape(*x.shape[:-1], self.n_vertices, self.dim)

    def lame(self, E: Tensor) -> tuple[Tensor, Tensor]:
        self.check_modulus(E)
        return E * self.mu_per_E, E * self.lam_per_E

    def deformation_gradients(self, x: Tensor) -> Tensor:
        """``(F, n_cells, d, d)`` of flat dofs ``(F, n_dofs)``."""
        return self.rest.deformation_gradient(self.positions(x))

    # -- energy, residual, tangent --------------------------------------------------------
    def energy(self, x: Tensor, E: Tensor) -> Tensor:
        """Elastic energy per frame ``(F,)``."""
        mu, lam = self.lame(E)
        psi = self.material.energy_density(self.deformation_gradients(x), mu, lam)
        return (psi * self.rest.volumes.to(psi)).sum(-1)

    def element_forces(self, x: Tensor, E: Tensor) -> Tensor:
        """Energy gradient per element and local vertex ``(F, n_cells, d + 1, d)``."""
        mu, lam = self.lame(E)
        P = self.material.stress(self.deformation_gradients(x), mu, lam)
        return self.rest.nodal(P)

    def residual(self, x: Tensor, E: Tensor) -> Tensor:
        """``dEnergy/dx`` ``(F, n_dofs)`` (zero at equilibrium of the free dofs)."""
        return self.rest.scatter(self.element_forces(x, E))

    def residual_and_energy(self, x: Tensor, E: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`residual` ``(F, n_dofs)`` and :meth:`energy` ``(F,)`` together, sharing the
        material's decomposition of ``F`` where it offers ``stress_and_energy``."""
        if not hasattr(self.material, "stress_and_energy"):
            return self.residual(x, E), self.energy(x, E)
        mu, lam = self.lame(E)
        P, psi = self.material.stress_and_energy(self.deformation_gradients(x), mu, lam)
        energy = (psi * self.rest.volumes.to(psi)).sum(-1)
        return self.rest.scatter(self.rest.nodal(P)), energy

    def forces(self, x: Tensor, E: Tensor) -> Tensor:
        """Internal nodal forces ``-dEnergy/dx`` ``(F, n_dofs)``."""
        return -self.residual(x, E)

    def stress_derivative(self, x: Tensor, E: Tensor, projected: bool = False) -> Tensor:
        """``A = dP/dF`` per frame and element ``(F, n_cells, d, d, d, d)``."""
        mu, lam = self.lame(E)
        F = self.deformation_gradients(x.detach())
        if hasattr(self.material, "stiffness_terms") or getattr(self.material,
                                                                "projects_tangent", False):
            # the material projects in closed form (no batched eigensolver)
            return self.material.stress_derivative(F, mu.detach(), lam.detach(), projected)
        A = self.material.stress_derivative(F, mu.detach(), lam.detach())
        return project_psd(A) if projected else A

    def element_stiffness(self, x: Tensor, E: Tensor, projected: bool = False) -> Tensor:
        """Element Hessians ``(F, n_cells, (d+1) d, (d+1) d)`` (local dofs a-major).

        A material with ``stiffness_terms`` (``A = c0 I + sum_m c_m vec(V_m) vec(V_m)^T``,
        corotated) gets ``K = vol (c0 (G G^T) x I + sum_m c_m q_m q_m^T)`` with
        ``q_m = G V_m^T``: no ``d^4`` tensor is formed (about 10x faster in 3-D).
        """
        g = self.rest.grads
        vol = self.rest.volumes
        k = self.local_dofs
        if hasattr(self.material, "stiffness_terms"):
            mu, lam = self.lame(E)
            F = self.deformation_gradients(x.detach())
            c0, c, U, Vh = self.material.stiffness_terms(F, mu.detach(), lam.detach(), projected)
            q = self._mode_gradients(U, Vh, self.material.TWIST_PAIRS[self.dim])
            vol = vol.to(q)
            # volumes folded into the small coefficient arrays: two passes over K, not four
            K = torch.einsum("...em,...emk,...eml->...ekl", c * vol[:, None], q, q)
            return K.addcmul_((c0 * vol)[..., None, None], self._gram(K).reshape(-1, k, k))
        A = self.stress_derivative(x, E, projected)
        g = g.to(A)
        K = torch.einsum("...eijkl,eaj,ebl->...eaibk", A, g, g)
        K = K * vol.to(A)[:, None, None, None, None]
        return K.reshape(*K.shape[:-4], k, k)

    def _mode_gradients(self, U: Tensor, Vh: Tensor, pairs) -> Tensor:
        """``q_m = G V_m^T`` flattened a-major ``(..., n_cells, m, (d+1) d)`` for the modes
        ``V_m = U T_m V^T`` of :meth:`~.materials.Corotated.stiffness_terms`, from outer
        products of columns (no batched 3x3 matmul: slow in torch on CPU)."""
        g = self.rest.grads.to(U)
        # gw[..., e, a, b] = sum_j g[e, a, j] Vh[..., e, b, j]
        gw = (g[:, :, None, :] * Vh[..., :, None, :, :]).sum(-1)

        def outer(b: int, a: int) -> Tensor:      # G (U_a Vh_b)^T -> [x, i] = gw[x, b] U[i, a]
            return gw[..., :, b, None] * U[..., None, :, a]

        root_half = 1.0 / math.sqrt(2.0)
        modes = [(outer(k, j) * -root_half) + (outer(j, k) * root_half) for j, k in pairs]
        modes.append(sum(outer(b, b) for b in range(U.shape[-1])))
        q = torch.stack(modes, dim=-3)
        return q.reshape(*q.shape[:-2], -1)

    def _gram(self, like: Tensor) -> Tensor:
        """``(G G^T)_ab delta_ik`` per element ``(n_cells, d+1, d, d+1, d)`` (cached)."""
        key = (like.dtype, like.device)
        if getattr(self, "_gram_key", None) != key:
            g = self.rest.grads.to(like)
            eye = torch.eye(self.dim, dtype=like.dtype, device=like.device)
            self._gram_cache = torch.einsum("eaj,ebj,ik->eaibk", g, g, eye)
            self._gram_key = key
        return self._gram_cache

    def tangent_values(self, x: Tensor, E: Tensor, projected: bool = False) -> Tensor:
        """Contributions of ``dR/dx`` ``(F, n_contrib)``; ``(1, n_contrib)`` for ``linear``.

        ``projected=True``: each element's ``dP/dF`` is clamped to be positive
        semi-definite (a descent direction for Newton far from equilibrium); the
        default is the exact derivative that the adjoint needs.
        """
        if self.linear:
            x = self.rest.points.reshape(1, -1).to(x)       # the tangent is constant
        K = self.element_stiffness(x, E, projected)
        return K.reshape(K.shape[0], -1)

    def near_nullspace(self) -> Tensor:
        """Rigid-body modes at the rest positions, ``(n_dofs, 3)`` in 2-D (2 translations,
        1 rotation) or ``(n_dofs, 6)`` in 3-D (3 + 3): the near-nullspace an AMG
        preconditioner (the ``amg`` backend) aggregates with."""
        points = self.rest.points.detach().cpu().to(torch.float64)
        points = points - points.mean(dim=0)          # rotations about the centroid
        n, d = points.shape
        rotations = [(0, 1), (1, 2), (2, 0)] if d == 3 else [(0, 1)]
        modes = torch.zeros(n, d, d + len(rotations), dtype=torch.float64)
        for axis in range(d):
            modes[:, axis, axis] = 1.0
        for k, (a, b) in enumerate(rotations):      # rotation in the (a, b) plane
            modes[:, a, d + k] = -points[:, b]
            modes[:, b, d + k] = points[:, a]
        return modes.reshape(n * d, -1)

    def param_derivative(self, x: Tensor, E: Tensor) -> ElasticParamDerivative:
        """``dR/dE`` at ``x`` (``R`` is linear in ``E`` at fixed ``nu``)."""
        self.check_modulus(E)
        unit = torch.ones_like(E.detach())
        return ElasticParamDerivative(self.rest, self.element_forces(x.detach(), unit))

    def __repr__(self) -> str:
        return (f"SimplicialElasticity(d={self.dim}, cells={self.n_cells}, "
                f"vertices={self.n_vertices}, material={self.material.name}, nu={self.nu})")
