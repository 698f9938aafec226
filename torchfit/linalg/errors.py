"""Errors of the linear-algebra layer shared by its backends (kept apart so that a backend
module never imports another)."""
from __future__ import annotations

from ..errors import SimulationError


class SingularMatrixError(SimulationError):
    """Raised when a system matrix cannot be factorised (or CG breaks down)."""


class BackendDeviceError(ValueError):
    """A backend was given tensors on a device it cannot use (one line naming both and
    the backend to use instead)."""


def cpu_only(backend: str, device: "object") -> BackendDeviceError:
    """The error of a CPU-only backend asked to factorise or solve tensors on ``device``."""
    return BackendDeviceError(
        f"the {backend} backend runs on the CPU, but the tensors are on {device}: use "
        "backend='cudss' (CUDA sparse direct solver, pip install 'torchfit[cuda]') or "
        "backend='cg' there, or move the problem to the CPU (problem.device=cpu)")
