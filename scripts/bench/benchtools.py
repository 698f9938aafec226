"""What every benchmark script shares: machine description and the JSON report.

Benchmarks print their figures as JSON (and optionally write them to a file) so that
notes and CI logs quote measured numbers, never guesses.
"""
from __future__ import annotations

import dataclasses
import gc
import json
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import scipy
import torch
import torch.autograd.forward_ad as fwAD

from torchfit.linalg import counting
from torchfit.solvers.gauss_newton import GaussNewtonConfig, gauss_newton


def machine_info() -> dict[str, Any]:
    """Versions, thread settings and load of the machine the figures come from."""
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        affinity = None
    return {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "torch_num_threads": torch.get_num_threads(),
        "torch_num_interop_threads": torch.get_num_interop_threads(),
        "cpu_count": os.cpu_count(),
        "cpu_affinity": affinity,
        "openmp": torch.backends.openmp.is_available(),
        "mkl": torch.backends.mkl.is_available(),
        "env": {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS",
                                                 "OPENBLAS_NUM_THREADS")},
        "loadavg": loadavg(),
    }


def loadavg() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:  # pragma: no cover
        return None


def emit_report(report: dict[str, Any], out: Path | None) -> None:
    """Print the report as JSON and, if ``out`` is given, write it there too."""
    text = json.dumps(report, indent=2)
    print(text)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text + "\n")


def stats(times: list[float]) -> dict[str, Any]:
    """Median, min and max of repeated wall times (seconds)."""
    return {"median_s": statistics.median(times), "min_s": min(times),
            "max_s": max(times), "repeats": len(times),
            "all_s": [round(t, 6) for t in times]}


def timed(fn: Callable[[], Any]) -> tuple[float, Any, dict[str, int]]:
    """Run ``fn`` once; return (seconds, result, counter delta)."""
    gc.disable()  # as timeit does: no collector pauses inside the timed call
    try:
        with counting() as delta:
            start = time.perf_counter()
            out = fn()
            elapsed = time.perf_counter() - start
            counts = delta.as_dict()  # the delta is live: snapshot it inside the block
    finally:
        gc.enable()
    return elapsed, out, counts


def same_counts(all_counts: list[dict[str, int]]) -> dict[str, Any]:
    """The counts of one repeat, flagged if repeats disagree (they must not)."""
    first = all_counts[0]
    out: dict[str, Any] = dict(first)
    if any(c != first for c in all_counts[1:]):
        out["inconsistent_across_repeats"] = all_counts
    return out


class ProblemBench:
    """Forward, backward-after-forward, ``J v`` and ``J^T w`` of one problem instance.

    Args:
        problem: an inverse problem with ``equilibrium``, ``simulate``,
            ``parameterization``, ``residual()``, ``theta0`` and ``data``.
        repeats: timed repeats (after one warm-up).
        seed: seeds the evaluation point and the random directions.
        state_shape: shape of ``simulate``'s output (the cotangent ``g`` of backward).
        build_s: seconds it took to build ``problem`` (reported).
    """

    def __init__(self, problem: Any, repeats: int, seed: int, state_shape: tuple[int, ...],
                 build_s: float) -> None:
        self.problem, self.repeats, self.build_s = problem, repeats, build_s
        self.eq = problem.equilibrium
        self.generator = torch.Generator().manual_seed(seed)
        theta0 = problem.theta0
        # A generic (non-constant) point: the initial guess plus a small perturbation.
        self.theta = (theta0 + 0.1 * self.randn(theta0.shape)).detach()
        self.g = self.randn(state_shape)
        self.v = self.randn(theta0.shape)
        self.w = self.randn(problem.data.shape)

    def randn(self, shape: tuple[int, ...] | torch.Size) -> torch.Tensor:
        return torch.randn(shape, generator=self.generator, dtype=self.problem.theta0.dtype)

    def _forward(self, theta: torch.Tensor) -> torch.Tensor:
        return self.problem.simulate(self.problem.parameterization(theta))

    def forward_backward(self) -> dict[str, Any]:
        """Forward from a cleared cache, then backward (it reuses the factorisation)."""
        fwd_t, bwd_t, fwd_c, bwd_c = [], [], [], []
        gc.collect()
        for rep in range(self.repeats + 1):  # repeat 0 warms up
            self.eq.clear_cache()
            theta = self.theta.clone().requires_grad_(True)
            t_f, x, c_f = timed(lambda: self._forward(theta))
            t_b, (grad,), c_b = timed(lambda: torch.autograd.grad(x, theta, self.g))
            assert grad.shape == theta.shape and bool(torch.isfinite(grad).all())
            if rep:
                fwd_t.append(t_f), bwd_t.append(t_b), fwd_c.append(c_f), bwd_c.append(c_b)
        forward = {**stats(fwd_t), "counts": same_counts(fwd_c)}
        backward = {**stats(bwd_t), "counts": same_counts(bwd_c)}
        return {"forward": forward, "backward": backward,
                "backward_over_forward": backward["median_s"] / forward["median_s"],
                "backward_over_forward_min": backward["min_s"] / forward["min_s"]}

    def products(self) -> dict[str, Any]:
        """``J v`` and ``J^T w`` at a linearised point, with the adjoint identity."""
        residual = self.problem.residual()
        self.eq.clear_cache()
        t_lin, lin, c_lin = timed(lambda: residual.linearize(self.theta))
        out: dict[str, Any] = {"linearize": {"seconds": t_lin, "counts": c_lin}}
        for name, fn in (("jvp", lambda: lin.jvp(self.v)), ("vjp", lambda: lin.vjp(self.w))):
            times, counts = [], []
            gc.collect()
            for rep in range(self.repeats + 1):
                t, y, c = timed(fn)
                assert bool(torch.isfinite(y).all())
                if rep:
                    times.append(t), counts.append(c)
            out[name] = {**stats(times), "counts": same_counts(counts)}
        # Adjoint consistency <w, J v> = <J^T w, v> (a cheap correctness check).
        lhs = float(torch.dot(self.w, lin.jvp(self.v)))
        rhs = float(torch.dot(lin.vjp(self.w), self.v))
        out["adjoint_check_rel_err"] = abs(lhs - rhs) / max(abs(lhs), abs(rhs), 1e-300)
        return out

    def one_gn_step(self, start: torch.Tensor, warm: bool, config: GaussNewtonConfig,
                    **inputs: Any) -> dict[str, Any]:
        """One Gauss-Newton step from ``start``, timed and counted.

        ``warm``: ``start`` is evaluated and factorised first, as in a running fit.
        Returns seconds, counts, the result, ``m`` (CGLS iterations), the number of new
        parameter vectors simulated and ``t`` (line-search trial points).
        """
        residual = self.problem.residual()
        evaluated: list[torch.Tensor] = []
        forward, products = residual.forward, residual.products

        def record(theta: torch.Tensor) -> None:
            primal = fwAD.unpack_dual(theta).primal.detach()
            if not any(torch.equal(primal, seen) for seen in evaluated):
                evaluated.append(primal.clone())

        def recording_forward(theta: torch.Tensor) -> torch.Tensor:
            record(theta)
            return forward(theta)

        def recording_products(theta: torch.Tensor):
            record(theta)
            return products(theta)

        self.eq.clear_cache()
        if warm:
            residual.linearize(start)
        residual.forward = recording_forward
        if products is not None:     # the explicit products linearise without forward
            residual.products = recording_products
        config = dataclasses.replace(config, max_iter=1)
        t, result, counts = timed(lambda: gauss_newton(residual, start, config, **inputs))
        distinct = len(evaluated)
        return {"seconds": t, "counts": counts, "result": result,
                "cg_iterations_m": int(result.history[-1].cg_iterations),
                "distinct_theta_evaluated": distinct,
                "new_theta_evaluated": distinct - int(warm and any(torch.equal(start, e)
                                                                   for e in evaluated)),
                "line_search_trials_t": distinct - 1}  # every point but the start
