"""Files of a run directory, written atomically and byte-identically for identical content.

:func:`write_json` (strict JSON: NaN and infinities become ``null``), :func:`save_params`
(``params.pt``: ``{'theta', 'field', 'field_name'}`` as CPU tensors; ``field.npy``) and
:func:`save_torch` (any ``torch.save``-able object, e.g. the checkpoint of
:mod:`torchfit.run.checkpoint`). Every file goes to a temporary file in the same directory
that is then renamed over the target, so none is ever half-written; ``torch.save`` writes
into the open file (never to a path, whose name would end up inside its zip archive). What
``result.json`` and ``checkpoint.pt`` hold is :mod:`torchfit.run`'s contract. A writer
killed between the two leaves its temporary file (``.<name>.<pid>.<thread>.tmp``, or
``<name>.tmp.vtu`` of the body's ParaView file): :func:`remove_stale_temporaries` removes
them when the next run or resume takes the directory.
"""
from __future__ import annotations

import dataclasses
import enum
import json
import math
import os
import re
import shutil
import threading
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import torch
from torch import Tensor

from ..records import IterationRecord

RESULT_FILE = "result.json"
PARAMS_FILE = "params.pt"
FIELD_FILE = "field.npy"
CHECKPOINT_FILE = "checkpoint.pt"


def jsonable(value: Any) -> Any:
    """Plain JSON types; NaN and infinities become ``None``; an Enum becomes its value."""
    if isinstance(value, enum.Enum):
        return jsonable(value.value)
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Tensor):
        return jsonable(value.detach().cpu().tolist())
    if isinstance(value, np.generic):
        return jsonable(value.item())
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return jsonable(dataclasses.asdict(value))
    return str(value)


def atomic_write(path: Path, write, mode: str = "wb") -> None:
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
    except BaseException as error:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(error, OSError) and error.errno is not None and not error.filename:
            # torch.save and write(f) raise without a file name: name the file being written
            raise OSError(error.errno, error.strerror or str(error), str(path)) from error
        raise


#: Suffix of a folder of the run being written (renamed to its name when whole).
PARTIAL = ".partial"


def write_folder(target: Path, fill: Callable[[Path], Any]) -> Any:
    """Fill a new folder beside ``target`` (``.<name>.partial``, by ``fill(folder)``), then
    put it in ``target``'s place: a kill or a full disk never leaves a partial folder
    (0-byte files) under the name a user opens. Returns what ``fill`` returns."""
    partial = target.with_name(f".{target.name}{PARTIAL}")
    shutil.rmtree(partial, ignore_errors=True)
    try:
        partial.mkdir(parents=True)
        out = fill(partial)
        if target.exists():
            shutil.rmtree(target)
        partial.rename(target)
        return out
    finally:
        shutil.rmtree(partial, ignore_errors=True)

#: Names of the temporary files of :func:`atomic_write` and of the body's ParaView writer.
_TEMPORARY = re.compile(r"^\..+\.\d+\.\d+\.tmp$|^.+\.tmp\.vtu$")


def remove_stale_temporaries(run_dir: Path) -> list[Path]:
    """Delete the temporary files a killed writer left in ``run_dir`` (and below); only
    for the process that holds the run directory (:mod:`torchfit.run.lock`), before it
    writes. Returns what was removed."""
    removed = []
    if run_dir.is_dir():
        for partial in sorted(run_dir.glob(f".*{PARTIAL}")):
            if partial.is_dir() and not partial.is_symlink():
                shutil.rmtree(partial)
                removed.append(partial)
        for path in sorted(run_dir.rglob("*")):
            if _TEMPORARY.match(path.name) and path.is_file() and not path.is_symlink():
                path.unlink()
                removed.append(path)
    return removed


def _torch_bytes(obj: Any, f) -> None:
    """``torch.save`` into an open file: the same bytes for the same content, whatever the
    file's name, directory or process."""
    torch.save(obj, f)


def write_json(path: str | Path, data: Mapping[str, Any]) -> Path:
    """Write strict JSON (atomically)."""
    path = Path(path)

    def write(f) -> None:
        json.dump(jsonable(data), f, indent=2, allow_nan=False)
        f.write("\n")

    atomic_write(path, write, "w")
    return path


def history_rows(history: list[IterationRecord], step_offset: int = 0) -> list[dict[str, Any]]:
    """One dict per record: ``iteration`` then every scalar of the record."""
    return [rec.row(step_offset) for rec in history]


def save_params(run_dir: str | Path, theta: Tensor, field: Tensor,
                field_name: str = "k", transform: str | None = None,
                meaning: Mapping[str, Any] | None = None) -> tuple[Path, Path]:
    """Write ``params.pt`` (theta, field, the field's name and, if given, the
    parameterisation's transform and the parameters' ``meaning``: what ``init=`` checks)
    and ``field.npy``; returns both paths."""
    run_dir = Path(run_dir)
    theta_cpu = theta.detach().cpu().clone()
    field_cpu = field.detach().cpu().clone()
    params_path = run_dir / PARAMS_FILE
    payload: dict[str, Any] = {"theta": theta_cpu, "field": field_cpu, "field_name": field_name}
    if transform is not None:
        payload["transform"] = transform
    if meaning is not None:
        payload["meaning"] = dict(meaning)
    atomic_write(params_path, lambda f: _torch_bytes(payload, f))
    field_path = run_dir / FIELD_FILE
    atomic_write(field_path, lambda f: np.save(f, field_cpu.numpy()))
    return params_path, field_path


def save_torch(path: str | Path, obj: Any) -> Path:
    """``torch.save(obj)`` to ``path`` atomically, byte-identical for identical content."""
    path = Path(path)
    atomic_write(path, lambda f: _torch_bytes(obj, f))
    return path
