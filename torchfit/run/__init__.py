"""One run: a problem, a solver and callbacks in; a run directory and a result out.

:func:`fit` (one fit), :func:`fit_continued` (the frames far from a fold first, then all),
:func:`verify` (derivative checks at a point) and :func:`simulate` (a fitted material on an
animation of the same body) serve a notebook, a test and the Hydra apps alike; nothing here
knows a Hydra type.
"""
from .checkpoint import ResumeError
from .continuation import fit_continued
from .directory import RunDirectoryError
from .fitting import fit
from .options import FitConfigError, FitOptions, VerifyOptions
from .result import FitResult
from .simulating import SimulationResult, simulate
from .solver import build_solver
from .start import initial_theta
from .verifying import verify

__all__ = ["FitConfigError", "FitOptions", "FitResult", "ResumeError", "RunDirectoryError",
           "SimulationResult", "VerifyOptions", "build_solver", "fit", "fit_continued",
           "initial_theta", "simulate", "verify"]
