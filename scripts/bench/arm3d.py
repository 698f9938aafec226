#!/usr/bin/env python
"""Benchmark the 3-D arm (``problem=arm3d``): what one fit is made of.

For every target mesh size (``--edge-lengths``: pytetwild's edge length as a fraction of the
bounding-box diagonal; the defaults give about 5k and 20k tetrahedra) and every model
(``--models``, default linear and corotated) this measures, with counted factorisations and
solves (:func:`torchfit.linalg.counting`):

* ``tetrahedralize``: pytetwild on the arm's surface (the time stored with the cached mesh,
  and the time of the cache hit);
* ``simulate``: one forward of all frames (default 48) from a cleared equilibrium cache;
* ``backward``: one reverse pass (``J^T w``) after that forward (reuses its factorisations);
* ``jacobian``: the whole Jacobian ``(m, n_params)`` of the coarse grid (192 parameters):
  every parameter direction as a right-hand side of each frame's factorisation;
* ``lm_iteration``: one Levenberg-Marquardt iteration from the homogeneous start (its
  linearisation, the damped dense solve, the trial point's simulation).

Timings are wall clock on the machine at hand (run with ``--threads`` equal to its cores);
counts are exact. Prints JSON and writes it to ``--out``. Example::

    .venv/bin/python scripts/bench/arm3d.py --out bench_arm3d.json
    .venv/bin/python scripts/bench/arm3d.py --edge-lengths 0.06 --frames 6 --models linear
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchtools import emit_report, machine_info, timed  # noqa: E402

from torchfit.linalg import set_threads  # noqa: E402
from torchfit.problems import build_problem  # noqa: E402
from torchfit.solvers import LevenbergMarquardtConfig, SOLVERS  # noqa: E402


def bench_case(edge_length: float, model: str, frames: int, cache: str,
               backend: str) -> dict:
    settings = {"tet_edge_length": edge_length, "model": model, "cache_dir": cache,
                "backend": backend}
    if frames < 48:
        settings["frames"] = list(range(frames))
    start = time.perf_counter()
    problem = build_problem("arm3d", settings)
    build_s = time.perf_counter() - start
    out = {"edge_length": edge_length, "model": model, "n_frames": problem.n_frames,
           "n_tets": problem.model.n_cells, "n_vertices": problem.model.n_vertices,
           "n_free_dofs": problem.describe()["n_free_dofs"], "backend": problem.backend,
           "n_params": problem.parameterization.n_params, "n_data": int(problem.data.numel()),
           "build_problem_s": build_s, "tetrahedralize_s": problem.tet.build_seconds,
           "tet_cache_hit": problem.tet.from_cache}
    eq = problem.poses.quasistatic.equilibrium
    theta = problem.theta0.clone()

    eq.clear_cache()
    leaf = theta.clone().requires_grad_(True)
    t, y, counts = timed(lambda: problem.forward(leaf))
    out["simulate"] = {"s": t, "counts": counts,
                       "newton_iterations": list(problem.poses.quasistatic.last_newton_iterations)}
    w = torch.randn(y.shape, generator=torch.Generator().manual_seed(0), dtype=y.dtype)
    t, _, counts = timed(lambda: torch.autograd.grad(y, leaf, w))
    out["backward"] = {"s": t, "counts": counts,
                       "ratio_to_simulate": t / out["simulate"]["s"]}
    t, J, counts = timed(lambda: problem.forward_jacobian(theta))
    out["jacobian"] = {"s": t, "counts": counts, "shape": list(J.shape),
                       "MB": J.numel() * J.element_size() / 1e6}
    del J, y, leaf

    eq.clear_cache()
    entry = SOLVERS["levenberg_marquardt"]
    config = LevenbergMarquardtConfig(max_iter=1)
    solver = entry.solver_class(config)
    t, result, counts = timed(lambda: solver.solve(problem.residual(), theta, []))
    out["lm_iteration"] = {"s": t, "counts": counts,
                           "misfit": [float(r.misfit) for r in result.history],
                           "accepted": [bool(r.accepted) for r in result.history]}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--edge-lengths", type=float, nargs="+", default=[0.04, 0.021])
    parser.add_argument("--models", nargs="+", default=["linear", "corotated"])
    parser.add_argument("--frames", type=int, default=48)
    parser.add_argument("--backend", default="auto")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--cache-dir", default=None,
                        help="tet-mesh cache (default: a fresh temporary one, so that "
                             "tetrahedralisation is timed)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    set_threads(args.threads)
    cache = args.cache_dir or tempfile.mkdtemp(prefix="torchfit-bench-")
    cases = [bench_case(e, m, args.frames, cache, args.backend)
             for e in args.edge_lengths for m in args.models]
    emit_report({"benchmark": "arm3d", "machine": machine_info(), "threads": args.threads,
                 "cases": cases}, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
