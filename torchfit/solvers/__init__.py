"""Solvers: they see a residual with ``J v`` / ``J^T w`` products and nothing else.

This package imports nothing from ``physics``, ``mesh`` or ``problems``.
"""
from .gauss_newton import GaussNewtonConfig, SolverConfigError, gauss_newton
from .levenberg_marquardt import LevenbergMarquardtConfig, levenberg_marquardt
from ..records import Callback, IterationRecord, SolveResult
from ..residual import Linearization, ResidualFunction
from .split_bregman import GroupTV, SplitBregmanConfig, check_difference_operator, split_bregman

#: config name -> (config dataclass, solver function)
SOLVERS = {
    "gauss_newton": (GaussNewtonConfig, gauss_newton),
    "levenberg_marquardt": (LevenbergMarquardtConfig, levenberg_marquardt),
    "split_bregman": (SplitBregmanConfig, split_bregman),
}

__all__ = ["Callback", "GaussNewtonConfig", "GroupTV", "IterationRecord",
           "LevenbergMarquardtConfig", "Linearization", "ResidualFunction", "SOLVERS",
           "SolveResult", "SolverConfigError", "SplitBregmanConfig", "check_difference_operator",
           "gauss_newton", "levenberg_marquardt", "split_bregman"]
