"""Errors of the dynamics layer, each a subclass of a class of :mod:`torchfit.errors`.

Input that is wrong before anything is integrated (output times, density, step size) is a
:class:`~torchfit.errors.ConfigurationError`; what goes wrong while integrating at given
parameters (a negative damping coefficient reached by an identity parameterisation, an
explicit integrator that blows up, a state that is not finite) is a
:class:`~torchfit.errors.SimulationError`, which solvers treat as a failed step at a
trial point. Every message is one line.
"""
from __future__ import annotations

from ...errors import ConfigurationError, SimulationError


class DynamicsInputError(ConfigurationError):
    """Invalid dynamics input: output times that do not increase, a density or step size
    that is not positive, an unknown integrator or method."""

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))


class NegativeDampingError(SimulationError):
    """A Rayleigh damping coefficient (``alpha`` or ``beta``) is negative or not finite."""


class InvalidFieldError(SimulationError):
    """A stiffness field value that is not positive and finite (names the element)."""


class UnstableStepError(SimulationError):
    """An explicit integrator blew up (step above its stability limit) or its adaptive
    step collapsed (the message names the integrator to use instead), or an implicit step's
    Newton did not converge (the message names the step, its time and length: take shorter
    steps). ``time`` (s) and ``step`` where known."""

    def __init__(self, message: str, time: float | None = None, step: int | None = None) -> None:
        super().__init__(message)
        self.time, self.step = time, step


class NonFiniteStateError(SimulationError):
    """The state became NaN or infinite; the message names the time and the vertex."""
