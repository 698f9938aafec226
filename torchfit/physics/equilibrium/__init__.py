"""The generic differentiable equilibrium ``x*(params)`` with ``R(x*, params) = 0``.

A physics model supplies its residual and sparse tangent (:mod:`.model`);
:class:`Equilibrium` (:mod:`.equilibrium`) handles its Dirichlet dofs (:mod:`.dirichlet`),
solves the free ones by Newton (:mod:`.newton`), keeps solutions with their factors and
picks warm starts (:mod:`.cache`), differentiates by the implicit function theorem
(:mod:`.adjoint`: backward solves ``K^T lam = g``, jvp ``K dx = -(dR/dparams) v``; Newton
is never unrolled) and gives explicit products and whole Jacobians without autograd
(:mod:`.linearization`). Measured costs and the history of these choices:
``docs/notes/equilibrium.md``.
"""
from .equilibrium import Equilibrium
from .linearization import EquilibriumLinearization
from .model import EquilibriumModel
from .newton import NewtonConvergenceError, NewtonOptions, TrialBudgetExceeded, newton_progress

__all__ = ["Equilibrium", "EquilibriumLinearization", "EquilibriumModel",
           "NewtonConvergenceError", "NewtonOptions", "TrialBudgetExceeded", "newton_progress"]
