"""The Hydra apps (``experiments/fit.py``, ``simulate.py``, ``verify.py``) run in the test's own
process, as ``python experiments/<app>.py <args>`` runs them, without starting a Python.

:func:`run_app` executes the app's file as ``__main__`` (:func:`runpy.run_path`: its
``if __name__ == "__main__"`` block, the same code a shell runs) with ``sys.argv``, the
working directory and the environment of the command, and returns what
:func:`subprocess.run` would: the exit status (``sys.exit``'s code; 1 and the traceback on
standard error for an uncaught exception) and everything written to standard output and
standard error, through Python's streams or the file descriptors (a C library's output
included). What the app changes in the process for its run is put back afterwards: the
environment, the working directory, ``sys.path``, signal handlers, ``threading.excepthook``,
logging (Hydra's handlers, the job's log file closed), warnings filters, Hydra's global
state, torch's default dtype (float32 for the run, as in a fresh process), thread counts
and random states, the BLAS thread limits. The run keeps the test's torch thread count
(one, tests/conftest.py) unless the app sets its own (``threads=``).

A fresh process saves about 2.5 s of imports per run (5 s on two busy cores); what needs
a process of its own stays a subprocess (:func:`helpers.fit_app.run_fit_app_process`): a
kill, SIGTERM, two runs at once into one directory (the lock is per process), a full disk
in a private mount namespace, the shell scripts, the launchers that start processes.
Not thread-safe: one app at a time in a process (the tests run them one after another).
"""
from __future__ import annotations

import io
import logging
import os
import random
import runpy
import signal
import subprocess
import sys
import tempfile
import threading
import traceback
import warnings
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[2]
APPS = ("fit.py", "simulate.py", "verify.py")
#: the seed of torch's default generator in a fresh process
FRESH_SEED = 67280421310721
_RUNNING = threading.Lock()


def run_app(script: str, *args: str, cwd: str | Path = REPO, env: Mapping[str, str] | None = None,
            unset: Sequence[str] = ("HYDRA_FULL_ERROR",),
            timeout: float | None = None) -> subprocess.CompletedProcess:
    """``python experiments/<script> <args>`` in ``cwd``, in this process.

    ``env``: variables set for the run (on top of this process's environment), ``unset``:
    variables removed (``HYDRA_FULL_ERROR``, as the subprocess tests ran the apps).
    ``timeout`` is accepted for the subprocess helpers' signature and not enforced."""
    del timeout
    if script not in APPS:
        raise ValueError(f"{script!r}: one of {APPS}")
    path = str(REPO / "experiments" / script)
    if not _RUNNING.acquire(blocking=False):
        raise RuntimeError("run_app: another app is running in this process (not thread-safe)")
    try:
        with _ProcessState(cwd, env, unset), _Captured() as captured:
            code = _execute(path, [path, *args], captured)
        return subprocess.CompletedProcess([sys.executable, path, *args], code,
                                           captured.stdout, captured.stderr)
    finally:
        _RUNNING.release()


def _execute(path: str, argv: list[str], captured: "_Captured") -> int:
    sys.argv = argv
    try:
        runpy.run_path(path, run_name="__main__")
    except SystemExit as exit_:
        code = exit_.code
        if code is None:
            return 0
        if isinstance(code, int):
            return code
        print(code, file=sys.stderr)        # as the interpreter reports sys.exit("text")
        return 1
    except KeyboardInterrupt:
        raise                               # Ctrl-C of the test run: not the app's to report
    except BaseException:                   # what the interpreter does with an uncaught error
        traceback.print_exc(file=sys.stderr)
        return 1
    return 0


class _Captured:
    """File descriptors 1 and 2 (and ``sys.stdout``/``sys.stderr`` on them) into temporary
    files for the run, as a subprocess's pipes would take them."""

    def __enter__(self) -> "_Captured":
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        self.files = [tempfile.TemporaryFile(), tempfile.TemporaryFile()]
        self.saved_fds = [os.dup(1), os.dup(2)]
        self.saved_streams = (sys.stdout, sys.stderr)
        for fd, file in zip((1, 2), self.files):
            os.dup2(file.fileno(), fd)
        self.streams = [io.TextIOWrapper(io.FileIO(os.dup(fd), "w"), encoding="utf-8",
                                         errors="backslashreplace", line_buffering=True)
                        for fd in (1, 2)]
        sys.stdout, sys.stderr = self.streams
        return self

    def __exit__(self, *exc) -> None:
        for stream in self.streams:
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        sys.stdout, sys.stderr = self.saved_streams
        for fd, saved in zip((1, 2), self.saved_fds):
            os.dup2(saved, fd)
            os.close(saved)
        for stream in self.streams:
            try:
                stream.close()
            except (OSError, ValueError):
                pass
        self.stdout, self.stderr = (self._read(file) for file in self.files)

    @staticmethod
    def _read(file) -> str:
        file.seek(0)
        text = file.read().decode("utf-8", errors="backslashreplace")
        file.close()
        return text


class _ProcessState:
    """Sets up a fresh process's view for the app and puts back, on exit, what the app
    changes in its process."""

    def __init__(self, cwd: str | Path, env: Mapping[str, str] | None,
                 unset: Sequence[str]) -> None:
        self.cwd, self.env, self.unset = Path(cwd), dict(env or {}), tuple(unset)

    def __enter__(self) -> "_ProcessState":
        from threadpoolctl import threadpool_limits

        from torchfit.linalg import threads as torchfit_threads

        self.saved_cwd = os.getcwd()
        self.saved_environ = dict(os.environ)
        self.saved_path = list(sys.path)
        self.saved_argv = list(sys.argv)
        self.saved_signals = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
        self.saved_excepthook = threading.excepthook
        self.saved_raise = logging.raiseExceptions
        self.saved_logging = _logging_state()
        self.saved_dtype = torch.get_default_dtype()
        self.saved_threads = torch.get_num_threads()
        self.saved_rng = (torch.random.get_rng_state(), np.random.get_state(), random.getstate())
        self.saved_requested = torchfit_threads._REQUESTED
        self.blas = threadpool_limits(limits=None)      # records every library's limit
        self.warnings = warnings.catch_warnings()
        self.warnings.__enter__()
        _python_default_warnings()
        _clear_hydra()
        for name in self.unset:
            os.environ.pop(name, None)
        os.environ.update(self.env)
        os.chdir(self.cwd)
        torch.set_default_dtype(torch.float32)          # a fresh process's defaults
        torch.manual_seed(FRESH_SEED)
        return self

    def __exit__(self, *exc) -> None:
        from torchfit.linalg import threads as torchfit_threads
        from torchfit.run.lock import release_all

        release_all()
        _clear_hydra()
        _restore_logging(self.saved_logging)
        logging.raiseExceptions = self.saved_raise
        threading.excepthook = self.saved_excepthook
        for number, handler in self.saved_signals.items():
            signal.signal(number, handler)
        self.warnings.__exit__(None, None, None)
        self.blas.restore_original_limits()
        torchfit_threads._REQUESTED = self.saved_requested
        torch.set_num_threads(self.saved_threads)
        torch.set_default_dtype(self.saved_dtype)
        torch.random.set_rng_state(self.saved_rng[0])
        np.random.set_state(self.saved_rng[1])
        random.setstate(self.saved_rng[2])
        os.chdir(self.saved_cwd)
        os.environ.clear()
        os.environ.update(self.saved_environ)
        sys.path[:] = self.saved_path
        sys.argv = self.saved_argv


def _python_default_warnings() -> None:
    """The interpreter's default filters (``python -W`` unset): each warning shown once per
    place on standard error, deprecations only from ``__main__``."""
    warnings.resetwarnings()
    warnings.simplefilter("default")
    for category in (ResourceWarning, ImportWarning, PendingDeprecationWarning,
                     DeprecationWarning):
        warnings.filterwarnings("ignore", category=category)
    warnings.filterwarnings("default", category=DeprecationWarning, module="__main__")
    warnings.showwarning = warnings._showwarning_orig   # type: ignore[attr-defined]


def _clear_hydra() -> None:
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()


def _logging_state() -> dict:
    loggers = {"": logging.getLogger()}
    loggers.update({name: logger for name, logger in logging.Logger.manager.loggerDict.items()
                    if isinstance(logger, logging.Logger)})
    return {name: (logger, logger.level, list(logger.handlers), logger.propagate,
                   logger.disabled) for name, logger in loggers.items()}


def _restore_logging(saved: dict) -> None:
    """Every logger as it was; the handlers the run added (Hydra's console and job log file)
    flushed and closed."""
    current = _logging_state()
    kept = {id(h) for _, _, handlers, _, _ in saved.values() for h in handlers}
    for name, (logger, _, handlers, _, _) in current.items():
        for handler in handlers:
            if id(handler) not in kept:
                logger.removeHandler(handler)
                try:
                    handler.flush()
                    handler.close()
                except (OSError, ValueError):
                    pass
    for name, (logger, level, handlers, propagate, disabled) in saved.items():
        logger.setLevel(level)
        logger.handlers[:] = handlers
        logger.propagate = propagate
        logger.disabled = disabled
    for name, (logger, _, _, _, _) in current.items():
        if name not in saved:       # a logger the run created: as a new one would be
            logger.setLevel(logging.NOTSET)
            logger.propagate = True
            logger.disabled = False
