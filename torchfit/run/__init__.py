"""One run: a problem, a solver and callbacks in; a run directory and a result out.

:func:`fit` (one fit), :func:`fit_continued` (the frames far from a fold first, then all),
:func:`verify` (derivative checks at a point) and :func:`simulate` (a fitted material on an
animation of the same body) serve a notebook, a test and the Hydra apps alike; nothing here
knows a Hydra type. The apps (``experiments/``) import only this face (and ``torchfit``,
``torchfit.config``, ``torchfit.errors``): beside the verbs, the checks they make before a
run starts (threads, the solver's section, the continuation's settings, a run directory),
the lock of a run directory, the mesh a resume builds on and the result file of a failed
sweep job.
"""
from ..linalg import set_threads
from ..problems import resumed_mesh
from ..reporting import write_json
from .checkpoint import ResumeError
from .continuation import (FIRST_STAGE_DIR, continuation_applies, continuation_setting,
                           first_stage_iterations, fit_continued)
from .directory import RunDirectoryError, check_writable
from .fitting import fit
from .lock import RunLockedError, acquire, release_all
from .options import FitConfigError, FitOptions, VerifyOptions, check_threads
from .result import FitResult
from .simulating import SimulationResult, check_run_dir, read_fitted_run, simulate
from .solver import build_solver, solver_config
from .start import initial_theta
from .verifying import verify

__all__ = ["FIRST_STAGE_DIR", "FitConfigError", "FitOptions", "FitResult", "ResumeError",
           "RunDirectoryError", "RunLockedError", "SimulationResult", "VerifyOptions",
           "acquire", "build_solver", "check_run_dir", "check_threads", "check_writable",
           "continuation_applies", "continuation_setting", "first_stage_iterations", "fit",
           "fit_continued", "initial_theta", "read_fitted_run", "release_all", "resumed_mesh",
           "set_threads", "simulate", "solver_config", "verify", "write_json"]
