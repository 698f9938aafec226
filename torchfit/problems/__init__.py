"""Canonical problems of PROBLEMS.md, one module each, and the registry used by the app."""
from __future__ import annotations

from typing import Any, Callable

from .base import InverseProblem, ProblemConfigError
from .poisson2d import Poisson2D, Poisson2DConfig
from .membrane2d import Membrane2D, Membrane2DConfig
from .spring1d import Spring1D, Spring1DConfig

#: config name -> (config dataclass, problem class)
PROBLEMS: dict[str, tuple[type, Callable[..., InverseProblem]]] = {
    "spring1d": (Spring1DConfig, Spring1D),
    "poisson2d": (Poisson2DConfig, Poisson2D),
    "membrane2d": (Membrane2DConfig, Membrane2D),
}


def build_problem(name: str, cfg: Any = None) -> InverseProblem:
    """Problem ``name`` from a config (dataclass, mapping or OmegaConf node)."""
    if name not in PROBLEMS:
        raise ProblemConfigError(f"unknown problem {name!r}; choose one of {sorted(PROBLEMS)}")
    config_cls, problem_cls = PROBLEMS[name]
    if cfg is None:
        return problem_cls(config_cls())
    if not isinstance(cfg, config_cls):
        fields = {f for f in config_cls.__dataclass_fields__}
        values = {k: v for k, v in dict(cfg).items() if k in fields}
        unknown = set(dict(cfg)) - fields
        if unknown:
            raise ProblemConfigError(f"unknown setting(s) {sorted(unknown)} for problem {name}")
        cfg = config_cls(**values)
    return problem_cls(cfg)


__all__ = ["InverseProblem", "Membrane2D", "Membrane2DConfig", "PROBLEMS", "Poisson2D",
           "Poisson2DConfig", "ProblemConfigError",
           "Spring1D", "Spring1DConfig",
           "build_problem"]
