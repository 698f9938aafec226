"""What a torchfit run directory says: progress while it runs, its summary when done (no ``bpy``).

Progress (:func:`read_progress`) comes from ``history.jsonl`` (one JSON row per iteration:
``iteration``, ``misfit``, ``surface_err_mean`` in metres; a torn last line, being written,
is skipped) and ``fit.log``'s last lines. The summary (:func:`read_summary`) comes from
``result.json`` and the ``[WARNING]`` lines of ``fit.log``.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

__all__ = ["Progress", "Summary", "read_progress", "read_summary", "log_tail"]


@dataclasses.dataclass
class Progress:
    """A running fit's state as its files show it.

    Attributes:
        iteration: the last iteration recorded (-1: none yet).
        misfit: its misfit (the solver's objective's data term), or ``None``.
        surface_error: its mean surface error, metres, or ``None``.
        fraction: ``iteration / max_iter`` in [0, 1] (for a progress bar).
        log: the log's last lines.
    """

    iteration: int = -1
    misfit: float | None = None
    surface_error: float | None = None
    fraction: float = 0.0
    log: list[str] = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class Summary:
    """A finished fit, from ``result.json`` (lengths in metres).

    Attributes:
        surface_error: mean surface error of the fitted frames.
        held_out_error: of the held-out frames (``None`` without validation).
        reduction: the homogeneous material's error over the fitted one.
        determined: whether the data determine the field (``None`` if not said).
        units: the modulus's unit (e.g. ``relative to problem.E0``, ``Pa``).
        iterations: iterations run; ``stop_reason``: why it stopped.
        warnings: the log's warning lines (their messages).
    """

    surface_error: float
    held_out_error: float | None
    reduction: float | None
    determined: bool | None
    units: str
    iterations: int
    stop_reason: str
    warnings: list[str]


def _rows(path: Path) -> list[dict]:
    try:
        text = path.read_text()
    except OSError:
        return []
    rows = []
    for line in text.splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            break                            # a line being written
    return rows


def log_tail(run: str | Path, lines: int = 5, name: str = "fit.log") -> list[str]:
    """The last ``lines`` lines of the run's log, without the timestamp and logger prefix."""
    try:
        text = (Path(run) / name).read_text(errors="replace")
    except OSError:
        return []
    out = []
    for line in text.splitlines()[-lines:]:
        # "[2026-12-07 21:49:31,544][torchfit.setup][INFO] - message"
        out.append(line.split("] - ", 1)[1] if "] - " in line else line)
    return out


def read_progress(run: str | Path, max_iter: int, log_lines: int = 5) -> Progress:
    """The progress of the run in ``run`` whose budget is ``max_iter`` iterations."""
    run = Path(run)
    rows = _rows(run / "history.jsonl")
    progress = Progress(log=log_tail(run, log_lines))
    if rows:
        last = rows[-1]
        progress.iteration = int(last.get("iteration", len(rows) - 1))
        progress.misfit = last.get("misfit")
        progress.surface_error = last.get("surface_err_mean")
        progress.fraction = min(1.0, max(0.0, progress.iteration / max(1, max_iter)))
    return progress


def _warnings(run: Path) -> list[str]:
    try:
        text = (run / "fit.log").read_text(errors="replace")
    except OSError:
        return []
    return [line.split("] - ", 1)[-1] for line in text.splitlines() if "][WARNING]" in line]


def read_summary(run: str | Path) -> Summary | None:
    """The summary of a finished fit in ``run`` (``None`` while it has no ``result.json``)."""
    run = Path(run)
    try:
        result = json.loads((run / "result.json").read_text())
    except (OSError, json.JSONDecodeError):
        return None
    units = result.get("modulus_units", {})
    return Summary(surface_error=float(result["surface_err_mean"]),
                   held_out_error=result.get("validation_surface_err_mean"),
                   reduction=result.get("surface_err_reduction"),
                   determined=result.get("determined"),
                   units=units.get("unit", "") if isinstance(units, dict) else str(units),
                   iterations=int(result.get("iterations", 0)),
                   stop_reason=str(result.get("stop_reason", "")),
                   warnings=_warnings(run))
