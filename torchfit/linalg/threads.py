"""CPU threads of a run: torch's own kernels and the BLAS/OpenMP libraries loaded in the
process, through ``threadpoolctl``.

``torch.set_num_threads`` governs torch's own kernels only; scipy's LAPACK (the banded
Cholesky backend) runs on the OpenBLAS that numpy/scipy bundle, which starts one thread
per core. On a machine whose cores are shared with other jobs those threads spin and
wait (``docs/notes/threads.md``).
:func:`set_threads` sets both for the whole process (a sweep job with ``threads=1``).
A library loaded later (MKL, when the ``pardiso`` backend is first used) gets the same
limit through :func:`apply_requested_threads`.

``torch.set_num_threads`` also switches MKL's *dynamic* threading off (so that OpenMP
threads are not recreated between MKL and non-MKL regions), and MKL then runs even a tiny
vector function (``torch.sqrt`` of 384 doubles goes to MKL's VML) on every thread: on a
loaded machine that took 24-32 ms instead of 2 us. :func:`set_threads` switches it back on
in torch's own MKL (``MKL_Set_Dynamic(1)``), so MKL picks fewer threads for small calls;
figures in ``docs/notes/threads.md`` (``scripts/bench/threads.py``).
"""
from __future__ import annotations

import ctypes
import os

import torch
from threadpoolctl import threadpool_info, threadpool_limits

_REQUESTED: int | None = None


def _load_blas() -> None:
    import numpy  # noqa: F401  (make sure numpy's and scipy's BLAS are loaded, so that
    import scipy.linalg  # noqa: F401  threadpoolctl finds and limits them)


def set_threads(n: int) -> None:
    """Use ``n`` CPU threads in this process: ``torch.set_num_threads(n)``,
    ``threadpoolctl.threadpool_limits(n)`` for every BLAS and OpenMP library loaded
    (numpy's and scipy's OpenBLAS included), and MKL's dynamic threading back on (module
    docstring); kept until the process ends."""
    if n < 1:
        raise ValueError(f"thread count must be >= 1, got {n}")
    global _REQUESTED
    _load_blas()
    torch.set_num_threads(int(n))
    threadpool_limits(limits=int(n))
    # torch applies the count again (MKL dynamic off included) at a thread's first parallel
    # region: make that happen now in this thread, then switch dynamic threading back on
    torch.get_num_threads()
    mkl_dynamic(True)
    _REQUESTED = int(n)


def mkl_dynamic(on: bool) -> bool:
    """Switch the dynamic threading of the MKL inside torch's CPU library on or off (module
    docstring); ``False`` where that library exports no MKL (another BLAS build)."""
    try:
        library = ctypes.CDLL(os.path.join(os.path.dirname(torch.__file__), "lib",
                                           "libtorch_cpu.so"))
        set_dynamic = library.MKL_Set_Dynamic     # the C interface (int by value)
    except (OSError, AttributeError):
        return False
    set_dynamic.argtypes = [ctypes.c_int]
    set_dynamic.restype = None
    set_dynamic(1 if on else 0)
    return True


def requested_threads() -> int | None:
    """The count of the last :func:`set_threads` call (``None``: never called)."""
    return _REQUESTED


def apply_requested_threads() -> None:
    """Limit the libraries loaded since :func:`set_threads` (e.g. MKL) to its count."""
    if _REQUESTED is not None:
        threadpool_limits(limits=_REQUESTED)


def blas_threads() -> dict[str, int]:
    """``{library file: threads}`` of the BLAS libraries loaded (for benchmark reports)."""
    _load_blas()
    return {os.path.basename(info["filepath"]): int(info["num_threads"])
            for info in threadpool_info() if info.get("user_api") == "blas"}

