"""Exceptions shared by the layers (kept here so that no layer imports another for them)."""
from __future__ import annotations

import errno
import os


class SimulationError(RuntimeError):
    """The forward simulation has no valid answer at these parameters.

    Raised by the physics and linear-algebra layers (Newton did not converge, a singular
    system, an infeasible material such as a non-positive Young's modulus). Called
    directly, it reports the problem; inside a fit, solvers treat it at a *trial* point
    as a failed step (Levenberg-Marquardt rejects the step, Gauss-Newton's line search
    shortens it) instead of stopping the run.
    """


class ConfigurationError(ValueError):
    """A setting is invalid; the message is one line naming the setting and what is allowed.

    The problem, solver and run layers raise subclasses of it; applications report it
    without a traceback and run nothing.
    """


#: what to do about a write that failed, by its errno (the failures a user can act on)
_WRITE_REMEDIES = {
    errno.ENOSPC: "free space there",
    errno.EDQUOT: "free space there (the disk quota is exhausted)",
    errno.EFBIG: "raise the file-size limit (ulimit -f) or write to another place",
    errno.EROFS: "write to another place (this one is read-only)",
    errno.EACCES: "write where you have permission",
    errno.EPERM: "write where you have permission",
}


#: the ``errno`` values of a write that failed for a reason the user can act on
WRITE_ERRNOS = frozenset(_WRITE_REMEDIES)


def write_remedy(error: OSError) -> str:
    """What to do about the failed write ``error`` (one phrase: "free space there", ...)."""
    return _WRITE_REMEDIES.get(error.errno, "check the place and try again")


def write_failure(error: BaseException | None) -> OSError | None:
    """The failed write in ``error`` or the chain it was raised from, as an ``OSError`` whose
    ``errno`` is one of :data:`_WRITE_REMEDIES`; ``None`` where there is none.

    The USD library reports a failed write as ``pxr.Tf.ErrorException`` with the C++ error
    text of every layer it went through (40 lines and more, the ``strerror`` among them):
    that becomes the ``OSError`` it reports, without a file name."""
    while error is not None:
        if isinstance(error, OSError) and error.errno in _WRITE_REMEDIES:
            return error
        if type(error).__name__ == "ErrorException":          # pxr.Tf, not imported here
            text = str(error)
            for code in _WRITE_REMEDIES:
                if os.strerror(code) in text:
                    return OSError(code, os.strerror(code))
        error = error.__cause__ or error.__context__
    return None


def write_failure_line(error: OSError, target: object) -> str:
    """One line for a write to ``target`` that failed with ``error`` (:func:`write_failure`):
    what happened and what to do."""
    return f"cannot write {target}: {error.strerror or error}; {write_remedy(error)}"
