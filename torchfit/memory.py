"""Sizes checked before allocation, and numpy files read by their headers first.

* :func:`memory_limit`: the bytes a problem may allocate: ``$TORCHFIT_MEMORY_LIMIT`` when
  set (bytes, or with a suffix ``K``, ``M``, ``G``, ``T``: ``TORCHFIT_MEMORY_LIMIT=8G``),
  else the memory available now (``MemAvailable`` of ``/proc/meminfo``, else
  ``os.sysconf``); ``None`` (no check) where neither says.
* :func:`check_allocation`: raises ``error`` (one line naming the setting, the size and the
  limit) when an estimate exceeds :func:`memory_limit`. An estimate is what the problem
  will hold at once (a lower bound: the solver's work arrays, the process itself, the
  tetrahedralisation and the outputs come on top; the short arm's fit peaks at about 70
  times its estimate above the bare process, docs/guide/resume.md), so a refused setting
  would have failed; an accepted one may still run short.
* :func:`npy_header`, :func:`npz_headers`: shape and dtype of a ``.npy`` file or of each
  array of a ``.npz`` without reading the data; :func:`load_npy` refuses (one line) a file
  that is not a ``.npy``, an object array, a file shorter than its header declares, or one
  that declares more than the memory limit, before reading its data.
"""
from __future__ import annotations

import os
import re
import zipfile
from pathlib import Path
from typing import Optional

import numpy as np

from .errors import ConfigurationError

#: The environment variable that sets the memory limit (bytes, or 512M, 8G, ...).
LIMIT_VARIABLE = "TORCHFIT_MEMORY_LIMIT"
_SUFFIX = {"": 1, "K": 2 ** 10, "M": 2 ** 20, "G": 2 ** 30, "T": 2 ** 40}


class MemoryLimitError(ConfigurationError):
    """A setting or file asks for more memory than is available (one line)."""


def size_text(nbytes: float) -> str:
    """``9.2e9`` -> ``'8.6 GiB'``."""
    for unit, scale in (("TiB", 2 ** 40), ("GiB", 2 ** 30), ("MiB", 2 ** 20), ("KiB", 2 ** 10)):
        if nbytes >= scale:
            return f"{nbytes / scale:.1f} {unit}"
    return f"{int(nbytes)} B"


def memory_limit() -> Optional[int]:
    """Bytes that may be allocated (module docstring); ``None`` when unknown."""
    given = os.environ.get(LIMIT_VARIABLE, "").strip()
    if given:
        match = re.fullmatch(r"(\d+(?:\.\d+)?)\s*([KMGT]?)(?:i?B)?", given, re.IGNORECASE)
        if match is None:
            raise ConfigurationError(f"{LIMIT_VARIABLE}={given}: not a size; give bytes or a "
                                     "number with K, M, G or T (e.g. 8G)")
        return int(float(match.group(1)) * _SUFFIX[match.group(2).upper()])
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, OSError, ValueError):
        return None


def check_allocation(setting: str, nbytes: float, what: str,
                     error: type[Exception] = MemoryLimitError,
                     advice: str = "choose a smaller value") -> None:
    """Raise ``error`` when ``nbytes`` (an estimate of ``what``) exceeds the limit; the
    line ends with ``advice`` (what to change)."""
    limit = memory_limit()
    if limit is not None and not nbytes <= limit:       # nan as well
        source = f"{LIMIT_VARIABLE}" if os.environ.get(LIMIT_VARIABLE, "").strip() else \
            "available memory"
        raise error(f"{setting}: needs about {size_text(nbytes)} for {what}, more than the "
                    f"{size_text(limit)} of {source}; {advice} (or set "
                    f"{LIMIT_VARIABLE} on a machine with more memory)")


def _header(f, where: str, error: type[Exception]) -> tuple[tuple[int, ...], np.dtype, int]:
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise ValueError(f"format version {version}")
    except Exception as err:  # noqa: BLE001 - numpy raises many kinds for a bad header
        raise error(f"{where}: not a numpy .npy array (its header cannot be read); write it "
                    "with np.save") from err
    if dtype.hasobject:
        raise error(f"{where}: holds Python objects (dtype {dtype}); give numbers, e.g. "
                    "np.save(file, np.asarray(values, dtype=float))")
    return tuple(int(n) for n in shape), dtype, f.tell()


def npy_header(path: Path, where: str, error: type[Exception] = ConfigurationError
               ) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of a ``.npy`` file (its data unread); refuses a short file."""
    try:
        with open(path, "rb") as f:
            shape, dtype, offset = _header(f, where, error)
    except OSError as err:
        raise error(f"{where}: cannot read it ({err.strerror or err})") from err
    declared = offset + int(np.prod(shape, dtype=np.float64) * dtype.itemsize)
    if Path(path).stat().st_size < declared:
        raise error(f"{where}: the file is truncated ({Path(path).stat().st_size} bytes, its "
                    f"header declares {declared} for shape {shape}); write it again")
    return shape, dtype


def npz_headers(path: Path, where: str, error: type[Exception] = ConfigurationError
                ) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """Shape and dtype of each array of a ``.npz`` (its data unread)."""
    out = {}
    try:
        with zipfile.ZipFile(path) as archive:
            for info in archive.infolist():
                name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
                with archive.open(info) as f:
                    shape, dtype, _ = _header(f, f"{where} ({info.filename})", error)
                out[name] = (shape, dtype)
    except (OSError, zipfile.BadZipFile, EOFError) as err:
        raise error(f"{where}: not a numpy .npz archive ({err})") from err
    return out


def array_bytes(shape: tuple[int, ...], dtype: np.dtype) -> float:
    """Bytes of an array of ``shape`` and ``dtype`` (a float: no overflow)."""
    return float(np.prod(shape, dtype=np.float64)) * np.dtype(dtype).itemsize


def load_npy(path: Path, where: str, error: type[Exception] = ConfigurationError) -> np.ndarray:
    """A ``.npy`` array, its header checked first (module docstring)."""
    shape, dtype = npy_header(path, where, error)
    check_allocation(where, array_bytes(shape, dtype), f"its array {shape} of {dtype}", error)
    try:
        return np.asarray(np.load(path, allow_pickle=False))
    except Exception as err:  # noqa: BLE001 - numpy raises many kinds for a bad file
        raise error(f"{where}: cannot read it as a numpy array "
                    f"({' '.join(str(err).split())[:120]})") from err
