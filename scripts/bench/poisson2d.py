#!/usr/bin/env python
"""Benchmark poisson2d: forward, backward after forward, ``J v``, one GN step, GN iterations.

For every grid size ``N`` (``--sizes``, default 64 128 256 nodes per side) this measures
the wall time (median and minimum of a few repeats, ``time.perf_counter``) and counts the
factorisations and solves (:func:`torchfit.linalg.counting`) of

* ``forward``: ``problem.simulate(problem.parameterization(theta))`` from a cleared
  equilibrium cache (assembly + one factorisation + one solve for both components),
  ``theta`` requiring grad;
* ``backward``: ``torch.autograd.grad(x, theta, g)`` on the graph of that forward (one
  adjoint solve with the stored factor; ``backward_over_forward`` is the ratio of the
  medians, the acceptance asks for at most 0.15 at ``N = 256``);
* ``jvp`` / ``vjp``: one ``Linearization.jvp(v)`` / ``vjp(w)`` at a stored point;
* ``gn_step``: ``gauss_newton(residual, theta0, GaussNewtonConfig(max_iter=1))`` with the
  start already evaluated (as inside a running fit), noise-free dense data, with the
  number of CGLS iterations ``m`` and the check that it made one factorisation per new
  parameter vector and at most ``2m + 2 + t`` solves (``t`` line-search trial points).

For every ``N`` of ``--gn-sizes`` (default 32 64 128 256) it runs Gauss-Newton to the
discrepancy stop on dense data with noise ``--noise`` (default 1e-3) and reports its
outer iterations (the acceptance asks them to vary by at most 30% over the sizes), CGLS
iterations, wall time and aligned error.

Timings are wall clock; on a shared machine use ``--threads 1`` and read ``loadavg_*``.
Prints JSON to stdout (and writes it to ``--out``). Example::

    .venv/bin/python scripts/bench/poisson2d.py --threads 1 --out bench_poisson2d.json
    .venv/bin/python scripts/bench/poisson2d.py --sizes 8 12 --gn-sizes 8 12 --repeats 2
"""
from __future__ import annotations

import argparse
import dataclasses
import gc
import sys
import time
from pathlib import Path
from typing import Any

import torch

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchtools import (ProblemBench, emit_report, loadavg, machine_info,  # noqa: E402
                        timed)
from torchfit.problems import Poisson2D  # noqa: E402
from torchfit.problems.poisson2d import Poisson2DConfig  # noqa: E402
from torchfit.solvers.gauss_newton import GaussNewtonConfig, gauss_newton  # noqa: E402

BACKWARD_RATIO_TARGET = 0.15
ACCEPTANCE_N = 256
ITERATION_SPREAD_TARGET = 0.30


class Bench(ProblemBench):
    """Cost of the building blocks at one grid size ``N``."""

    def __init__(self, N: int, repeats: int, seed: int, solver: GaussNewtonConfig) -> None:
        self.N, self.solver = N, solver
        start = time.perf_counter()
        problem = Poisson2D(N=N)
        super().__init__(problem, repeats, seed, (1, N * N, 2), time.perf_counter() - start)

    def gn_step(self) -> dict[str, Any]:
        """One GN step from ``theta0`` (evaluated already), noise-free dense data.

        Cost with ``m`` CGLS iterations and ``t`` line-search trial points: ``t``
        factorisations and ``1 (J^T r) + m (J v) + (m - 1) (J^T w) + t + 1 (J^T r at the
        new point) = 2m + 1 + t`` solves; one more (``m`` products ``J^T w``) when CGLS
        stops on its normal-equation residual rather than on the linear residual (it has
        evaluated ``J^T w`` after its last ``J v``), as on small grids, where the
        linear-residual target is out of reach.
        """
        inputs = {"D": self.problem.parameterization.difference_operator()} \
            if self.solver.preconditioner == "difference" else {}
        step = self.one_gn_step(self.problem.theta0, True, self.solver, **inputs)
        t, counts, result = step["seconds"], step["counts"], step["result"]
        last = result.history[-1]
        m, new, trials = (step["cg_iterations_m"], step["new_theta_evaluated"],
                          step["line_search_trials_t"])
        return {"seconds": t, "counts": counts, "cg_iterations_m": m,
                "seconds_per_cg_iteration": t / max(m, 1),
                "new_theta_evaluated": new, "line_search_trials_t": trials,
                "step_length": last.extra.get("step_length"),
                "misfit_before": result.history[0].misfit, "misfit_after": last.misfit,
                "ok_factorizations_eq_new_theta": counts["factorizations"] == new,
                "solves_bound_2m_plus_2_plus_t": 2 * m + 2 + trials,
                "ok_solves_le_2m_plus_2_plus_t": counts["solves"] <= 2 * m + 2 + trials}


def gn_to_discrepancy(N: int, noise: float, seed: int, solver: GaussNewtonConfig) -> dict[str, Any]:
    """Gauss-Newton from ``theta0`` to its stop on dense data with noise ``noise``."""
    problem = Poisson2D(N=N, noise=noise, seed=seed)
    inputs = {"D": problem.parameterization.difference_operator()} \
        if solver.preconditioner == "difference" else {}
    t, result, counts = timed(lambda: gauss_newton(problem.residual(), problem.theta0, solver,
                                                   **inputs))
    metrics = problem.metrics(result.theta)
    return {"N": N, "iterations": result.iterations, "stop_reason": result.stop_reason,
            "cg_iterations_total": sum(r.cg_iterations for r in result.history),
            "cg_iterations": [r.cg_iterations for r in result.history[1:]],
            "seconds": t, "counts": counts, "misfit": metrics["misfit"],
            "noise_level": problem.noise_level,
            "k_err_rel_aligned": metrics["k_err_rel_aligned"]}


def run(sizes: list[int], gn_sizes: list[int], repeats: int, noise: float, seed: int,
        solver: GaussNewtonConfig) -> dict[str, Any]:
    report: dict[str, Any] = {
        "benchmark": "poisson2d",
        "machine": machine_info(),
        "loadavg_start": loadavg(),
        "settings": {"sizes": sizes, "gn_sizes": gn_sizes, "repeats": repeats,
                     "noise": noise, "seed": seed,
                     "backend": Poisson2DConfig.backend.value, "dtype": "float64",
                     "solver": dataclasses.asdict(solver),
                     "timing": "time.perf_counter; median over repeats after one warm-up; "
                               "forward from a cleared equilibrium cache"},
        "results": {},
        "gn_iterations": {},
    }
    for N in sizes:
        bench = Bench(N, repeats, seed, solver)
        res: dict[str, Any] = {"N": N, "n_params": bench.problem.theta0.numel(),
                               "n_free_dofs": int(bench.eq.free_dofs.numel()),
                               "build_problem_s": bench.build_s}
        res.update(bench.forward_backward())
        res.update(bench.products())
        res["gn_step"] = bench.gn_step()
        res["count_checks"] = {
            "forward_one_factorization": res["forward"]["counts"]["factorizations"] == 1,
            "backward_factorizations_zero": res["backward"]["counts"]["factorizations"] == 0,
            "backward_one_solve": res["backward"]["counts"]["solves"] == 1,
            "jvp_factorizations_zero": res["jvp"]["counts"]["factorizations"] == 0,
            "jvp_one_solve": res["jvp"]["counts"]["solves"] == 1,
            "vjp_factorizations_zero": res["vjp"]["counts"]["factorizations"] == 0,
            "vjp_one_solve": res["vjp"]["counts"]["solves"] == 1,
            "gn_step_factorizations_eq_new_theta":
                res["gn_step"]["ok_factorizations_eq_new_theta"],
            "gn_step_solves_le_2m_plus_2_plus_t": res["gn_step"]["ok_solves_le_2m_plus_2_plus_t"],
        }
        report["results"][str(N)] = res
        del bench
        gc.collect()
    for N in gn_sizes:
        report["gn_iterations"][str(N)] = gn_to_discrepancy(N, noise, seed, solver)
        gc.collect()
    acceptance: dict[str, Any] = {}
    if sizes:
        acceptance_n = ACCEPTANCE_N if ACCEPTANCE_N in sizes else max(sizes)
        at = report["results"][str(acceptance_n)]
        acceptance.update({
            "N": acceptance_n, "backward_over_forward": at["backward_over_forward"],
            "backward_over_forward_min": at["backward_over_forward_min"],
            "target": BACKWARD_RATIO_TARGET,
            "backward_le_0.15x_forward": at["backward_over_forward"] <= BACKWARD_RATIO_TARGET,
            "all_count_checks_pass_at_every_size": all(
                ok for r in report["results"].values() for ok in r["count_checks"].values())})
    if gn_sizes:
        iterations = [r["iterations"] for r in report["gn_iterations"].values()]
        spread = (max(iterations) - min(iterations)) / max(min(iterations), 1)
        acceptance.update({
            "gn_iterations": iterations,
            "gn_iteration_spread": spread,
            "gn_iteration_spread_target": ITERATION_SPREAD_TARGET,
            "gn_iterations_within_30_percent": spread <= ITERATION_SPREAD_TARGET,
            "gn_all_stop_by_discrepancy": all(r["stop_reason"] == "discrepancy"
                                              for r in report["gn_iterations"].values())})
    report["acceptance"] = acceptance
    report["loadavg_end"] = loadavg()
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="*", default=[64, 128, 256],
                        help="N (nodes per side) for forward/backward/J v/GN step")
    parser.add_argument("--gn-sizes", type=int, nargs="*", default=[32, 64, 128, 256],
                        help="N for Gauss-Newton iterations to the discrepancy stop")
    parser.add_argument("--repeats", type=int, default=5,
                        help="timed repeats of forward/backward/jvp (after one warm-up)")
    parser.add_argument("--noise", type=float, default=1e-3,
                        help="sigma of the data of the GN-iterations runs (must be > 0)")
    parser.add_argument("--preconditioner", default=GaussNewtonConfig.preconditioner,
                        choices=["none", "difference"], help="Gauss-Newton CGLS preconditioner")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=None,
                        help="torch.set_num_threads (default: torch's choice)")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    if any(n < 3 for n in args.sizes + args.gn_sizes) or args.repeats < 1:
        parser.error("sizes must be >= 3 (nodes per side) and repeats >= 1")
    if args.gn_sizes and not args.noise > 0:
        parser.error("--noise must be > 0: the GN runs stop by the discrepancy principle")
    if args.threads:
        torch.set_num_threads(args.threads)
    solver = GaussNewtonConfig(preconditioner=args.preconditioner)
    report = run(args.sizes, args.gn_sizes, args.repeats, args.noise, args.seed, solver)
    emit_report(report, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
