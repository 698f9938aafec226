"""The on-disk cache of tetrahedral meshes: the same surface and options give the same tetrahedra.

fTetWild is not deterministic (its output changes from run to run and with the number of
threads); the first build of a surface is stored under a key that hashes the input (vertex
and face bytes), the options and the pytetwild version (:func:`cache_key`), and every later
call reads the stored arrays bit for bit. Entries are written atomically and never
overwritten by a concurrent build (:func:`write_entry`).
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
import logging
from pathlib import Path

import numpy as np

from .options import TetOptions

log = logging.getLogger(__name__)

#: Version of the cache file layout (part of the key: a new layout never reads old files).
_CACHE_FORMAT = "torchfit-tetmesh-1"


def default_cache_dir() -> Path:
    """``$TORCHFIT_CACHE_DIR/tetmesh`` when that variable is set, else
    ``~/.cache/torchfit/tetmesh``."""
    root = os.environ.get("TORCHFIT_CACHE_DIR")
    if root:
        return Path(root).expanduser() / "tetmesh"
    return Path.home() / ".cache" / "torchfit" / "tetmesh"


def cache_key(vertices: np.ndarray, faces: np.ndarray, options: TetOptions,
              version: str) -> str:
    """sha256 hex digest of the float64 vertex bytes, the int64 face bytes (little-endian,
    C order, with their shapes), the options' JSON and the pytetwild version."""
    v = np.ascontiguousarray(vertices, dtype="<f8")
    f = np.ascontiguousarray(faces, dtype="<i8")
    h = hashlib.sha256()
    h.update(json.dumps({"format": _CACHE_FORMAT, "vertices": list(v.shape),
                         "faces": list(f.shape)}).encode())
    h.update(v.tobytes())
    h.update(f.tobytes())
    h.update(json.dumps(options.as_dict(), sort_keys=True).encode())
    h.update(f"pytetwild {version}".encode())
    return h.hexdigest()


# -- the cache ---------------------------------------------------------------------------
def read_entry(path: Path, key: str) -> tuple[np.ndarray, np.ndarray, float]:
    with np.load(path, allow_pickle=False) as data:
        stored_key = str(data["key"])
        points = np.ascontiguousarray(data["points"])
        cells = np.ascontiguousarray(data["cells"])
        build_seconds = float(data["build_seconds"])
    if stored_key != key:
        raise ValueError(f"it holds key {stored_key[:12]}..., not {key[:12]}...")
    if (points.dtype != np.float64 or points.ndim != 2 or points.shape[1] != 3
            or cells.dtype != np.int64 or cells.ndim != 2 or cells.shape[1] != 4
            or len(cells) == 0):
        raise ValueError(f"arrays of the wrong type or shape (points {points.dtype} "
                         f"{points.shape}, cells {cells.dtype} {cells.shape})")
    if cells.min() < 0 or cells.max() >= len(points):
        raise ValueError("cell vertex index out of range")
    return points, cells, build_seconds


def write_entry(path: Path, key: str, points: np.ndarray, cells: np.ndarray,
                 build_seconds: float, options: TetOptions, version: str,
                 overwrite: bool, extra: dict[str, np.ndarray] | None = None) -> bool | None:
    """Store an entry atomically (``extra``: more named arrays, e.g. the canonical
    surface). ``True``: stored; ``False``: another writer's entry was already there (kept,
    never overwritten unless ``overwrite``); ``None``: the cache is not writable (warned)."""
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{key[:16]}.", suffix=".npz.tmp", dir=path.parent)
        with os.fdopen(fd, "wb") as out:
            np.savez(out, points=points, cells=cells, key=np.str_(key),
                     build_seconds=np.float64(build_seconds),
                     options=np.str_(json.dumps(options.as_dict(), sort_keys=True)),
                     pytetwild=np.str_(version), **(extra or {}))
            out.flush()
            os.fsync(out.fileno())
        if overwrite:
            os.replace(tmp, path)
            tmp = None
            return True
        try:
            os.link(tmp, path)                        # atomic, and never overwrites
        except FileExistsError:
            return False
        except OSError:                               # no hard links here: rename instead
            if path.exists():
                return False
            os.replace(tmp, path)
            tmp = None
        return True
    except OSError as e:
        log.warning(f"cannot write the tetrahedral mesh cache {path} "
                    f"({' '.join(str(e).split())}); continuing without caching")
        return None
    finally:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass

