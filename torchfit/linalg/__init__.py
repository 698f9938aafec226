"""Sparse linear algebra: patterns, factorisation backends and their reuse, Krylov, counters."""
from .amg import AmgBackend, AmgUnavailableError, amg_available
from .backends import (BandedBackend, Backend, CGBackend, Factor, PardisoBackend, ScipyBackend,
                       SingularMatrixError, default_backend, get_backend)
from .cg import CGLSResult, batched_cg, cgls
from .counters import COUNTERS, counting
from .cudss import CudssBackend, CudssUnavailableError, GpuMemoryError, cudss_available
from .errors import BackendDeviceError
from .ldl import LdlBackend
from .pardiso import PardisoError, PardisoUnavailableError, pardiso_available
from .pattern import FreeMatrixLayout, SparsePattern, coo_to_csr
from .threads import blas_threads, set_threads

__all__ = [
    "AmgBackend", "AmgUnavailableError", "BackendDeviceError", "Backend", "BandedBackend",
    "CGBackend", "CGLSResult", "COUNTERS", "CudssBackend", "CudssUnavailableError", "Factor", "FreeMatrixLayout", "GpuMemoryError",
    "LdlBackend", "PardisoBackend", "PardisoError", "PardisoUnavailableError", "ScipyBackend",
    "SingularMatrixError", "SparsePattern", "batched_cg", "blas_threads", "cgls", "coo_to_csr",
    "amg_available", "counting", "cudss_available", "default_backend", "get_backend",
    "pardiso_available", "set_threads",
]
