"""The solver of a run, from a name, a settings mapping or a config object.

Solver construction asks the problem's parameterisation for what the solver's registry
entry says it needs (the difference operator ``D``, its TV groups).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping

from ..problems import InverseProblem
from ..solvers import SOLVERS, Solver, SolverConfig
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
        return solver
    config = solver_config(solver)
    entry = SOLVERS[config.name]
    inputs: dict[str, Any] = {}
    if entry.takes_difference_operator(config) and not entry.needs_difference_operator(config):
        operator = getattr(problem.parameterization, "difference_operator", None)
        if operator is not None:
            inputs["D"] = operator()
    elif entry.needs_difference_operator(config):
        param = problem.parameterization
        operator = getattr(param, "difference_operator", None)
        if operator is None:
            raise FitConfigError(f"solver={config.name} needs the difference operator D of the "
                                 f"parameterisation, but {problem.name}'s "
                                 f"({type(param).__name__}) has none")
        inputs["D"] = operator()
        if entry.uses_groups(config):
            groups_of = getattr(param, "difference_groups", None)
            inputs["groups"] = groups_of() if groups_of is not None else None
    return entry.solver_class(config, **inputs)
