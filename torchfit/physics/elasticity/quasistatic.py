"""Quasistatic frames of an elastic body with prescribed (Dirichlet) vertices.

Each frame is an independent equilibrium: the Dirichlet vertices are placed where the
frame says, the free vertices are solved by Newton with line search (all frames at once
in the generic :class:`~torchfit.physics.Equilibrium`, one factorisation per frame and
iteration) and derivatives w.r.t. the per-element Young's modulus come from the implicit
adjoint (never by unrolling Newton).

Cold start: the linear-elastic solution of the frame's Dirichlet displacement at the
rest shape (one Newton step from rest, one factorisation shared by all frames); later
calls with the same Dirichlet data warm-start from the last solution (see
:class:`~torchfit.physics.Equilibrium`).
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from ..equilibrium import Equilibrium, NewtonOptions
from .fem import SimplicialElasticity

STARTS = ("linear", "rest")


class DirichletDataError(ValueError):
    """Per-frame Dirichlet data that do not match the Dirichlet set; names the frame."""


class QuasistaticElasticity:
    """Frames of quasistatic equilibrium of a :class:`SimplicialElasticity` model.

    Args:
        model: the elastic model (mesh, material, ``nu``).
        dirichlet_vertices: vertices whose positions every frame prescribes (any order;
            per-frame positions are given in this order).
        backend: linear-solve backend (``'scipy'`` or ``'cg'``).
        newton: Newton settings.
        start: cold start of Newton: ``'linear'`` (linear-elastic solution from rest,
            the default) or ``'rest'`` (rest positions with the Dirichlet vertices moved).
        warm_start: start from the last solution when the Dirichlet data are unchanged.
    """

    def __init__(self, model: SimplicialElasticity, dirichlet_vertices: Sequence[int] | Tensor,
                 backend: str = "scipy", newton: NewtonOptions | None = None,
                 start: str = "linear", warm_start: bool = True) -> None:
        vertices = np.asarray(torch.as_tensor(dirichlet_vertices).cpu(), dtype=np.int64).reshape(-1)
        if vertices.size == 0:
            raise DirichletDataError("the Dirichlet set is empty: an elastic body with no "
                                     "prescribed vertex can move freely (singular system)")
        if vertices.min() < 0 or vertices.max() >= model.n_vertices:
            raise DirichletDataError(f"Dirichlet vertex out of range [0, {model.n_vertices})")
        if np.unique(vertices).size != vertices.size:
            raise DirichletDataError("the Dirichlet set lists a vertex twice")
        if start not in STARTS:
            raise ValueError(f"unknown start {start!r}; choose one of {STARTS}")
        self.model = model
        self.dim = model.dim
        self.dirichlet_vertices = torch.as_tensor(vertices)
        # Equilibrium sorts its fixed dofs; vertex-major dofs of sorted vertices are sorted.
        self._order = torch.as_tensor(np.argsort(vertices, kind="stable"))
        sorted_vertices = vertices[self._order.numpy()]
        fixed = (sorted_vertices[:, None] * self.dim + np.arange(self.dim)).reshape(-1)
        self.equilibrium = Equilibrium(model, torch.as_tensor(fixed), backend=backend,
                                       newton=newton, warm_start=warm_start,
                                       linear_refinement=1 if model.linear else 0)
        self.start = start
        free = np.setdiff1d(np.arange(model.n_vertices), vertices)
        self.free_vertices = torch.as_tensor(free)

    @property
    def n_dirichlet(self) -> int:
        return int(self.dirichlet_vertices.numel())

    def dirichlet_values(self, positions: Tensor | Sequence[Tensor]) -> Tensor:
        """Equilibrium's ``(F, n_fixed)`` values of per-frame Dirichlet positions.

        Args:
            positions: ``(F, n_dirichlet, d)`` or a sequence of ``(n_dirichlet, d)``, in the
                order of ``dirichlet_vertices``.
        Raises:
            DirichletDataError: naming the frame whose data do not fit the Dirichlet set or
                are not finite.
        """
        expected = (self.n_dirichlet, self.dim)
        if isinstance(positions, Tensor):
            if positions.dim() != 3 or tuple(positions.shape[1:]) != expected:
                raise DirichletDataError(
                    f"Dirichlet data must have shape (frames, {expected[0]}, {expected[1]}) "
                    f"(one position per Dirichlet vertex and frame), got {tuple(positions.shape)}")
            frames = positions
        else:
            frames_list = list(positions)
            if not frames_list:
                raise DirichletDataError("no frame of Dirichlet data given")
            for f, p in enumerate(frames_list):
                shape = tuple(torch.as_tensor(p).shape)
                if shape != expected:
                    raise DirichletDataError(
                        f"frame {f}: Dirichlet data of shape {shape} do not match the "
                        f"Dirichlet set of {expected[0]} vertices in {expected[1]}-D "
                        f"(expected {expected})")
            frames = torch.stack([torch.as_tensor(p) for p in frames_list])
        if frames.shape[0] == 0:
            raise DirichletDataError("no frame of Dirichlet data given")
        bad = ~torch.isfinite(frames.detach())
        if bool(bad.any()):
            f, v, _ = torch.nonzero(bad)[0].tolist()
            raise DirichletDataError(f"frame {f}: Dirichlet position of vertex "
                                     f"{int(self.dirichlet_vertices[v])} is not finite")
        ordered = frames[:, self._order.to(frames.device), :]
        return ordered.reshape(frames.shape[0], -1)

    def rest_dofs(self, like: Tensor) -> Tensor:
        return self.model.rest.points.reshape(1, -1).to(like)

    def cold_start(self, E: Tensor, values: Tensor) -> Tensor:
        """The cold start ``(F, n_dofs)`` for Dirichlet values ``values``."""
        if self.start == "linear":
            return self.equilibrium.linearized_start(E, values, self.rest_dofs(values))
        return self._rest_start(values)

    def _rest_start(self, values: Tensor) -> Tensor:
        """Rest positions with the Dirichlet dofs moved to ``values``, ``(F, n_dofs)``."""
        x = self.rest_dofs(values).expand(values.shape[0], -1).clone()
        x[:, self.equilibrium.fixed_dofs.to(x.device)] = values.detach()
        return x

    def __call__(self, E: Tensor, positions: Tensor | Sequence[Tensor],
                 x_init: Tensor | None = None) -> Tensor:
        """Positions ``(F, n_vertices, d)`` of every vertex in every frame.

        Args:
            E: ``(n_cells,)`` Young's modulus per element (differentiable).
            positions: per-frame Dirichlet positions (see :meth:`dirichlet_values`).
            x_init: optional cold start ``(F, n_vertices, d)``.
        """
        self.model.check_modulus(E)
        values = self.dirichlet_values(positions).to(E)
        x = self.equilibrium(E, values, self._start(E, values, x_init))
        return x.reshape(values.shape[0], self.model.n_vertices, self.dim)

    def linearization(self, E: Tensor, positions: Tensor | Sequence[Tensor],
                      x_init: Tensor | None = None):
        """The equilibrium of every frame at ``E`` with explicit derivative products
        (:class:`~torchfit.physics.equilibrium.EquilibriumLinearization`; ``x`` is
        ``(F, n_dofs)``, the free-dof products are ``(n_free, F)``). Solved exactly as
        :meth:`__call__` solves (or taken from its cache); no autograd graph."""
        self.model.check_modulus(E)
        values = self.dirichlet_values(positions).to(E)
        return self.equilibrium.linearization(E.detach(), values.detach(),
                                              self._start(E, values, x_init))

    def jacobian(self, E: Tensor, positions: Tensor | Sequence[Tensor], directions: Tensor,
                 x_init: Tensor | None = None, observe: Tensor | None = None) -> Tensor:
        """``(dx/dE) directions``: ``(F, n_vertices, d, k)`` for ``directions`` ``(n_cells, k)``;
        with ``observe`` (sparse ``(n_rows, n_vertices d)``, on the flat dofs) the observed
        columns ``(F, n_rows, k)`` instead, applied frame by frame as they are solved.

        At the solution :meth:`__call__` gives for the same ``E`` and ``positions`` (cached,
        else solved the same way); one solve with ``k`` right-hand sides per frame, no
        factorisation (see :meth:`~torchfit.physics.Equilibrium.jacobian`). Dirichlet
        vertices do not move (zero rows). No autograd graph.
        """
        self.model.check_modulus(E)
        values = self.dirichlet_values(positions).to(E)
        dx = self.equilibrium.jacobian(E.detach(), values.detach(), directions,
                                       self._start(E, values, x_init), observe=observe)
        if observe is not None:
            return dx
        return dx.reshape(values.shape[0], self.model.n_vertices, self.dim, dx.shape[-1])

    def _start(self, E: Tensor, values: Tensor,
               x_init: Tensor | None) -> Tensor | Callable[[], Tensor]:
        """The cold start handed to the equilibrium (used only when it must solve)."""
        if x_init is not None:
            return x_init.reshape(values.shape[0], -1)
        if self.model.linear:
            # one linear solve from the rest shape: its round-off scales with the
            # displacement, not with the positions (as it would from zero)
            return self._rest_start(values.detach())

        def start() -> Tensor:
            return self.cold_start(E.detach(), values.detach())

        return start

    @property
    def last_newton_iterations(self) -> list[int]:
        return self.equilibrium.last_newton_iterations

    def clear_cache(self) -> None:
        self.equilibrium.clear_cache()
