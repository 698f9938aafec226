"""torchfit: fit material parameters of differentiable simulations to animated motion.

The verbs and the registries::

    import torchfit

    problem = torchfit.build_problem("poisson2d", {"N": 33, "noise": 1e-3})
    result = torchfit.fit(problem, "split_bregman", run_dir="runs/sb")   # a run directory
    report = torchfit.verify(problem)                                    # derivative checks

``torchfit.PROBLEMS`` and ``torchfit.SOLVERS`` map config names to their entries (config
dataclass and class). Layers (docs/architecture.md): ``linalg``, ``mesh``, ``physics``, ``params``,
``problems``, ``solvers``, ``reporting``, and :mod:`torchfit.run` (one run) on top; the
contract between problems and solvers is :mod:`torchfit.residual` and :mod:`torchfit.records`.

Importing torchfit changes nothing process-wide (torch's default dtype included): problems
make their tensors in ``problem.dtype``, float64 unless asked otherwise. The run's other
names (``fit_continued``, ``VerifyOptions``, its errors) are in :mod:`torchfit.run`.
"""
from .run import FitOptions, FitResult, build_solver, fit, verify
from .problems import PROBLEMS, InverseProblem, build_problem
from .solvers import SOLVERS, Solver

__version__ = "0.1.0"

__all__ = ["FitOptions", "FitResult", "InverseProblem", "PROBLEMS", "SOLVERS", "Solver",
           "build_problem", "build_solver", "fit", "verify"]
