"""Which backend: :func:`default_backend` picks one for a device, a dimension and a size;
:func:`get_backend` makes one by name.

The backends (one module each): ``scipy`` (:mod:`.superlu`, CPU, always there), ``banded``
(:mod:`.banded`, thin meshes), ``ldl`` (:mod:`.ldl`, qdldl), ``pardiso`` (:mod:`.pardiso`,
MKL, the 3-D default on the CPU where installed), ``amg`` (:mod:`.amg`, large 3-D bodies
with few solves per factorisation), ``cudss`` (:mod:`.cudss`, CUDA) and ``cg`` (:mod:`.cg`,
any device). Measured speeds and the alternatives rejected: ``docs/notes/backends.md``.
"""
from __future__ import annotations

import torch

from .amg import AmgBackend, amg_available
from .banded import BandedBackend
from .base import Backend
from .cg import CGBackend
from .ldl import LdlBackend
from .pardiso import PardisoBackend
from .pardiso_mkl import pardiso_available
from .superlu import ScipyBackend


#: free dofs above which :func:`default_backend` picks ``amg`` for a 3-D problem on the CPU
#: that makes few solves per factorisation (measured crossover: ``docs/notes/amg.md``)
AMG_MIN_DOFS = 20_000
#: the most solves (right-hand-side columns) per factorisation for which ``amg`` is picked
#: (a forward solve and its adjoint: 2; a dense Jacobian: one per parameter, 192 on the arm)
AMG_MAX_SOLVES = 4


def default_backend(dim: int, device: torch.device | str = "cpu", n_dofs: int | None = None,
                    solves_per_factor: int = 1) -> str:
    """The backend a new problem should use: ``'pardiso'`` for 3-D problems on the CPU
    when MKL PARDISO is installed (several times faster than SuperLU there), else
    ``'scipy'``; but ``'amg'`` (pyamg installed) for a 3-D CPU problem of more than
    :data:`AMG_MIN_DOFS` free dofs (``n_dofs``, when the caller knows it) whose use makes at
    most :data:`AMG_MAX_SOLVES` solves per factorisation (``solves_per_factor``: a
    simulation and its gradient, not a Jacobian's many columns, where the factor's cheap
    solves win at every size measured); on CUDA ``'cudss'`` where nvmath-python and cuDSS
    import (``torchfit[cuda]``), else ``'cg'``; ``'cg'`` on any other device. (Existing
    problems keep their own defaults.)"""
    kind = torch.device(device).type
    if kind == "cuda":
        from .cudss import cudss_available

        return "cudss" if cudss_available() else "cg"
    if kind != "cpu":
        return "cg"
    if int(dim) == 3 and n_dofs is not None and n_dofs > AMG_MIN_DOFS \
            and solves_per_factor <= AMG_MAX_SOLVES and amg_available():
        return "amg"
    if int(dim) == 3 and pardiso_available():
        return "pardiso"
    return "scipy"


def get_backend(name: str | Backend) -> Backend:
    """``'scipy'``, ``'banded'``, ``'ldl'``, ``'pardiso'``, ``'amg'``, ``'cudss'`` or ``'cg'``
    (or an object with ``factorize``).

    ``'pardiso'`` without its extra raises :class:`~.pardiso_mkl.PardisoUnavailableError`,
    ``'cudss'`` without CUDA or ``torchfit[cuda]`` :class:`~.cudss.CudssUnavailableError`.
    """
    if not isinstance(name, str):
        return name
    if name == "scipy":
        return ScipyBackend()
    if name == "banded":
        return BandedBackend()
    if name == "ldl":
        return LdlBackend(fallback=ScipyBackend())
    if name == "pardiso":
        return PardisoBackend()
    if name == "cg":
        return CGBackend()
    if name == "amg":
        return AmgBackend(fallback=PardisoBackend() if pardiso_available() else ScipyBackend())
    if name == "cudss":
        from .cudss import CudssBackend

        return CudssBackend()
    raise ValueError(f"unknown linear-solve backend {name!r}; choose 'scipy' (CPU direct), "
                     "'banded' (CPU banded Cholesky, SPD), 'ldl' (CPU sparse LDL^T, "
                     "SPD, qdldl), 'pardiso' (CPU, MKL PARDISO, "
                     "optional extra), 'amg' (CPU, AMG-preconditioned CG, pyamg), 'cudss' (CUDA sparse direct, optional extra "
                     "torchfit[cuda]) or 'cg' (torch CG, CPU or CUDA)")
