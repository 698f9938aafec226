"""A torchfit process in the background: start, poll, cancel (no ``bpy``).

:func:`start` runs a command line (:mod:`.command`) as a ``subprocess.Popen`` in a session
of its own, its standard output and error appended to the job's ``console.txt``; Blender's
UI thread never waits on it: the panel's modal timer calls :meth:`Job.poll` (a non-blocking
``Popen.poll``) and reads the run's files (:mod:`.results`). :meth:`Job.cancel` sends SIGTERM,
which torchfit ends like Ctrl-C (exit 143, a checkpoint after every iteration): the same fit
with ``resume=true`` continues it (docs/guide/resume.md).
"""
from __future__ import annotations

import dataclasses
import signal
import subprocess
from pathlib import Path

from .command import python_environment

__all__ = ["Job", "start", "last_error_line"]


@dataclasses.dataclass
class Job:
    """A started process (``process``), the folder it writes into and its console file."""

    process: subprocess.Popen
    run: Path
    console: Path

    def poll(self) -> int | None:
        """The exit status, or ``None`` while it runs (never blocks)."""
        return self.process.poll()

    @property
    def running(self) -> bool:
        """Whether the process still runs."""
        return self.poll() is None

    def cancel(self, timeout: float = 30.0) -> int | None:
        """SIGTERM (torchfit stops after writing what it holds; resume continues it), then
        wait up to ``timeout`` seconds; the exit status (``None`` if it still runs)."""
        if self.running:
            self.process.send_signal(signal.SIGTERM)
        try:
            return self.process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None

    def wait(self, timeout: float | None = None) -> int:
        """Block until the process ends (tests and headless use): its exit status."""
        return self.process.wait(timeout=timeout)

    def error_line(self) -> str:
        """The line torchfit printed for a failed run (:func:`last_error_line`)."""
        return last_error_line(self.console)


def start(command: list[str], cwd: str | Path, run: str | Path, console: str | Path) -> Job:
    """Start ``command`` in ``cwd`` (the repository) writing into ``run``; output appended to
    ``console`` (a resume appends after the cancelled run's lines). Returns at once."""
    console = Path(console)
    console.parent.mkdir(parents=True, exist_ok=True)
    with open(console, "ab") as out:        # the child keeps its own descriptor
        process = subprocess.Popen(command, cwd=str(cwd), stdout=out, stderr=subprocess.STDOUT,
                                   stdin=subprocess.DEVNULL, env=python_environment(),
                                   start_new_session=True)
    return Job(process=process, run=Path(run), console=console)


def last_error_line(console: str | Path) -> str:
    """The last ``error: ...`` line of a console (torchfit's one-line refusals), else its last
    non-empty line, else ""."""
    try:
        lines = [x.strip() for x in Path(console).read_text(errors="replace").splitlines()]
    except OSError:
        return ""
    errors = [x for x in lines if x.startswith("error:")]
    if errors:
        return errors[-1]
    lines = [x for x in lines if x]
    return lines[-1] if lines else ""
