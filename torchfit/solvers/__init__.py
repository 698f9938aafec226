"""Solvers: they see a residual with ``J v`` / ``J^T w`` products and nothing else.

This package imports nothing from ``physics``, ``mesh`` or ``problems``. Every solver is
a :class:`Solver` (one outer loop, shared stop rules, config validation, exact resume
through ``state_dict``) with a :class:`SolverConfig` dataclass (also its Hydra schema);
:data:`SOLVERS` maps a config name to its :class:`SolverEntry`, and :func:`build` makes
the solver of a config with what the parameterisation offers::

    solver = build(config, difference_operator=param.difference_operator,
                   difference_groups=param.difference_groups)
    result = solver.solve(residual, theta0, callbacks)     # a SolveResult

or, directly, ``gauss_newton(residual, theta0, config, callbacks, D=...)`` and its kin.
Each solver emits one :class:`IterationRecord` per outer iteration to every callback;
:class:`SolveResult.stop_reason <SolveResult>` is a :class:`StopReason`.
"""
from __future__ import annotations

from ..records import Callback, IterationRecord, SolveResult, StopReason
from ..residual import ResidualFunction
from .base import Need, Needs, Solver, SolverConfig, SolverConfigError, UnsimulatedStart
from .gauss_newton import GaussNewton, GaussNewtonConfig, gauss_newton
from .levenberg_marquardt import LevenbergMarquardt, LevenbergMarquardtConfig, levenberg_marquardt
from .registry import SOLVERS, SolverEntry, build
from .split_bregman import SplitBregman, SplitBregmanConfig, split_bregman
from .total_variation import GroupTV

__all__ = ["Callback", "GaussNewton", "GaussNewtonConfig", "GroupTV", "IterationRecord",
           "LevenbergMarquardt", "LevenbergMarquardtConfig", "Need", "Needs",
           "ResidualFunction", "SOLVERS", "SolveResult", "Solver", "SolverConfig",
           "SolverConfigError", "SolverEntry", "SplitBregman", "SplitBregmanConfig",
           "StopReason", "UnsimulatedStart", "build", "gauss_newton", "levenberg_marquardt",
           "split_bregman"]
