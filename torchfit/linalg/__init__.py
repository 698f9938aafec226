"""Sparse linear algebra: patterns, differentiable solves, factorisation reuse, Krylov."""
from .backends import (BandedBackend, Backend, CGBackend, Factor, PardisoBackend, PardisoFactor,
                       PardisoPlan, ScipyBackend, SingularMatrixError, default_backend,
                       get_backend)
from .cg import CGLSResult, batched_cg, cgls
from .cudss import (CUDA_EXTRA, CudssBackend, CudssUnavailableError, GpuMemoryError,
                    cudss_available)
from .errors import BackendDeviceError
from .ldl import LdlBackend, LdlFactor
from .counters import COUNTERS, SolveCounters, counting, reset_counters
from .pardiso import PardisoError, PardisoUnavailableError, pardiso_available
from .pattern import FreeMatrixLayout, SparsePattern, coo_to_csr, csr_matrix
from .sparse_solve import DEFAULT_CACHE, FactorCache, sparse_solve
from .threads import blas_threads, set_threads

__all__ = [
    "BackendDeviceError", "BandedBackend", "Backend", "CUDA_EXTRA", "CudssBackend",
    "CudssUnavailableError", "GpuMemoryError", "cudss_available", "CGBackend", "LdlBackend", "LdlFactor", "CGLSResult", "COUNTERS", "DEFAULT_CACHE", "Factor",
    "FactorCache", "FreeMatrixLayout", "PardisoBackend", "PardisoError", "PardisoFactor", "PardisoPlan",
    "PardisoUnavailableError", "ScipyBackend", "SingularMatrixError", "SolveCounters",
    "SparsePattern", "batched_cg", "coo_to_csr", "csr_matrix", "blas_threads", "cgls", "counting", "default_backend",
    "get_backend", "pardiso_available", "reset_counters", "set_threads", "sparse_solve",
]
