"""Command lines of torchfit's fit and simulate apps from the panel's settings (no ``bpy``).

The extension starts torchfit as ``<interpreter> <repository>/experiments/fit.py <overrides>``
(or ``simulate.py``), in the repository, with Hydra overrides built here. A job folder
(:class:`JobFolder`) holds the rig Blender exported (``rig.usda``), the run directory torchfit
owns (``run/``, its ``hydra.run.dir``) and the process's console (``console.txt``).

Frames: Blender exports the frame range ``frame_start .. frame_end``; torchfit numbers the
file's frames from 0, so Blender frame ``f`` is file frame ``f - frame_start``.
"""
from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path

__all__ = ["FitSettings", "JobFolder", "CommandError", "find_interpreter", "fit_command",
           "simulate_command", "file_frames", "python_environment"]


class CommandError(ValueError):
    """A setting that cannot make a command line: one line naming it and what to do."""


@dataclasses.dataclass
class FitSettings:
    """The panel's fit settings (each default here once; the panel's properties mirror them).

    Attributes:
        frame_start, frame_end: Blender frames exported (inclusive).
        held_out: Blender frames held out of the fit for validation (``problem.validation_frames``).
        model: ``problem.model`` (``linear``, ``corotated``, ``stable_neo_hookean``).
        grid_nodes: ``problem.grid_nodes`` (about this many nodes of the modulus grid).
        iterations: ``solver.max_iter`` (the whole run's budget, a resume included).
        dynamic: ``problem.dynamic`` (in time; else quasistatic).
        tet_edge_length: ``problem.tet_edge_length`` (a fraction of the body's diagonal).
        threads: ``threads`` (torch and the solvers; 0 leaves torchfit's default).
        init_field: ``problem.init_field`` (a painted layer), "" for the homogeneous start.
    """

    frame_start: int = 1
    frame_end: int = 250
    held_out: tuple[int, ...] = ()
    model: str = "corotated"
    grid_nodes: int = 192
    iterations: int = 20
    dynamic: bool = False
    tet_edge_length: float = 0.05
    threads: int = 0
    init_field: str = ""


@dataclasses.dataclass(frozen=True)
class JobFolder:
    """The files of one job under ``root``: the exported rig, the run, the console."""

    root: Path

    @property
    def rig(self) -> Path:
        """The rig as Blender's USD exporter wrote it."""
        return Path(self.root) / "rig.usda"

    @property
    def run(self) -> Path:
        """torchfit's run directory (``hydra.run.dir``)."""
        return Path(self.root) / "run"

    @property
    def console(self) -> Path:
        """The process's standard output and error."""
        return Path(self.root) / "console.txt"

    @property
    def painted(self) -> Path:
        """A painted modulus layer (``problem.init_field``)."""
        return Path(self.root) / "painted.usda"


def find_interpreter(repository: str | Path, interpreter: str = "") -> Path:
    """The Python that runs torchfit: ``interpreter`` if set, else the repository's
    ``.venv/bin/python``; a :class:`CommandError` naming the preference if neither exists."""
    repository = Path(repository).expanduser()
    if not (repository / "experiments" / "fit.py").is_file():
        raise CommandError(f"torchfit repository {repository} has no experiments/fit.py: set "
                           "the extension's preference 'torchfit repository'")
    candidate = Path(interpreter).expanduser() if interpreter else repository / ".venv" / "bin" / "python"
    if not candidate.is_file() or not os.access(candidate, os.X_OK):
        raise CommandError(f"interpreter {candidate} not found: set the extension's preference "
                           "'Python interpreter' (torchfit's venv, scripts/_venv.sh makes it)")
    return candidate


def file_frames(blender_frames, frame_start: int, frame_end: int) -> list[int]:
    """Blender frames as torchfit's file frame numbers (``f - frame_start``); a
    :class:`CommandError` for a frame outside the range."""
    out = []
    for f in blender_frames:
        if not frame_start <= int(f) <= frame_end:
            raise CommandError(f"held-out frame {f} is outside the frame range "
                               f"{frame_start}-{frame_end}: choose frames inside it")
        out.append(int(f) - frame_start)
    return sorted(set(out))


def _list(values) -> str:
    return "[" + ",".join(str(v) for v in values) + "]"


def fit_command(settings: FitSettings, job: JobFolder, repository: str | Path,
                interpreter: str | Path, resume: bool = False) -> list[str]:
    """The fit's command line (run in ``repository``) for ``settings`` on ``job.rig``;
    ``resume``: continue the run in ``job.run`` (the same overrides plus ``resume=true``,
    as torchfit requires: docs/guide/resume.md)."""
    if settings.frame_end <= settings.frame_start:
        raise CommandError(f"frame range {settings.frame_start}-{settings.frame_end} holds "
                           "fewer than two frames: set an end after the start")
    if settings.iterations < 1:
        raise CommandError("iterations must be at least 1")
    overrides = [f"hydra.run.dir={job.run}", "problem=animation", f"problem.path={job.rig}",
                 f"problem.model={settings.model}", f"problem.grid_nodes={settings.grid_nodes}",
                 f"problem.tet_edge_length={settings.tet_edge_length:g}",
                 f"solver.max_iter={settings.iterations}",
                 f"problem.dynamic={'true' if settings.dynamic else 'false'}"]
    held_out = file_frames(settings.held_out, settings.frame_start, settings.frame_end)
    if held_out:
        overrides.append(f"problem.validation_frames={_list(held_out)}")
    if settings.init_field:
        overrides.append(f"problem.init_field={settings.init_field}")
    if settings.threads:
        overrides.append(f"threads={settings.threads}")
    if resume:
        overrides.append("resume=true")
    return [str(interpreter), str(Path(repository) / "experiments" / "fit.py"), *overrides]


def simulate_command(fit_run: str | Path, animation: str | Path, out_dir: str | Path,
                     repository: str | Path, interpreter: str | Path,
                     dynamic: bool | None = None) -> list[str]:
    """The simulate app's command line: the fitted material of ``fit_run`` on ``animation``
    (another action of the same rig, exported), into ``out_dir``; ``dynamic``: in time or
    quasistatic (``None``: as the fit was)."""
    overrides = [f"hydra.run.dir={out_dir}", f"run={fit_run}", f"problem.path={animation}",
                 "problem.frames=null"]
    if dynamic is not None:
        overrides.append(f"problem.dynamic={'true' if dynamic else 'false'}")
    return [str(interpreter), str(Path(repository) / "experiments" / "simulate.py"), *overrides]


def python_environment() -> dict[str, str]:
    """The environment of a torchfit process started from Blender: Blender's own Python
    removed (``PYTHONHOME``, and ``PYTHONPATH`` entries inside a ``bpy`` module, whose
    bundled ``pxr`` must not meet torchfit's usd-core); other entries are kept."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONHOME", "PYTHONSTARTUP")}
    path = [p for p in env.pop("PYTHONPATH", "").split(os.pathsep)
            if p and "bpy" not in Path(p).parts]
    if path:
        env["PYTHONPATH"] = os.pathsep.join(path)
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


if sys.version_info < (3, 10):  # Blender 4.2+ ships 3.11; the dataclass syntax needs 3.10
    raise ImportError("torchfit_blender needs Python 3.10+")
