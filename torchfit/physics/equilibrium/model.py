"""What a physics model provides to the equilibrium: the protocol and its optional extensions.

A model gives its residual ``R(x, params)`` ``(F, n_dofs)`` (net force, torch, vectorised
over elements and frames) and the contributions of its sparse tangent ``K = dR/dx`` on a
pattern built once per mesh. Optional extensions, detected once per model
(:class:`ModelExtensions`):

* ``tangent_values(x, params, projected=True)``: a positive semi-definite modification of
  the tangent for Newton's search direction far from equilibrium (the factorisation kept
  for the adjoint is always the exact ``dR/dx`` at ``x*``);
* ``param_derivative(x, params)``: an object with ``jvp(v) -> (F, n_dofs)`` (``dR/dparams
  v``) and ``vjp(w (F, n_dofs)) -> (n_params,)``, optionally ``matmul(V (n_params, k)) ->
  (F, n_dofs, k)`` (a new tensor) and ``matrix_entries()`` (a sparse ``(F * n_dofs,
  n_params)`` as rows, cols, values, shape); used instead of autograd of the residual;
* ``energy(x, params)`` ``(F,)`` of a symmetric model (``R = dEnergy/dx``): Newton's line
  search is then an Armijo search on the energy too; ``residual_and_energy(x, params)``
  gives both from one pass;
* ``frame_independent = True``: the residual of a frame depends on that frame's positions
  only (no per-frame loads), so the line search evaluates the frames still iterating alone.
"""
from __future__ import annotations

import dataclasses
import inspect
from typing import Any, Callable, Protocol

from torch import Tensor

from ...linalg import SparsePattern


class EquilibriumModel(Protocol):
    """What a physics model provides to :class:`~torchfit.physics.Equilibrium`.

    Attributes:
        n_dofs: number of scalar degrees of freedom per frame.
        tangent_pattern: ``n_dofs x n_dofs`` pattern of ``dR/dx``.
        linear: ``R`` is affine in ``x`` with a frame-independent tangent.
        symmetric: the tangent is symmetric (an energy Hessian).
    """

    n_dofs: int
    tangent_pattern: SparsePattern
    linear: bool
    symmetric: bool

    def residual(self, x: Tensor, params: Tensor) -> Tensor:
        """Net force ``(F, n_dofs)`` at positions ``x`` ``(F, n_dofs)``."""

    def tangent_values(self, x: Tensor, params: Tensor) -> Tensor:
        """``dR/dx`` contributions ``(F or 1, tangent_pattern.n_contrib)``.

        A model may accept a keyword ``projected: bool = False`` (see the module
        docstring); models without it are called without it.
        """


@dataclasses.dataclass(frozen=True)
class ModelExtensions:
    """The optional extensions a model offers (see the module docstring)."""

    accepts_projected: bool        # tangent_values(..., projected=True)
    has_param_derivative: bool     # param_derivative(x, params)
    has_energy: bool               # symmetric with energy(x, params): energy line search
    has_residual_and_energy: bool  # residual_and_energy(x, params): one pass for both
    frame_independent: bool        # a frame's residual depends on its positions only

    @classmethod
    def of(cls, model: EquilibriumModel) -> "ModelExtensions":
        return cls(
            accepts_projected=accepts_keyword(model.tangent_values, "projected"),
            has_param_derivative=callable(getattr(model, "param_derivative", None)),
            has_energy=bool(model.symmetric) and callable(getattr(model, "energy", None)),
            has_residual_and_energy=callable(getattr(model, "residual_and_energy", None)),
            frame_independent=bool(getattr(model, "frame_independent", False)))


def accepts_keyword(function: Callable[..., Any], name: str) -> bool:
    """Whether ``function`` takes a keyword argument ``name`` (or ``**kwargs``)."""
    try:
        parameters = inspect.signature(function).parameters
    except (TypeError, ValueError):  # pragma: no cover - builtins
        return False
    return name in parameters or any(p.kind is inspect.Parameter.VAR_KEYWORD
                                     for p in parameters.values())
