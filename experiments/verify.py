"""Verify the derivatives of a problem's residual: Taylor, dot-product and FD checks.

    python experiments/verify.py problem=spring1d
    python experiments/verify.py problem=spring1d at=truth perturbation=0.05 seed=3

The point is the problem's initial guess (``at=initial``) or the parameters of its true
field (``at=truth``), offset by ``perturbation`` times a seeded Gaussian vector so that it
is generic (for an ``exp`` parameterisation that is a relative change of the field by
about ``perturbation``; for the identity the offset is scaled by ``|theta|``). Prints the
report, writes ``verify.json`` into the run directory and exits 1 when a check fails,
2 on a bad configuration (``error: ...`` on stderr, nothing written).
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any, NoReturn

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from torchfit.config import register_configs
from torchfit.linalg.threads import set_blas_threads
from torchfit.problems import InverseProblem, ProblemConfigError, build_problem
from torchfit.verification import verify

POINTS = ("initial", "truth")
#: the offset draws from seed + OFFSET_STREAM so that it is independent of the
#: directions ``verify`` draws from ``seed``
OFFSET_STREAM = 1_000_003

_task_started = False


class VerifyConfigError(ValueError):
    """A setting of ``verify.yaml`` is invalid."""


def _fail(message: str) -> NoReturn:
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def check_config(cfg: DictConfig) -> None:
    if cfg.at not in POINTS:
        raise VerifyConfigError(f"at={cfg.at!r} is not a point to verify at; choose one of "
                                f"{POINTS}")
    if not (math.isfinite(cfg.perturbation) and cfg.perturbation >= 0):
        raise VerifyConfigError(f"perturbation must be a finite number >= 0, got "
                                f"{cfg.perturbation}")
    for name in ("taylor_tol", "dot_tol", "fd_tol"):
        value = cfg[name]
        if not (math.isfinite(value) and value > 0):
            raise VerifyConfigError(f"{name} must be a positive number, got {value}")
    if int(cfg.get("threads", 0)) < 0:
        raise VerifyConfigError(f"threads must be >= 0 (0: default), got {cfg.threads}")


def base_point(problem: InverseProblem, at: str) -> torch.Tensor:
    if at == "initial":
        return problem.theta0.detach().clone()
    if problem.field_true is None:
        raise VerifyConfigError(f"at=truth needs a true field, but problem {problem.name} has "
                                "none (user targets); use at=initial")
    return problem.parameterization.inverse(problem.field_true).detach()


def perturbed(problem: InverseProblem, theta: torch.Tensor, perturbation: float,
              seed: int) -> torch.Tensor:
    """``theta`` plus a seeded Gaussian offset of relative size ``perturbation``."""
    if perturbation == 0:
        return theta
    generator = torch.Generator().manual_seed(int(seed) + OFFSET_STREAM)
    xi = torch.randn(theta.shape, generator=generator, dtype=torch.float64).to(theta)
    if getattr(problem.parameterization, "transform", "exp") == "exp":
        scale = torch.ones_like(theta)           # log-field: additive = relative change
    else:
        rms = float(torch.linalg.vector_norm(theta)) / math.sqrt(max(theta.numel(), 1))
        scale = torch.where(theta != 0, theta.abs(), torch.full_like(theta, rms or 1.0))
    return theta + perturbation * scale * xi


@hydra.main(config_path="../conf", config_name="verify", version_base="1.3")
def main(cfg: DictConfig) -> None:
    global _task_started
    _task_started = True
    try:
        check_config(cfg)
        threads = int(cfg.get("threads", 0))
        if threads > 0:
            torch.set_num_threads(threads)
            set_blas_threads(threads)
        problem = build_problem(cfg.problem.name, cfg.problem)
        theta = perturbed(problem, base_point(problem, cfg.at), float(cfg.perturbation),
                          int(cfg.seed))
        residual = problem.residual()
    except (ProblemConfigError, VerifyConfigError) as exc:
        _fail(str(exc))
    except ValueError as exc:      # e.g. a parameterisation refusing the true field
        _fail(str(exc))

    report = verify(residual, theta, seed=int(cfg.seed), taylor_tol=float(cfg.taylor_tol),
                    dot_tol=float(cfg.dot_tol), fd_tol=float(cfg.fd_tol))
    print(f"problem {problem.name} at {cfg.at} + {cfg.perturbation:g} * random offset "
          f"(seed {cfg.seed})")
    print(report.format())

    result: dict[str, Any] = report.to_dict()
    result["problem"] = problem.describe()
    result["point"] = {"at": cfg.at, "perturbation": float(cfg.perturbation),
                       "theta_norm": float(torch.linalg.vector_norm(theta))}
    result["config"] = OmegaConf.to_container(cfg, resolve=True)
    out = Path(HydraConfig.get().runtime.output_dir) / "verify.json"
    out.write_text(json.dumps(result, indent=2, allow_nan=False) + "\n")
    print(f"wrote {out}")
    if not report.passed:
        sys.exit(1)


if __name__ == "__main__":
    register_configs()
    try:
        main()
    except SystemExit as exit_:
        # Hydra exits 1 on a composition error (misspelt or mistyped override) before
        # the task runs; that is a bad configuration too, not a failed check.
        if exit_.code == 1 and not _task_started:
            _fail("invalid configuration (see Hydra's message above)")
        raise
