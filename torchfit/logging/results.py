"""Result files of a run: ``result.json``, fitted parameters, the resume checkpoint.

Files written into a run directory:

``result.json``
    Every final metric of PROBLEMS.md at top level (``misfit``, ``u_err_inf``,
    ``u_err_2``, ``k_err_inf``, ``k_err_2``, ``k_err_rel``, and ``k_err_rel_aligned`` for a
    scale-free problem; those that need a truth only when the problem has one), then
    ``iterations``, ``wall_s`` (solver wall time), ``factorizations``, ``solves``,
    ``converged``, ``stop_reason``, ``problem`` (``problem.describe()``), ``config`` (the
    resolved config) and ``history`` (one dict of scalars per outer iteration, with its
    ``iteration``). Non-finite floats are written as ``null`` (strict JSON).
``params.pt``
    ``{'theta': (n_params,), 'field': (n_field,), 'field_name': 'k'}`` (CPU tensors).
``field.npy``
    the fitted field as a NumPy array.
``checkpoint.pt``
    ``{'iteration', 'theta', 'misfit', 'problem', 'n_params', 'problem_config'}`` (the
    last one a JSON string) of the last outer
    iteration, rewritten after every iteration by :class:`CheckpointWriter` (written to a
    temporary file then renamed, so it is never half-written); :func:`load_checkpoint`
    reads it back to resume.
"""
from __future__ import annotations

import dataclasses
import enum
import json
import math
import os
import pickle
import threading
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
from torch import Tensor

from ..records import IterationRecord, SolveResult

RESULT_FILE = "result.json"
PARAMS_FILE = "params.pt"
FIELD_FILE = "field.npy"
CHECKPOINT_FILE = "checkpoint.pt"


def _jsonable(value: Any) -> Any:
    """Plain JSON types; NaN and infinities become ``None``; an Enum becomes its value."""
    if isinstance(value, enum.Enum):
        return _jsonable(value.value)
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Tensor):
        return _jsonable(value.detach().cpu().tolist())
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _jsonable(dataclasses.asdict(value))
    return str(value)


def _atomic_write(path: Path, write, mode: str = "wb") -> None:
    """Call ``write(f)`` on a temporary file opened with ``mode`` in the same directory,
    then rename it onto ``path`` (atomic: the file is never half-written).

    ``write`` gets the open file object, never the temporary name: ``torch.save`` to a
    *path* records the file's name inside its zip archive, which made two identical runs
    give different bytes."""
    path.parent.mkdir(parents=True, exist_ok=True)
    # A name of our own (not mkstemp, whose files are private): the result keeps the
    # permissions of the umask, like every other file of the run.
    tmp = str(path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp"))
    try:
        encoding = None if "b" in mode else "utf-8"
        with open(tmp, mode, encoding=encoding) as f:
            write(f)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _torch_bytes(obj: Any, f) -> None:
    """``torch.save`` into an open file: the same bytes for the same content, whatever the
    file's name, directory or process."""
    torch.save(obj, f)


def write_json(path: str | Path, data: Mapping[str, Any]) -> Path:
    """Write strict JSON (atomically)."""
    path = Path(path)

    def write(f) -> None:
        json.dump(_jsonable(data), f, indent=2, allow_nan=False)
        f.write("\n")

    _atomic_write(path, write, "w")
    return path


def history_rows(history: list[IterationRecord], step_offset: int = 0) -> list[dict[str, Any]]:
    """One dict per record: ``iteration`` then every scalar of the record."""
    return [{"iteration": rec.iteration + step_offset, **rec.scalars()} for rec in history]


def result_dict(result: SolveResult, metrics: Mapping[str, float],
                problem: Mapping[str, Any] | None = None,
                config: Mapping[str, Any] | None = None,
                step_offset: int = 0, **extra: Any) -> dict[str, Any]:
    """The content of ``result.json`` (see the module docstring)."""
    out: dict[str, Any] = {k: float(v) for k, v in metrics.items()}
    out.update({
        "iterations": result.iterations,
        "wall_s": result.wall_time,
        "factorizations": result.factorizations,
        "solves": result.solves,
        "converged": result.converged,
        "stop_reason": result.stop_reason,
    })
    if step_offset:
        out["resumed_from_iteration"] = step_offset
    out.update(extra)
    out["problem"] = dict(problem or {})
    out["config"] = dict(config or {})
    out["history"] = history_rows(result.history, step_offset)
    return out


def write_result(run_dir: str | Path, result: SolveResult, metrics: Mapping[str, float],
                 problem: Mapping[str, Any] | None = None,
                 config: Mapping[str, Any] | None = None,
                 step_offset: int = 0, **extra: Any) -> Path:
    """Write ``<run_dir>/result.json``; returns its path."""
    return write_json(Path(run_dir) / RESULT_FILE,
                      result_dict(result, metrics, problem, config, step_offset, **extra))


def save_params(run_dir: str | Path, theta: Tensor, field: Tensor,
                field_name: str = "k") -> tuple[Path, Path]:
    """Write ``params.pt`` (theta and field) and ``field.npy``; returns both paths."""
    run_dir = Path(run_dir)
    theta_cpu = theta.detach().cpu().clone()
    field_cpu = field.detach().cpu().clone()
    params_path = run_dir / PARAMS_FILE
    _atomic_write(params_path, lambda f: _torch_bytes(
        {"theta": theta_cpu, "field": field_cpu, "field_name": field_name}, f))
    field_path = run_dir / FIELD_FILE
    _atomic_write(field_path, lambda f: np.save(f, field_cpu.numpy()))
    return params_path, field_path


@dataclasses.dataclass
class Checkpoint:
    """What a resumed run starts from."""

    iteration: int
    theta: Tensor
    misfit: float | None = None
    problem: str | None = None
    problem_config: dict[str, Any] = dataclasses.field(default_factory=dict)


def save_checkpoint(path: str | Path, iteration: int, theta: Tensor,
                    misfit: float | None = None, problem: str | None = None,
                    problem_config: Mapping[str, Any] | None = None) -> Path:
    """Write a checkpoint atomically (temporary file, then ``os.replace``).

    ``problem_config`` (plain values) lets a resumed run notice changed problem settings.
    """
    path = Path(path)
    theta_cpu = theta.detach().cpu().clone()
    payload = {"iteration": int(iteration), "theta": theta_cpu, "misfit": misfit,
               "problem": problem, "n_params": int(theta_cpu.numel()),
               "problem_config": json.dumps(_jsonable(problem_config or {}))}
    _atomic_write(path, lambda f: _torch_bytes(payload, f))
    return path


def load_checkpoint(path: str | Path, n_params: int | None = None,
                    problem: str | None = None) -> Checkpoint:
    """Read a checkpoint; raise ``ValueError`` naming the file if it does not fit.

    Args:
        n_params: expected length of ``theta`` (the problem's parameter count).
        problem: expected problem name.
    """
    path = Path(path)
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
        theta = payload["theta"]
        iteration = int(payload["iteration"])
    except (OSError, RuntimeError, KeyError, TypeError, EOFError, ValueError,
            pickle.UnpicklingError) as e:
        raise ValueError(f"cannot read checkpoint {path}: {e}") from None
    if not isinstance(theta, Tensor) or theta.dim() != 1:
        raise ValueError(f"checkpoint {path} holds no parameter vector")
    saved_problem = payload.get("problem")
    if problem is not None and saved_problem is not None and saved_problem != problem:
        raise ValueError(f"checkpoint {path} belongs to problem {saved_problem!r}, not "
                         f"{problem!r}; use another hydra.run.dir or resume=false")
    if n_params is not None and theta.numel() != n_params:
        raise ValueError(f"checkpoint {path} has {theta.numel()} parameters but the problem has "
                         f"{n_params}; use another hydra.run.dir or resume=false")
    if not bool(torch.isfinite(theta).all()):
        raise ValueError(f"checkpoint {path} contains non-finite parameters")
    misfit = payload.get("misfit")
    try:
        problem_config = json.loads(payload.get("problem_config") or "{}")
    except ValueError:
        problem_config = {}
    return Checkpoint(iteration, theta, None if misfit is None else float(misfit), saved_problem,
                      problem_config)


class CheckpointWriter:
    """Callback rewriting ``checkpoint.pt`` after every outer iteration.

    Args:
        path: the checkpoint file.
        step_offset: iteration the run started from (a resumed run keeps counting).
        problem: problem name stored with the checkpoint (checked on resume).
        problem_config: the problem's settings, stored for comparison on resume.
    """

    def __init__(self, path: str | Path, step_offset: int = 0, problem: str | None = None,
                 problem_config: Mapping[str, Any] | None = None) -> None:
        self.path = Path(path)
        self.step_offset = int(step_offset)
        self.problem = problem
        self.problem_config = dict(problem_config or {})

    def __call__(self, record: IterationRecord) -> None:
        save_checkpoint(self.path, self.step_offset + record.iteration, record.theta,
                        record.misfit, self.problem, self.problem_config)
        return None


def save_torch(path: str | Path, obj: Any) -> Path:
    """``torch.save(obj)`` to ``path`` atomically, byte-identical for identical content."""
    path = Path(path)
    _atomic_write(path, lambda f: _torch_bytes(obj, f))
    return path
