"""Sparse linear algebra: patterns, factorisation backends and their reuse, Krylov, counters."""
from .backends import (AmgBackend, AmgUnavailableError, BandedBackend, Backend, CGBackend,
                       CudssBackend, CudssUnavailableError, Factor, GpuMemoryError, LdlBackend,
                       PardisoBackend, PardisoError, PardisoUnavailableError, ScipyBackend,
                       amg_available, cudss_available, default_backend,
                       get_backend, pardiso_available)
from .cg import CGLSResult, batched_cg, cgls
from .counters import SolveCounters, counting
from .errors import BackendDeviceError, SingularMatrixError
from .pattern import FreeMatrixLayout, SparsePattern, coo_to_csr
from .threads import blas_threads, set_threads

__all__ = [
    "AmgBackend", "AmgUnavailableError", "BackendDeviceError", "Backend", "BandedBackend",
    "CGBackend", "CGLSResult", "CudssBackend", "CudssUnavailableError", "Factor", "FreeMatrixLayout", "GpuMemoryError",
    "LdlBackend", "PardisoBackend", "PardisoError", "PardisoUnavailableError", "ScipyBackend",
    "SingularMatrixError", "SolveCounters", "SparsePattern", "batched_cg", "blas_threads", "cgls", "coo_to_csr",
    "amg_available", "counting", "cudss_available", "default_backend", "get_backend",
    "pardiso_available", "set_threads",
]
