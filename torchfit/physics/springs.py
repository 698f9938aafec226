"""Linear springs between scalar node values: a weighted graph Laplacian with loads.

Two problems use it: the hanging chain of docs/problems.md ``spring1d`` (positions along gravity)
and the 2-D Poisson grid ``poisson2d`` (``div(k grad x) = 0`` by finite differences: one
spring per grid edge, ``k`` its conductance, rest length 0, each displacement component a
frame). Node values are scalars. Spring ``e`` joins nodes ``a_e < b_e``
with stiffness ``k_e`` (force per unit length) and rest length ``L_e``; its tension is
``T_e = k_e (x_b - x_a - L_e)``. The residual (net force, positive along gravity) is

    R_j = sum_{e: b_e = j} T_e - sum_{e: a_e = j} T_e - f_ext_j,

so ``R = 0`` is equilibrium and ``dR/dx`` is the SPD stiffness matrix. The model is
linear in ``x`` with a frame-independent tangent: one factorisation serves every load
case. Everything is vectorised over springs and frames.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..linalg import SparsePattern


class ScalarSpringNetwork:
    """Springs between scalar node values with per-frame external nodal forces.

    Args:
        edges: ``(n_springs, 2)`` node pairs ``(a, b)``.
        rest_lengths: ``(n_springs,)`` rest lengths (length units).
        external_forces: ``(F, n_nodes)`` external force on every node in every frame
            (gravity times mass plus applied loads; force units, along gravity).
    """

    linear = True
    symmetric = True

    def __init__(self, edges: Tensor, rest_lengths: Tensor, external_forces: Tensor) -> None:
        if edges.dim() != 2 or edges.shape[1] != 2:
            raise ValueError(f"edges must be (n_springs, 2), got {tuple(edges.shape)}")
        if rest_lengths.shape != (edges.shape[0],):
            raise ValueError(f"rest_lengths must be ({edges.shape[0]},), got "
                             f"{tuple(rest_lengths.shape)}")
        self.edges = edges.long()
        self.rest_lengths = rest_lengths
        self.external_forces = external_forces
        self.n_dofs = int(external_forces.shape[1])
        self.n_springs = int(edges.shape[0])
        a, b = self.edges[:, 0], self.edges[:, 1]
        # Local 2x2 stiffness [[k, -k], [-k, k]] of every spring, flattened row-major.
        rows = torch.stack([a, a, b, b], dim=1).reshape(-1)
        cols = torch.stack([a, b, a, b], dim=1).reshape(-1)
        self.tangent_pattern = SparsePattern(rows, cols, (self.n_dofs, self.n_dofs))

    def tensions(self, x: Tensor, stiffness: Tensor) -> Tensor:
        """Spring tensions ``(F, n_springs)`` (force units)."""
        a, b = self.edges[:, 0], self.edges[:, 1]
        return stiffness * (x[:, b] - x[:, a] - self.rest_lengths)

    def residual(self, x: Tensor, stiffness: Tensor) -> Tensor:
        """Net force ``(F, n_nodes)`` for positions ``(F, n_nodes)``, stiffness ``(n_springs,)``."""
        self._check(stiffness)
        tension = self.tensions(x, stiffness)
        a, b = self.edges[:, 0], self.edges[:, 1]
        internal = x.new_zeros(x.shape).index_add(1, b, tension).index_add(1, a, -tension)
        return internal - self.external_forces.to(x)

    def tangent_values(self, x: Tensor, stiffness: Tensor) -> Tensor:
        """``dR/dx`` contributions ``(1, 4 n_springs)``: shared by all frames."""
        self._check(stiffness)
        return torch.stack([stiffness, -stiffness, -stiffness, stiffness], dim=1).reshape(1, -1)

    def param_derivative(self, x: Tensor, stiffness: Tensor) -> "SpringParamDerivative":
        """``dR/dk`` at positions ``x`` ``(F, n_nodes)`` as products (``R`` is linear in ``k``).

        Used by :class:`~torchfit.physics.Equilibrium` for its backward and jvp: an
        explicit scatter instead of (double) autograd through :meth:`residual`.
        """
        self._check(stiffness)
        return SpringParamDerivative(self, x.detach())

    def energy(self, x: Tensor, stiffness: Tensor) -> Tensor:
        """Total potential energy per frame ``(F,)``: springs minus work of external forces."""
        stretch = x[:, self.edges[:, 1]] - x[:, self.edges[:, 0]] - self.rest_lengths
        return 0.5 * (stiffness * stretch ** 2).sum(dim=1) - (self.external_forces.to(x) * x).sum(dim=1)

    def _check(self, stiffness: Tensor) -> None:
        if stiffness.shape != (self.n_springs,):
            raise ValueError(f"stiffness must have shape ({self.n_springs},), got "
                             f"{tuple(stiffness.shape)}")


class SpringParamDerivative:
    """``dR/dk`` of :class:`ScalarSpringNetwork` at fixed positions.

    Column ``e`` is the tension of spring ``e`` at unit stiffness (its stretch
    ``x_b - x_a - L_e``, per frame) pushed onto node ``b`` and pulled from node ``a``.
    """

    def __init__(self, springs: ScalarSpringNetwork, x: Tensor) -> None:
        self._a = springs.edges[:, 0].to(x.device)
        self._b = springs.edges[:, 1].to(x.device)
        self._n_dofs = springs.n_dofs
        self.stretch = x[:, self._b] - x[:, self._a] - springs.rest_lengths.to(x)   # (F, n_springs)

    def jvp(self, v: Tensor) -> Tensor:
        """``(dR/dk) v`` ``(F, n_nodes)`` for ``v`` ``(n_springs,)``."""
        tension = self.stretch * v.to(self.stretch)
        out = tension.new_zeros(tension.shape[0], self._n_dofs)
        return out.index_add_(1, self._b, tension).index_add_(1, self._a, -tension)

    def matmul(self, V: Tensor) -> Tensor:
        """``(dR/dk) V`` of every frame, ``(F, n_nodes, k)``, for ``V`` ``(n_springs, k)``."""
        tension = self.stretch[:, :, None] * V.to(self.stretch)[None]      # (F, n_springs, k)
        out = tension.new_zeros(tension.shape[0], self._n_dofs, tension.shape[2])
        return out.index_add_(1, self._b, tension).index_add_(1, self._a, -tension)

    def matrix_entries(self) -> tuple[Tensor, Tensor, Tensor, tuple[int, int]]:
        """``dR/dk`` as sparse entries ``(rows, cols, values, shape)`` of a
        ``(F * n_nodes, n_springs)`` matrix, row ``f * n_nodes + node``: ``+stretch`` at node
        ``b``, ``-stretch`` at node ``a``. Rows and columns are the same for every
        solution with ``F`` frames (:class:`~torchfit.physics.Equilibrium` builds its
        sparse layout once and refills the values)."""
        n_frames, n_springs = self.stretch.shape
        offset = (torch.arange(n_frames, device=self._a.device) * self._n_dofs)[:, None]
        rows = torch.cat([(offset + self._b[None]).reshape(-1), (offset + self._a[None]).reshape(-1)])
        springs = torch.arange(n_springs, device=self._a.device).repeat(2 * n_frames)
        values = torch.cat([self.stretch.reshape(-1), -self.stretch.reshape(-1)])
        return rows, springs, values, (n_frames * self._n_dofs, n_springs)

    def vjp(self, w: Tensor) -> Tensor:
        """``(dR/dk)^T w`` ``(n_springs,)`` for ``w`` ``(F, n_nodes)`` (summed over frames)."""
        w = w.to(self.stretch)
        return (self.stretch * (w[:, self._b] - w[:, self._a])).sum(dim=0)
