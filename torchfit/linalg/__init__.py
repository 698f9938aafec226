"""Sparse linear algebra: patterns, factorisation backends and their reuse, Krylov, counters."""
from .backends import (AMG_EXTRA, CUDA_EXTRA, PARDISO_EXTRA, AmgBackend, AmgUnavailableError,
                       BandedBackend, Backend, CGBackend, CudssBackend, CudssUnavailableError,
                       Factor, GpuMemoryError, LdlBackend, PardisoBackend, PardisoError,
                       PardisoUnavailableError, ScipyBackend, amg_available, cudss_available,
                       default_backend, get_backend, gpu_memory_error, pardiso_available)
from .cg import CGLSResult, batched_cg, cgls
from .counters import SolveCounters, active_scopes, counting, credit, within
from .errors import BackendDeviceError, SingularMatrixError
from .estimators import column_norms, frobenius_norm_sq, power_norm_sq
from .pattern import FreeMatrixLayout, SparsePattern, coo_to_csr, csr_matrix
from .threads import blas_threads, set_threads

__all__ = [
    "AMG_EXTRA", "AmgBackend", "AmgUnavailableError", "BackendDeviceError", "Backend",
    "BandedBackend", "CGBackend", "CGLSResult", "CUDA_EXTRA", "CudssBackend",
    "CudssUnavailableError", "Factor", "FreeMatrixLayout", "GpuMemoryError", "LdlBackend",
    "PARDISO_EXTRA", "PardisoBackend", "PardisoError", "PardisoUnavailableError",
    "ScipyBackend", "SingularMatrixError", "SolveCounters", "SparsePattern", "active_scopes",
    "amg_available", "batched_cg", "blas_threads", "cgls", "column_norms", "coo_to_csr",
    "counting", "credit", "csr_matrix", "cudss_available", "default_backend",
    "frobenius_norm_sq", "get_backend", "gpu_memory_error", "pardiso_available",
    "power_norm_sq", "set_threads", "within",
]
