"""The solvers by config name, and a solver built from a config and what the
parameterisation offers.

:data:`SOLVERS` maps a config name (``solver=<name>``) to its :class:`SolverEntry`
(config dataclass, also the Hydra schema, and solver class). What a solver needs of the
parameterisation depends on its settings and is said by the config itself
(:meth:`~.base.SolverConfig.needs`: the difference operator ``D`` unused, used where
offered, or required; its row groups or not). :func:`build` acts on that: it calls the
parameterisation's operators only where the settings use them.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

from torch import Tensor

from .base import Need, Solver, SolverConfig, SolverConfigError
from .gauss_newton import GaussNewton, GaussNewtonConfig
from .levenberg_marquardt import LevenbergMarquardt, LevenbergMarquardtConfig
from .split_bregman import SplitBregman, SplitBregmanConfig


@dataclasses.dataclass(frozen=True)
class SolverEntry:
    """A registered solver.

    Attributes:
        config_class: its :class:`~.base.SolverConfig` dataclass (also the Hydra schema);
            an instance's :meth:`~.base.SolverConfig.needs` says what the solver needs of
            the parameterisation.
        solver_class: its :class:`~.base.Solver`.
    """

    config_class: type[SolverConfig]
    solver_class: type[Solver]


#: config name -> :class:`SolverEntry`
SOLVERS: dict[str, SolverEntry] = {
    "gauss_newton": SolverEntry(GaussNewtonConfig, GaussNewton),
    "levenberg_marquardt": SolverEntry(LevenbergMarquardtConfig, LevenbergMarquardt),
    "split_bregman": SolverEntry(SplitBregmanConfig, SplitBregman),
}


def build(config: SolverConfig, *, difference_operator: Callable[[], Tensor] | None = None,
          difference_groups: Callable[[], Tensor | None] | None = None,
          offered_by: str = "the parameterisation") -> Solver:
    """The registered solver of ``config`` (validated here), given what the
    parameterisation offers.

    Args:
        config: a solver config whose ``name`` is in :data:`SOLVERS`.
        difference_operator: the parameterisation's ``D`` as a call
            (``parameterization.difference_operator``), or ``None`` where it has none.
            Called only where the settings use ``D``.
        difference_groups: the row groups of ``D`` as a call, or ``None``; called only
            where ``D`` is required and the settings use the groups.
        offered_by: who offers the operators, for the error message (e.g.
            ``"spring1d's (Parameterization)"``).

    Raises:
        SolverConfigError: an unknown ``config.name``, a bad setting, or a required ``D``
            that is not offered (``solver=<name> needs the difference operator D of the
            parameterisation, but <offered_by> has none``).
    """
    entry = SOLVERS.get(config.name)
    if entry is None:
        raise SolverConfigError(f"solver={config.name!r} is not a solver; choose one of "
                                f"{sorted(SOLVERS)}")
    config.validate()
    needs = config.needs()
    inputs: dict[str, Tensor | None] = {}
    if needs.difference_operator is Need.if_offered:
        if difference_operator is not None:
            inputs["D"] = difference_operator()
    elif needs.difference_operator is Need.required:
        if difference_operator is None:
            raise SolverConfigError(f"solver={config.name} needs the difference operator D of "
                                    f"the parameterisation, but {offered_by} has none")
        inputs["D"] = difference_operator()
        if needs.difference_groups:
            inputs["groups"] = difference_groups() if difference_groups is not None else None
    return entry.solver_class(config, **inputs)


__all__ = ["SOLVERS", "SolverEntry", "build"]
