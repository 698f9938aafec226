"""Sparse linear algebra: patterns, differentiable solves, factorisation reuse, Krylov."""
from .backends import (BandedBackend, Backend, CGBackend, Factor, ScipyBackend,
                       SingularMatrixError, get_backend)
from .cg import CGLSResult, batched_cg, cgls
from .counters import COUNTERS, SolveCounters, counting, reset_counters
from .pattern import SparsePattern
from .sparse_solve import DEFAULT_CACHE, FactorCache, sparse_solve
from .threads import blas_threads, set_threads

__all__ = [
    "BandedBackend", "Backend", "CGBackend", "CGLSResult", "COUNTERS", "DEFAULT_CACHE", "Factor",
    "FactorCache", "ScipyBackend", "SingularMatrixError", "SolveCounters", "SparsePattern",
    "batched_cg", "blas_threads", "cgls", "counting", "get_backend", "reset_counters",
    "set_threads", "sparse_solve",
]
