"""Elastodynamics ``M a = f_int(x; k) - C v + f_ext`` and two integrators behind one
interface (:func:`make_integrator`):

* ``torchdiffeq`` (:mod:`.explicit`): the first-order system through
  ``torchdiffeq.odeint_adjoint`` (adaptive ``dopri5``, fixed-step ``rk4`` ...), the
  physical parameters as its adjoint parameters; for non-stiff problems;
* ``implicit`` (:mod:`.implicit`): backward Euler or BDF2, every step an equilibrium solve
  through :class:`~torchfit.physics.Equilibrium` (its implicit-function adjoint, its
  factorisation counting), memory bounded by checkpointing.

Both take the physical parameter vector ``[k (n_field,), alpha, beta]`` and return the
positions of every dof at the output times, ``(K, n_dofs)``, differentiable in reverse
mode (``J^T w``) and forward mode (``J v``); ``jacobian(params, V)`` gives ``k``
directions at once.
"""
from __future__ import annotations

from typing import Any

from .errors import (DynamicsInputError, InvalidFieldError, NegativeDampingError,
                     NonFiniteStateError, UnstableStepError)
from .explicit import ADAPTIVE_METHODS, FIXED_METHODS, TorchdiffeqIntegrator
from .implicit import ImplicitIntegrator
from .system import DynamicSystem, KeyedMotion, SplineMotion, check_output_times

INTEGRATORS = ("torchdiffeq", "implicit")


def make_integrator(kind: str, system: DynamicSystem, output_times: Any, *, dt: float,
                    method: str = "dopri5", scheme: str = "bdf2", rtol: float = 1e-8,
                    atol: float = 1e-10, backend: str = "scipy", newton: Any = None,
                    checkpoint_every: int = 1,
                    trial_factor: float = 0.0) -> TorchdiffeqIntegrator | ImplicitIntegrator:
    """The integrator ``kind`` (``'torchdiffeq'`` or ``'implicit'``) of ``system``.

    ``dt`` is the implicit step and the fixed step of torchdiffeq's fixed-step methods;
    ``method``, ``rtol``, ``atol``, ``trial_factor`` are torchdiffeq's; ``scheme``, ``backend``, ``newton``,
    ``checkpoint_every`` the implicit integrator's.
    """
    if kind == "torchdiffeq":
        return TorchdiffeqIntegrator(system, output_times, method=method, rtol=rtol, atol=atol,
                                     step_size=dt if method in FIXED_METHODS else None,
                                     trial_factor=trial_factor)
    if kind == "implicit":
        return ImplicitIntegrator(system, output_times, dt, scheme=scheme, backend=backend,
                                  newton=newton, checkpoint_every=checkpoint_every)
    raise DynamicsInputError(f"unknown integrator {kind!r}; choose one of {', '.join(INTEGRATORS)}")


__all__ = ["ADAPTIVE_METHODS", "DynamicSystem", "DynamicsInputError", "FIXED_METHODS",
           "INTEGRATORS", "InvalidFieldError", "KeyedMotion", "NegativeDampingError",
           "NonFiniteStateError", "SplineMotion", "UnstableStepError", "check_output_times", "make_integrator"]
