"""Physics: energies, forces, tangents and the differentiable equilibrium solve."""
from .equilibrium import (Equilibrium, EquilibriumModel, NewtonConvergenceError, NewtonOptions,
                          newton_progress)
from .springs import ScalarSpringNetwork

__all__ = ["Equilibrium", "EquilibriumModel", "NewtonConvergenceError", "NewtonOptions",
           "ScalarSpringNetwork", "newton_progress"]
