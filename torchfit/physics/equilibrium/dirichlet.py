"""The Dirichlet reduction: the free/fixed split of the dofs and the reduced system to solve.

A model's residual and tangent are restricted to the free dofs, and that reduced system is
factorised and solved. Dirichlet dofs are prescribed per frame (``fixed_values``
``(F, n_fixed)``, ordered as the sorted ``fixed_dofs``). Full states are ``(F, n_dofs)``; free
vectors ``(F, n_free)`` in the order of ``free_dofs``. The free-free tangent pattern and the
CSR slots it takes in the model's pattern are built once. A factor list holds one shared
factor (a tangent that is the same for every frame) or one factor per frame.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ...linalg import Backend, Factor, get_backend
from .model import EquilibriumModel, ModelExtensions


class DirichletReduction:
    """The free/fixed split of ``model``'s dofs and the reduced (free-free) system.

    Args:
        model: the physics (see :class:`~.model.EquilibriumModel`); its optional
            extensions are detected once (``extensions``).
        fixed_dofs: ``(n_fixed,)`` indices of Dirichlet dofs (must not be empty unless
            ``allow_no_dirichlet``: a pure-traction elastic problem is singular).
        backend: linear-solve backend (name or object) of the reduced tangent.
    """

    def __init__(self, model: EquilibriumModel, fixed_dofs: Tensor, backend: str | Backend,
                 allow_no_dirichlet: bool = False) -> None:
        fixed = torch.as_tensor(fixed_dofs, dtype=torch.long).reshape(-1)
        if fixed.numel() == 0 and not allow_no_dirichlet:
            raise ValueError("the system has no Dirichlet (fixed) degree of freedom, so its "
                             "stiffness matrix is singular; fix at least one node")
        if fixed.numel() and (fixed.min() < 0 or fixed.max() >= model.n_dofs):
            raise ValueError(f"fixed dofs out of range [0, {model.n_dofs})")
        if torch.unique(fixed).numel() != fixed.numel():
            raise ValueError("fixed dofs contain duplicates")
        self.model = model
        self.fixed_dofs = torch.sort(fixed).values
        is_free = torch.ones(model.n_dofs, dtype=torch.bool)
        is_free[self.fixed_dofs] = False
        self.free_dofs = torch.nonzero(is_free).reshape(-1)
        # position of every dof among the free ones (-1: Dirichlet)
        self.free_positions = torch.full((model.n_dofs,), -1, dtype=torch.long)
        self.free_positions[self.free_dofs] = torch.arange(self.free_dofs.numel())
        if self.free_dofs.numel() == 0:
            raise ValueError("every degree of freedom is fixed; nothing to solve")
        # Reduced (free-free) tangent pattern and the slots it takes, built once per model
        # pattern (a contact term's union pattern grows when new pairs touch: free_pattern)
        self._pattern_of_free = None
        self.extensions = ModelExtensions.of(model)
        self.use_backend(backend)

    def use_backend(self, backend: str | Backend) -> None:
        """Factorise the reduced tangent with ``backend`` (a name or an object, e.g. a
        configured :class:`~torchfit.linalg.CudssBackend`) from now on."""
        self.backend = get_backend(backend)
        # an AMG backend aggregates with the model's near-nullspace (rigid-body modes)
        modes, register = (getattr(self.model, "near_nullspace", None),
                           getattr(self.backend, "set_near_nullspace", None))
        if callable(modes) and callable(register):
            register(self.free_pattern, modes()[self.free_dofs])

    @property
    def free_pattern(self):
        """The free-free pattern of the model's current tangent pattern."""
        return self._free_submatrix()[0]

    @property
    def free_slots(self) -> Tensor:
        """The slots of :attr:`free_pattern`'s entries in the model's pattern."""
        return self._free_submatrix()[1]

    def _free_submatrix(self):
        pattern = self.model.tangent_pattern
        if self._pattern_of_free is not pattern:
            self._free = pattern.submatrix(self.free_dofs, self.free_dofs)
            self._pattern_of_free = pattern
        return self._free

    @property
    def n_fixed(self) -> int:
        return int(self.fixed_dofs.numel())

    # -- checks of the caller's tensors ---------------------------------------------------
    def check_fixed_values(self, fixed_values: Tensor) -> None:
        """``fixed_values`` must be ``(F, n_fixed)``."""
        if fixed_values.dim() != 2 or fixed_values.shape[1] != self.n_fixed:
            raise ValueError(f"Dirichlet values must have shape (frames, {self.n_fixed}), got "
                             f"{tuple(fixed_values.shape)}")

    def check_finite(self, fixed_values: Tensor) -> None:
        """Every Dirichlet value must be finite (the message names frame and dof)."""
        if not torch.isfinite(fixed_values).all():
            bad = torch.nonzero(~torch.isfinite(fixed_values))[0].tolist()
            raise ValueError(f"Dirichlet value of frame {bad[0]}, fixed dof "
                             f"{int(self.fixed_dofs[bad[1]])} is NaN or infinite")

    def check_x_init(self, x_init: Tensor, n_frames: int) -> None:
        if x_init.shape != (n_frames, self.model.n_dofs):
            raise ValueError(f"x_init must have shape {(n_frames, self.model.n_dofs)}, "
                             f"got {tuple(x_init.shape)}")

    def free_position(self, dofs: Tensor) -> Tensor:
        """Rows of ``dofs`` among the free dofs; a Dirichlet dof is an error."""
        positions = self.free_positions[torch.as_tensor(dofs, dtype=torch.long).cpu()]
        if bool((positions < 0).any()):
            raise ValueError("a Dirichlet dof has no free position (its derivative is 0)")
        return positions

    # -- restriction and lifting ------------------------------------------------------------
    def full(self, x_free: Tensor, fixed_values: Tensor) -> Tensor:
        """Full states ``(F, n_dofs)`` of free values ``(F, n_free)`` and Dirichlet values."""
        x = x_free.new_zeros(x_free.shape[0], self.model.n_dofs)
        x = x.index_copy(1, self.free_dofs.to(x.device), x_free)
        return x.index_copy(1, self.fixed_dofs.to(x.device), fixed_values)

    def free_residual(self, x: Tensor, params: Tensor) -> Tensor:
        """The model's residual on the free dofs, ``(F, n_free)``."""
        return self.model.residual(x, params)[:, self.free_dofs.to(x.device)]

    def tangent(self, x: Tensor, params: Tensor, projected: bool = False) -> Tensor:
        """Tangent contributions ``(F or 1, n_contrib)`` (exact unless ``projected``)."""
        if projected and self.extensions.accepts_projected:
            return self.model.tangent_values(x, params, projected=True)
        return self.model.tangent_values(x, params)

    def free_values(self, contributions: Tensor) -> Tensor:
        """CSR values of the free-free tangent, ``(F or 1, free_pattern.nnz)``."""
        slots = self.free_slots.to(contributions.device)
        return self.model.tangent_pattern.assemble(contributions)[..., slots]

    # -- the reduced system -----------------------------------------------------------------
    def factorize_values(self, values: Tensor) -> Factor:
        """One factor of free-free tangent values ``(free_pattern.nnz,)``."""
        return self.backend.factorize(self.free_pattern, values, self.model.symmetric)

    def factorize(self, x: Tensor, params: Tensor) -> list[Factor]:
        """Factors of the exact tangent: one shared or one per frame."""
        values = self.free_values(self.tangent(x, params))
        return [self.backend.factorize(self.free_pattern, v, self.model.symmetric) for v in values]

    @staticmethod
    def solve(factors: list[Factor], rhs: Tensor, transpose: bool = False) -> Tensor:
        """Solve per frame; ``rhs`` is ``(F, n_free)``. One shared factor takes all frames."""
        if len(factors) == 1:
            return factors[0].solve(rhs.T.contiguous(), transpose=transpose).to(rhs.device).T
        return torch.stack([f.solve(r, transpose=transpose).to(rhs.device)
                            for f, r in zip(factors, rhs)])
