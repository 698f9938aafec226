"""torchfit: fit material parameters of differentiable simulations to animated motion.

Layers (see DESIGN.md): ``linalg`` (sparse solves and their adjoints), ``physics``
(residuals, tangents, the differentiable equilibrium), ``params`` (parameterisations),
``problems`` (canonical problems), ``solvers`` (Gauss-Newton, Levenberg-Marquardt),
``logging`` (TensorBoard, progress, result files).

Importing torchfit leaves torch's default dtype alone: problems and physics make their
tensors in an explicit dtype (``problem.dtype``, float64 unless asked otherwise).
"""
__version__ = "0.1.0"
