"""torchfit: fit material parameters of differentiable simulations to animated motion.

Layers (see DESIGN.md): ``linalg`` (sparse solves and their adjoints), ``physics``
(residuals, tangents, the differentiable equilibrium), ``params`` (parameterisations),
``problems`` (canonical problems), ``solvers`` (Gauss-Newton, Levenberg-Marquardt),
``logging`` (TensorBoard, progress, result files).
"""
import torch as _torch

__version__ = "0.1.0"

# Fits are done in double precision unless a caller asks otherwise.
_torch.set_default_dtype(_torch.float64)
