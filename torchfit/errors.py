"""Exceptions shared by the layers (kept here so that no layer imports another for them)."""
from __future__ import annotations


class SimulationError(RuntimeError):
    """The forward simulation has no valid answer at these parameters.

    Raised by the physics and linear-algebra layers (Newton did not converge, a singular
    system, an infeasible material such as a non-positive Young's modulus). Called
    directly, it reports the problem; inside a fit, solvers treat it at a *trial* point
    as a failed step (Levenberg-Marquardt rejects the step, Gauss-Newton's line search
    shortens it) instead of stopping the run.
    """


class ConfigurationError(ValueError):
    """A setting is invalid; the message is one line naming the setting and what is allowed.

    The problem, solver and run layers raise subclasses of it; applications report it
    without a traceback and run nothing.
    """
