"""torchfit: fit material parameters of differentiable simulations to animated motion.

The verbs and the registries::

    import torchfit

    problem = torchfit.build_problem("poisson2d", {"N": 33, "noise": 1e-3})
    result = torchfit.fit(problem, "split_bregman", run_dir="runs/sb")   # a run directory
    report = torchfit.verify(problem)                                    # derivative checks

``torchfit.PROBLEMS`` and ``torchfit.SOLVERS`` map config names to their entries (config
dataclass and class). Layers (DESIGN.md): ``linalg``, ``mesh``, ``physics``, ``params``,
``problems``, ``solvers``, ``logging``, and :mod:`torchfit.fit` (one run) on top; the
contract between problems and solvers is :mod:`torchfit.residual` and :mod:`torchfit.records`.

Importing torchfit changes nothing process-wide (torch's default dtype included): problems
make their tensors in ``problem.dtype``, float64 unless asked otherwise. ``torchfit.fit``
is the function; its module's other names are imported as ``from torchfit.fit import ...``.
"""
from .fit import FitOptions, FitResult, build_solver, fit, verify
from .problems import PROBLEMS, InverseProblem, build_problem
from .solvers import SOLVERS, Solver

__version__ = "0.1.0"

__all__ = ["FitOptions", "FitResult", "InverseProblem", "PROBLEMS", "SOLVERS", "Solver",
           "build_problem", "build_solver", "fit", "verify"]
