"""The solver of a run, from a name, a settings mapping or a config object.

The solvers' registry (:func:`torchfit.solvers.build`) asks the problem's parameterisation
for what the settings need (the difference operator ``D``, its TV groups).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping

from ..problems import InverseProblem
from ..solvers import SOLVERS, Solver, SolverConfig, build
from .options import FitConfigError


def solver_config(section: Mapping[str, Any] | SolverConfig | str) -> SolverConfig:
    """A validated solver config from a name, a mapping (``{'name': ..., settings}``) or a
    config object; :class:`~torchfit.solvers.SolverConfigError` names a bad setting."""
    if isinstance(section, SolverConfig):
        config = section
    else:
        values = {"name": section} if isinstance(section, str) else dict(section)
        name = values.get("name")
        if name not in SOLVERS:
            raise FitConfigError(f"solver={name!r} is not a solver; choose one of {sorted(SOLVERS)}")
        config_class = SOLVERS[name].config_class
        fields = {f.name for f in dataclasses.fields(config_class)}
        unknown = sorted(set(values) - fields)
        if unknown:
            raise FitConfigError(f"unknown setting(s) {['solver.' + u for u in unknown]} for "
                                 f"solver={name}; it has {sorted(fields - {'name'})}")
        config = config_class(**values)
    config.validate()
    return config


def build_solver(problem: InverseProblem, solver: Solver | SolverConfig | Mapping[str, Any] | str
                 ) -> Solver:
    """The solver for ``problem``: a :class:`~torchfit.solvers.Solver` as it is, or one built
    from a name/config with what its registry entry says it needs from the problem's
    parameterisation (the difference operator ``D`` and its TV groups)."""
    if isinstance(solver, Solver):
        built = solver
    else:
        config = solver_config(solver)
        param = problem.parameterization
        built = build(config, difference_operator=param.difference_operator,
                      difference_groups=param.difference_groups,
                      offered_by=f"{problem.name}'s ({type(param).__name__})")
    bounds = problem.theta_bounds()
    if bounds is not None and built.bounds is None:   # the problem's bounds (solvers/bounds.py)
        built.set_bounds(*bounds)
    return built


def check_start_in_bounds(solver: Solver, start: Any, init: Any) -> None:
    """Refuse a start (``init=``) outside the solver's bounds before anything is written
    (:class:`FitConfigError`, one line naming ``init`` and what to do)."""
    if solver.bounds is None or start is None:
        return
    outside = solver.bounds.outside(start)
    if outside is not None:
        raise FitConfigError(
            f"init={init}: parameter {outside} ({float(start[outside]):.4g}) lies outside the "
            f"problem's bounds on theta [{float(solver.bounds.lower[outside]):.4g}, "
            f"{float(solver.bounds.upper[outside]):.4g}] (problem.E_min, problem.E_max); "
            f"widen them or set problem.bounds=false")
