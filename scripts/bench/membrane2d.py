#!/usr/bin/env python
"""Benchmark membrane2d: quasistatic frames, the 8-frame simulate, adjoint and products.

For every constitutive model (default ``linear``, ``corotated``, ``stable_neo_hookean``)
and resolution (default the canonical ``96 x 24`` cells and ``192 x 48``, i.e. 4x the
elements) at a generic point (the true field times ``exp(0.1 N(0, 1))`` per triangle),
this measures (wall clock, median and minimum of ``--repeats``; factorisations and
solves counted exactly):

* ``frame``: one quasistatic frame alone, cold (no warm start; linear-elastic start from
  rest, then Newton), for every frame of the animation: seconds and Newton iterations;
* ``simulate``: the whole 8-frame ``simulate`` cold, with ``E`` requiring grad, and its
  Newton iterations per frame;
* ``backward``: ``torch.autograd.grad`` of that simulate (one adjoint solve per frame with
  the factorisation kept from forward), and ``backward_over_forward`` (the ratio);
* ``simulate_warm``: the 8-frame simulate at a nearby point (``theta + 1e-2 v``) warm
  started from the previous solution (what every Levenberg-Marquardt trial point costs);
* ``jvp`` and ``vjp``: one ``J v`` and one ``J^T w`` of the residual (one CGLS iteration of
  the solvers costs one of each).

Prints JSON (and writes it to ``--out``). Timings are wall clock on a possibly shared
machine: run with ``--threads 1``. Example::

    .venv/bin/python scripts/bench/membrane2d.py --threads 1 --out bench_membrane2d.json
    .venv/bin/python scripts/bench/membrane2d.py --quick
"""
from __future__ import annotations

import argparse
import gc
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Callable

import torch

ROOT = Path(__file__).resolve().parents[2]
for path in (ROOT, ROOT / "scripts" / "bench"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

from benchtools import emit_report, machine_info  # noqa: E402
from torchfit.linalg import counting  # noqa: E402
from torchfit.linalg.threads import blas_threads, set_threads  # noqa: E402
from torchfit.problems import Membrane2D  # noqa: E402

MODELS = ["linear", "corotated", "stable_neo_hookean"]


def timed(fn: Callable[[], Any], setup: Callable[[], Any] | None = None,
          repeats: int = 3) -> dict[str, Any]:
    """Median/min seconds of ``fn`` over ``repeats`` (``setup`` untimed before each)."""
    times, counts, out = [], [], None
    for _ in range(repeats):
        state = setup() if setup is not None else None
        gc.collect()
        gc.disable()
        try:
            with counting() as delta:
                start = time.perf_counter()
                out = fn() if state is None else fn(state)
                times.append(time.perf_counter() - start)
                counts.append(delta.as_dict())
        finally:
            gc.enable()
    return {"median_s": statistics.median(times), "min_s": min(times), "repeats": repeats,
            "counts": counts[0], "_out": out}


def strip(entry: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in entry.items() if not k.startswith("_")}


def bench_one(model: str, nx: int, ny: int, repeats: int, seed: int) -> dict[str, Any]:
    start = time.perf_counter()
    problem = Membrane2D(nx=nx, ny=ny, model=model)
    build_s = time.perf_counter() - start
    qs = problem.quasistatic
    eq = qs.equilibrium
    gen = torch.Generator().manual_seed(seed)
    theta = problem.parameterization.inverse(problem.field_true) + 0.1 * torch.randn(
        problem.theta0.shape, generator=gen, dtype=problem.theta0.dtype)
    E = problem.parameterization(theta).detach()
    positions = problem.dirichlet_positions
    # warm-up (first-call costs of autograd and the allocator are not the method's)
    e0 = E.clone().requires_grad_(True)
    torch.autograd.grad(problem.simulate(e0).sum(), e0)
    qs.clear_cache()
    out: dict[str, Any] = {"cells": nx * ny * 2, "vertices": problem.model.n_vertices,
                           "free_dofs": int(eq.free_dofs.numel()),
                           "tangent_nnz_free": eq.free_pattern.nnz, "frames": problem.n_frames,
                           "build_and_truth_s": build_s}

    # one frame alone, cold
    frames = []
    for f in range(problem.n_frames):
        entry = timed(lambda: qs(E, positions[f:f + 1]), setup=qs.clear_cache, repeats=repeats)
        entry["newton_iterations"] = list(qs.last_newton_iterations)
        frames.append(strip(entry))
    out["frame"] = frames
    out["frame_median_s"] = statistics.median(f["median_s"] for f in frames)

    # the whole simulate, cold, then its backward
    def forward() -> tuple[torch.Tensor, torch.Tensor]:
        e = E.clone().requires_grad_(True)
        return e, problem.simulate(e)

    sim = timed(forward, setup=qs.clear_cache, repeats=repeats)
    sim["newton_iterations"] = list(qs.last_newton_iterations)
    out["simulate"] = strip(sim)

    def setup_backward() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        qs.clear_cache()
        e, x = forward()
        return e, x, torch.randn(x.shape, generator=gen, dtype=x.dtype)

    back = timed(lambda s: torch.autograd.grad(s[1], s[0], s[2]), setup=setup_backward,
                 repeats=repeats)
    out["backward"] = strip(back)
    out["backward_over_forward"] = back["median_s"] / sim["median_s"]

    # warm-started simulate at a nearby point (an LM trial point)
    direction = torch.randn(theta.shape, generator=gen, dtype=theta.dtype)

    def setup_warm() -> None:
        qs.clear_cache()
        with torch.no_grad():
            problem.simulate(E)

    warm = timed(lambda: problem.simulate(problem.parameterization(theta + 1e-2 * direction)),
                 setup=setup_warm, repeats=repeats)
    warm["newton_iterations"] = list(qs.last_newton_iterations)
    warm["warm_started"] = eq.last_warm_started
    out["simulate_warm"] = strip(warm)

    # Jacobian products (one CGLS iteration = one of each)
    qs.clear_cache()
    lin = problem.residual().linearize(theta)
    v = torch.randn(theta.shape, generator=gen, dtype=theta.dtype)
    w = torch.randn(problem.data.shape, generator=gen, dtype=theta.dtype)
    lin.jvp(v)
    lin.vjp(w)                                              # warm-up
    out["jvp"] = strip(timed(lambda: lin.jvp(v), repeats=max(repeats, 5)))
    out["vjp"] = strip(timed(lambda: lin.vjp(w), repeats=max(repeats, 5)))
    return out


def run(models: list[str], sizes: list[tuple[int, int]], repeats: int, seed: int) -> dict[str, Any]:
    results: dict[str, Any] = {}
    for model in models:
        results[model] = {}
        for nx, ny in sizes:
            results[model][f"{nx}x{ny}"] = bench_one(model, nx, ny, repeats, seed)
    return {"benchmark": "membrane2d", "machine": {**machine_info(), "blas_threads": blas_threads()},
            "settings": {"models": models, "sizes": [f"{nx}x{ny}" for nx, ny in sizes],
                         "repeats": repeats, "seed": seed,
                         "point": "true field * exp(0.1 N(0,1)) per triangle"},
            "results": results}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", nargs="+", default=MODELS, choices=MODELS)
    parser.add_argument("--sizes", nargs="+", default=["96x24", "192x48"],
                        help="resolutions NXxNY (default: 96x24 192x48, i.e. 4x the elements)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=None,
                        help="torch.set_num_threads (default: torch's choice)")
    parser.add_argument("--quick", action="store_true", help="tiny sizes, one repeat (smoke test)")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    if args.quick:
        args.sizes, args.repeats = ["16x4", "32x8"], 1
    try:
        sizes = [tuple(int(v) for v in s.lower().split("x")) for s in args.sizes]
    except ValueError:
        parser.error(f"sizes must look like 96x24, got {args.sizes}")
    if any(len(s) != 2 or min(s) < 1 for s in sizes) or args.repeats < 1:
        parser.error("sizes must be NXxNY with NX >= 2, NY >= 1 and repeats >= 1")
    if args.threads:
        set_threads(args.threads)
    emit_report(run(args.models, sizes, args.repeats, args.seed), args.out)  # type: ignore[arg-type]
    return 0


if __name__ == "__main__":
    sys.exit(main())
