"""The derivative checks of a problem at a chosen point, and ``verify.json``.

:func:`verify` runs :func:`torchfit.verification.verify` (Taylor, dot-product and
finite-difference checks of the residual's Jacobian) at :func:`verification_point`: the
initial guess or the truth, plus a seeded Gaussian offset so that the point is generic.
Its settings are :class:`~.options.VerifyOptions`; every one is checked before anything is
written. ``verify.json`` (in ``run_dir``, if given): the report
(:meth:`~torchfit.verification.VerificationReport.to_dict`), ``problem`` (sizes),
``point`` (``at``, ``perturbation``, ``theta_norm``) and ``config``.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, Mapping

import torch
from torch import Tensor

from ..linalg import set_threads
from ..problems import InverseProblem
from ..reporting import write_json
from ..verification import VerificationReport
from ..verification import verify as verify_residual
from .directory import check_writable
from .options import FitConfigError, VerifyOptions, VerifyPoint, plain_settings

VERIFY_FILE = "verify.json"
#: The offset draws from ``seed + OFFSET_STREAM``: independent of the directions ``verify``
#: draws from ``seed``.
OFFSET_STREAM = 1_000_003


def verification_point(problem: InverseProblem, at: str = VerifyOptions.at,
                       perturbation: float = VerifyOptions.perturbation,
                       seed: int = VerifyOptions.seed) -> Tensor:
    """``theta`` at the initial guess or the truth, plus a seeded Gaussian offset of relative
    size ``perturbation`` (additive on a log-field; scaled by ``|theta|`` otherwise)."""
    dataclasses.replace(VerifyOptions(), at=at, perturbation=perturbation).check()
    if at == VerifyPoint.initial:
        theta = problem.theta0.detach().clone()
    elif problem.field_true is None:
        raise FitConfigError(f"at=truth needs a true field, but {problem.name} has none (user "
                             "targets); use at=initial")
    else:
        theta = problem.true_theta().detach()
    if perturbation == 0:
        return theta
    generator = torch.Generator().manual_seed(int(seed) + OFFSET_STREAM)
    xi = torch.randn(theta.shape, generator=generator, dtype=torch.float64).to(theta)
    if str(getattr(problem.parameterization, "transform", "exp")) == "exp":
        scale = torch.ones_like(theta)
    else:
        rms = float(torch.linalg.vector_norm(theta)) / math.sqrt(max(theta.numel(), 1))
        scale = torch.where(theta != 0, theta.abs(), torch.full_like(theta, rms or 1.0))
    return theta + perturbation * scale * xi


def verify(problem: InverseProblem, *, run_dir: str | Path | None = None,
           options: VerifyOptions | None = None, config: Mapping[str, Any] | None = None,
           **settings: Any) -> VerificationReport:
    """Taylor, dot-product and finite-difference checks of ``problem``'s Jacobian at
    :func:`verification_point`; writes ``verify.json`` into ``run_dir`` (if given).

    Args:
        options: :class:`~.options.VerifyOptions` (default: its defaults).
        config: the settings stored in ``verify.json`` (default: the problem's).
        settings: :class:`~.options.VerifyOptions` fields that replace those of
            ``options`` (``at="truth"``, ``seed=3``, ...).
    Returns:
        the :class:`~torchfit.verification.VerificationReport` (``passed``).
    Raises:
        FitConfigError: a bad or unknown setting (before anything is written).
    """
    known = {f.name for f in dataclasses.fields(VerifyOptions)}
    unknown = sorted(set(settings) - known)
    if unknown:
        raise FitConfigError(f"unknown verify setting(s) {unknown}; the settings are "
                             f"{sorted(known)}")
    options = dataclasses.replace(options or VerifyOptions(), **settings)
    options.check()
    theta = verification_point(problem, options.at, options.perturbation, options.seed)
    run_path = None if run_dir is None else Path(run_dir).resolve()
    if run_path is not None:
        check_writable(run_path)
    if options.threads > 0:
        set_threads(options.threads)
    report = verify_residual(problem.residual(), theta, seed=int(options.seed),
                             taylor_tol=options.taylor_tol, dot_tol=options.dot_tol,
                             fd_tol=options.fd_tol)
    if run_path is not None:
        out: dict[str, Any] = report.to_dict()
        out["problem"] = problem.describe()
        out["point"] = {"at": options.at, "perturbation": float(options.perturbation),
                        "theta_norm": float(torch.linalg.vector_norm(theta))}
        out["config"] = dict(config) if config is not None else {
            "problem": plain_settings(problem.cfg)}
        run_path.mkdir(parents=True, exist_ok=True)
        write_json(run_path / VERIFY_FILE, out)
    return report
