"""Linear-solve backends behind one :class:`Factor` interface, and the choice among them.

A backend analyses a sparsity pattern once, factorises numerically once per matrix, and
every solve of that matrix (the adjoint, each Jacobian column, a trial step) reuses the
factor. One module per backend: SuperLU (:mod:`.superlu`, always there), banded Cholesky
(:mod:`.banded`), Jacobi-preconditioned CG (:mod:`.cg`), MKL PARDISO (:mod:`.pardiso_mkl`),
QDLDL (:mod:`.ldl`), smoothed-aggregation AMG (:mod:`.amg`) and cuDSS on CUDA
(:mod:`.cudss`); :mod:`.choice` picks one for a device and a size.
"""
from .amg import AMG_EXTRA, AmgBackend, AmgUnavailableError, amg_available
from .banded import BandedBackend
from .base import Backend, Factor
from .cg import CGBackend
from .choice import default_backend, get_backend
from .pardiso import PardisoBackend
from .superlu import ScipyBackend
from .cudss import (CUDA_EXTRA, CudssBackend, CudssUnavailableError, GpuMemoryError,
                    cudss_available, gpu_memory_error)
from .ldl import LdlBackend
from .pardiso_mkl import PARDISO_EXTRA, PardisoError, PardisoUnavailableError, pardiso_available

__all__ = ["AMG_EXTRA", "AmgBackend", "AmgUnavailableError", "Backend", "BandedBackend",
           "CGBackend", "CUDA_EXTRA", "CudssBackend", "CudssUnavailableError", "Factor",
           "GpuMemoryError", "LdlBackend", "PARDISO_EXTRA", "PardisoBackend", "PardisoError",
           "PardisoUnavailableError", "ScipyBackend", "amg_available", "cudss_available",
           "default_backend", "get_backend", "gpu_memory_error", "pardiso_available"]
