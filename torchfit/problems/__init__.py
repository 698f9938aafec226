"""Canonical problems of docs/problems.md, one module each, and the registry used by the app."""
from __future__ import annotations

import dataclasses
from typing import Any

from .body import Arm3D, Arm3DConfig
from .base import (NO_WARM_STARTS, InverseProblem, has_forward_jacobian, has_forward_products,
                   parameter_meaning)
from .dynamic import QUASISTATIC, TimeIntegration
from .protocols import (BodyProblem, BodySimulation, EmbeddedSurfaceProblem, FieldImageProblem,
                        FramedProblem, MeshProblem, MotionProblem, PosedProblem, PoseEquilibrium,
                        PoseSimulation, TimeModel, WarmStarts)
from .config import ProblemConfig, ProblemConfigError, make_config
from .membrane2d import DynamicMembrane2D, Membrane2D, Membrane2DConfig
from .poisson2d import Poisson2D, Poisson2DConfig
from ..mesh import KeptMesh
from .body import RiggedBody, RiggedBodyConfig, fitted_mesh, keep_mesh, resumed_mesh
from .spring1d import DynamicSpring1D, Spring1D, Spring1DConfig


@dataclasses.dataclass(frozen=True)
class ProblemEntry:
    """A registered problem: its config dataclass (the Hydra schema), its class, and the
    class of its motion (``problem.dynamic=true``) where it has one (a body is one class:
    its simulation in time is a collaborator, not a class)."""

    config_class: type[ProblemConfig]
    problem_class: type[InverseProblem]
    dynamic_class: type[InverseProblem] | None = None


#: config name -> registered problem
PROBLEMS: dict[str, ProblemEntry] = {
    "spring1d": ProblemEntry(Spring1DConfig, Spring1D, DynamicSpring1D),
    "poisson2d": ProblemEntry(Poisson2DConfig, Poisson2D),
    "membrane2d": ProblemEntry(Membrane2DConfig, Membrane2D, DynamicMembrane2D),
    "arm3d": ProblemEntry(Arm3DConfig, Arm3D, Arm3D),
    "animation": ProblemEntry(RiggedBodyConfig, RiggedBody, RiggedBody),
}


def build_problem(name: str, cfg: Any = None, kept_mesh: KeptMesh | None = None
                  ) -> InverseProblem:
    """Problem ``name`` from a config (its dataclass, a mapping or an OmegaConf node): the
    entry's dynamic class when the config says ``dynamic=true``, else its class. A body is
    built on ``kept_mesh`` (a run's own tetrahedral mesh: a resume, ``simulate``) where its
    surface is that mesh's; a problem without a tetrahedral mesh takes none."""
    if name not in PROBLEMS:
        raise ProblemConfigError(f"unknown problem {name!r}; choose one of "
                                 f"{', '.join(sorted(PROBLEMS))}")
    entry = PROBLEMS[name]
    config = make_config(entry.config_class, cfg)
    dynamic = entry.dynamic_class is not None and bool(getattr(config, "dynamic", False))
    problem_class = entry.dynamic_class if dynamic else entry.problem_class
    if kept_mesh is None:
        return problem_class(config)
    if not issubclass(problem_class, RiggedBody):
        raise ValueError(f"problem {name} has no tetrahedral mesh to build on a kept one")
    return problem_class(config, kept_mesh=kept_mesh)


__all__ = ["Arm3D", "Arm3DConfig", "BodyProblem", "BodySimulation", "DynamicMembrane2D",
           "DynamicSpring1D", "EmbeddedSurfaceProblem", "FieldImageProblem", "FramedProblem",
           "InverseProblem", "Membrane2D", "Membrane2DConfig", "MeshProblem", "MotionProblem",
           "NO_WARM_STARTS", "PROBLEMS", "PoseEquilibrium", "PoseSimulation", "PosedProblem",
           "Poisson2D", "Poisson2DConfig", "ProblemConfig", "ProblemConfigError", "ProblemEntry",
           "QUASISTATIC", "RiggedBody", "RiggedBodyConfig", "Spring1D", "Spring1DConfig",
           "TimeIntegration", "TimeModel", "WarmStarts", "build_problem",
           "fitted_mesh", "has_forward_jacobian", "has_forward_products", "keep_mesh",
           "parameter_meaning", "resumed_mesh"]
