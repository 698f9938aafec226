"""Whether a run directory can be written, checked before anything is written."""
from __future__ import annotations

import os
from pathlib import Path


class RunDirectoryError(OSError):
    """The run directory cannot be written (the message names the path and the reason)."""


def check_writable(run_dir: Path) -> None:
    """Raise :class:`RunDirectoryError` if ``run_dir`` cannot be created or written (writes
    nothing)."""
    if run_dir.exists() and not run_dir.is_dir():
        raise RunDirectoryError(f"cannot write the run directory {run_dir}: it is a file")
    existing = run_dir
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise RunDirectoryError(f"cannot create the run directory {run_dir}: {existing} is a file")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise RunDirectoryError(f"cannot write the run directory {run_dir}: permission denied "
                                f"on {existing}")
