"""Thread count of the BLAS/LAPACK libraries loaded in this process (OpenBLAS).

``torch.set_num_threads`` governs torch's own kernels only; scipy's LAPACK (the banded
Cholesky backend) runs on the OpenBLAS that numpy/scipy bundle, which starts one thread
per core. On a machine whose cores are shared with other jobs those threads spin and
wait: a banded Cholesky of the membrane2d tangent was measured 4-13x slower with two
OpenBLAS threads than with one while another process kept a core busy. This module sets
the count at run time the way ``threadpoolctl`` does (not a dependency here): it finds
the loaded OpenBLAS libraries in ``/proc/self/maps`` and calls their
``openblas_set_num_threads``. Where that is not possible it does nothing (the
``OPENBLAS_NUM_THREADS`` environment variable, set before Python starts, always works).
"""
from __future__ import annotations

import ctypes
from pathlib import Path

_SETTERS = ("openblas_set_num_threads", "openblas_set_num_threads64_",
            "scipy_openblas_set_num_threads", "scipy_openblas_set_num_threads64_")


def _loaded_openblas() -> list[str]:
    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError:  # pragma: no cover - not Linux
        return []
    paths = {line.split()[-1] for line in maps.splitlines()
             if "openblas" in line.lower() and line.split()[-1].startswith("/")}
    return sorted(paths)


def set_blas_threads(n: int) -> int:
    """Use ``n`` threads in every loaded OpenBLAS; returns how many libraries were set."""
    if n < 1:
        raise ValueError(f"thread count must be >= 1, got {n}")
    import numpy  # noqa: F401  (make sure numpy's and scipy's BLAS are loaded)
    import scipy.linalg  # noqa: F401

    done = 0
    for path in _loaded_openblas():
        try:
            lib = ctypes.CDLL(path)
        except OSError:  # pragma: no cover
            continue
        for name in _SETTERS:
            setter = getattr(lib, name, None)
            if setter is not None:
                setter(ctypes.c_int(int(n)))
                done += 1
                break
    return done


def blas_threads() -> dict[str, int]:
    """``{library: threads}`` of the loaded OpenBLAS libraries (for benchmark reports)."""
    out: dict[str, int] = {}
    for path in _loaded_openblas():
        try:
            lib = ctypes.CDLL(path)
        except OSError:  # pragma: no cover
            continue
        for name in ("openblas_get_num_threads", "openblas_get_num_threads64_",
                     "scipy_openblas_get_num_threads", "scipy_openblas_get_num_threads64_"):
            getter = getattr(lib, name, None)
            if getter is not None:
                out[Path(path).name] = int(getter())
                break
    return out
