"""Solvers: they see a residual with ``J v`` / ``J^T w`` products and nothing else.

This package imports nothing from ``physics``, ``mesh`` or ``problems``. Every solver is
a :class:`Solver` (one outer loop, shared stop rules, config validation, exact resume
through ``state_dict``); :data:`SOLVERS` maps a config name to its
:class:`SolverEntry`::

    entry = SOLVERS[name]
    config = entry.config_class(**section)
    config.validate()
    D = param.difference_operator() if entry.needs_difference_operator(config) else None
    # (or, where entry.takes_difference_operator(config), the parameterisation's D if any)
    groups = param.difference_groups() if entry.uses_groups(config) else None
    result = entry.solver_class(config, D=D, groups=groups).solve(residual, theta0, callbacks)
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable

from ..records import Callback, IterationRecord, SolveResult
from ..residual import Linearization, ResidualFunction
from .base import Solver, SolverConfig, SolverConfigError
from .gauss_newton import GaussNewton, GaussNewtonConfig, gauss_newton
from .levenberg_marquardt import LevenbergMarquardt, LevenbergMarquardtConfig, levenberg_marquardt
from .split_bregman import SplitBregman, SplitBregmanConfig, split_bregman
from .stacked import CachedResidual, LinearResidual, StackedResidual
from .total_variation import GroupTV, check_difference_operator


@dataclasses.dataclass(frozen=True)
class SolverEntry:
    """A registered solver.

    Attributes:
        config_class: its :class:`SolverConfig` dataclass (also the Hydra schema).
        solver_class: its :class:`Solver`.
        needs_difference_operator: ``config -> bool``: the solver must get the
            parameterisation's ``D``.
        uses_groups: ``config -> bool``: the solver uses the row groups of ``D``
            (``parameterization.difference_groups()``).
    """

    config_class: type[SolverConfig]
    solver_class: type[Solver]
    needs_difference_operator: Callable[[Any], bool]
    uses_groups: Callable[[Any], bool]
    # ``config -> bool``: the solver uses ``D`` where the parameterisation has one and runs
    # without it otherwise (Gauss-Newton's ``preconditioner=auto``)
    takes_difference_operator: Callable[[Any], bool] = lambda config: False


def _difference_preconditioned(config: Any) -> bool:
    return config.preconditioner == "difference"


def _auto_preconditioned(config: Any) -> bool:
    return config.preconditioner == "auto"


def _always(config: Any) -> bool:
    return True


def _never(config: Any) -> bool:
    return False


def _isotropic(config: Any) -> bool:
    return bool(config.isotropic)


#: config name -> :class:`SolverEntry`
SOLVERS: dict[str, SolverEntry] = {
    "gauss_newton": SolverEntry(GaussNewtonConfig, GaussNewton, _difference_preconditioned,
                                _never, _auto_preconditioned),
    "levenberg_marquardt": SolverEntry(LevenbergMarquardtConfig, LevenbergMarquardt,
                                       _difference_preconditioned, _never),
    "split_bregman": SolverEntry(SplitBregmanConfig, SplitBregman, _always, _isotropic),
}

__all__ = ["CachedResidual", "Callback", "GaussNewton", "GaussNewtonConfig", "GroupTV",
           "IterationRecord", "LevenbergMarquardt", "LevenbergMarquardtConfig",
           "LinearResidual", "Linearization", "ResidualFunction", "SOLVERS", "SolveResult",
           "Solver", "SolverConfig", "SolverConfigError", "SolverEntry", "SplitBregman",
           "SplitBregmanConfig", "StackedResidual", "check_difference_operator",
           "gauss_newton", "levenberg_marquardt", "split_bregman"]
