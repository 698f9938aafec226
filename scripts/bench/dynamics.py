"""Benchmark the two dynamics integrators at the same trajectory accuracy (JSON report).

    .venv/bin/python scripts/bench/dynamics.py --out bench_dynamics.json [--quick]
    .venv/bin/python scripts/bench/dynamics.py --problems --jacobian --columns-one-by-one

For each problem (``spring1d`` dynamic: 64 springs over 6 s; ``membrane2d`` dynamic: the
48 x 12 corotated sheet over 1.2 s) a reference trajectory is integrated with BDF2 at a
step 16 times below the finest candidate. Then, for a target accuracy (max position
error against the reference, relative to the largest displacement), the largest BDF2
step and the loosest dopri5 tolerance that meet it are chosen, and for each of them
(plus BDF2 with ``checkpoint_every = ceil(sqrt(steps))``) the report gives

* ``forward_s``: one simulation from a cleared cache, and its counted factorisations and
  solves (implicit) or right-hand-side evaluations (torchdiffeq);
* ``gradient_s``: the gradient of ``0.5 ||x||^2`` after that forward (reverse mode: the
  discrete adjoint, resp. ``odeint_adjoint``), its counts, and ``gradient_peak_mb``: the
  peak resident memory above the level before the forward, sampled every 2 ms during
  forward and gradient (what the trajectory keeps for the gradient);
* ``jvp_s``: one forward-mode product ``J v`` at the simulated point;
* ``error``: the trajectory's achieved error; ``stored_states``.

``--jacobian`` adds the torchdiffeq path's dense Jacobian (the one-pass ``d positions /
d params`` a Gauss-Newton or Levenberg-Marquardt iteration takes for few parameters) of
``spring1d`` dynamic at its initial guess (66 columns, dopri5 at the problem's
tolerances): ``after``, all columns in one augmented solve with the tangent right-hand
side batched over columns (two reverse passes per evaluation); with
``--columns-one-by-one`` also ``before``, the same solve with one reverse pass per column
per evaluation (the code before 2026-12-01), and the ratio; both in one run.

``--first-iteration gauss_newton levenberg_marquardt`` runs the fit app
(``experiments/fit.py problem=spring1d problem.dynamic=true problem.integrator=torchdiffeq
solver=<s> solver.max_iter=<n>``, one thread, a fresh run directory each) twice per solver,
with ``problem.ode_trial_factor=0`` (no trial budget: the code before 2026-12-02) and at its
default, and reports each run's iteration 0 (the start's simulation and dense Jacobian) and
iteration 1 (the first step, its trials included) from ``result.json``'s history; a run
past ``--run-timeout`` is stopped and reported as such. Both in one run.

Run with one torch thread (set here): step-by-step integration is many small kernels.
"""
from __future__ import annotations

import argparse
import gc
import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import torch
import torch.autograd.forward_ad as fwAD

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchtools import emit_report, machine_info  # noqa: E402
from torchfit.linalg import counting  # noqa: E402
from torchfit.physics.dynamics import make_integrator  # noqa: E402
from torchfit.physics.dynamics.explicit import TorchdiffeqIntegrator  # noqa: E402
from torchfit.problems import build_problem  # noqa: E402

PROBLEMS = {
    "spring1d": {"name": "spring1d", "cfg": {"dynamic": True}, "dts": [0.02, 0.01, 0.005],
                 "rtols": [1e-4, 1e-5, 1e-6, 1e-7, 1e-8]},
    "membrane2d": {"name": "membrane2d",
                   "cfg": {"dynamic": True, "nx": 48, "ny": 12, "backend": "scipy",
                           "duration": 1.2, "frames": 12, "dt": 0.03},
                   "dts": [0.03, 0.015, 0.0075], "rtols": [1e-3, 1e-4, 1e-5, 1e-6]},
}


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2 ** 20


class PeakSampler:
    """Peak resident memory above the start level while the block runs (2 ms sampling)."""

    def __enter__(self) -> "PeakSampler":
        gc.collect()
        self.start = rss_mb()
        self.peak = self.start
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop:
            self.peak = max(self.peak, rss_mb())
            time.sleep(0.002)

    def __exit__(self, *exc: object) -> None:
        self._stop = True
        self._thread.join()
        self.peak = max(self.peak, rss_mb())

    @property
    def mb(self) -> float:
        return self.peak - self.start


def integrator_for(problem, kind: str, **settings: Any):
    cfg = problem.cfg
    return make_integrator(kind, problem.system, problem.output_times, dt=settings.get("dt", cfg.dt),
                           method=settings.get("method", "dopri5"), scheme="bdf2",
                           rtol=settings.get("rtol", 1e-8), atol=settings.get("rtol", 1e-8) * 1e-2,
                           backend="scipy", newton=problem.integrator.equilibrium.newton,
                           checkpoint_every=settings.get("checkpoint_every", 1))


def relative_error(x: torch.Tensor, reference: torch.Tensor, scale: float) -> float:
    return float((x - reference).abs().max()) / scale


def measure(integrator, params: torch.Tensor, reference: torch.Tensor, scale: float) -> dict[str, Any]:
    out: dict[str, Any] = {"stored_states": int(integrator.stored_states)}
    integrator.clear_cache()
    with PeakSampler() as memory:
        evaluations = getattr(integrator, "evaluations", 0)
        with counting() as counts:
            start = time.perf_counter()
            leaf = params.detach().clone().requires_grad_(True)
            x = integrator(leaf)
            out["forward_s"] = time.perf_counter() - start
        out["forward_counts"] = counts.as_dict()
        if hasattr(integrator, "evaluations"):
            out["forward_rhs_evaluations"] = integrator.evaluations - evaluations
            evaluations = integrator.evaluations
        with counting() as counts:
            start = time.perf_counter()
            (grad,) = torch.autograd.grad(0.5 * (x ** 2).sum(), leaf)
            out["gradient_s"] = time.perf_counter() - start
        out["gradient_counts"] = counts.as_dict()
        if hasattr(integrator, "evaluations"):
            out["gradient_rhs_evaluations"] = integrator.evaluations - evaluations
    out["gradient_peak_mb"] = round(memory.mb, 1)
    out["error"] = relative_error(x.detach(), reference, scale)
    v = torch.randn(params.shape, generator=torch.Generator().manual_seed(0), dtype=params.dtype)
    with counting() as counts:
        start = time.perf_counter()
        with fwAD.dual_level():
            fwAD.unpack_dual(integrator(fwAD.make_dual(params, v * params))).tangent
        out["jvp_s"] = time.perf_counter() - start
    out["jvp_counts"] = counts.as_dict()
    return out


def bench_problem(key: str, target: float, quick: bool) -> dict[str, Any]:
    spec = PROBLEMS[key]
    problem = build_problem(spec["name"], spec["cfg"])
    params = problem.time.true_input(problem.field_true)
    dts = spec["dts"][:2] if quick else spec["dts"]
    reference_dt = dts[-1] / 16
    with torch.no_grad():      # nothing kept for a gradient: checkpoints only
        reference = integrator_for(problem, "implicit", dt=reference_dt,
                                   checkpoint_every=0)(params).detach()
    rest = problem.system.x0.to(reference)
    scale = float((reference - rest).abs().max())
    report: dict[str, Any] = {"problem": problem.describe(), "reference": {
        "scheme": "bdf2", "dt": reference_dt}, "target_error": target, "candidates": []}
    chosen: dict[str, Any] = {}
    for dt in dts:
        error = relative_error(integrator_for(problem, "implicit", dt=dt,
                                              checkpoint_every=0)(params).detach(),
                               reference, scale)
        report["candidates"].append({"integrator": "implicit", "dt": dt, "error": error})
        if error <= target and "implicit" not in chosen:
            chosen["implicit"] = {"dt": dt}
    for rtol in spec["rtols"]:
        try:
            error = relative_error(integrator_for(problem, "torchdiffeq", rtol=rtol)(params).detach(),
                                   reference, scale)
        except Exception as exc:  # noqa: BLE001 - a failed candidate is reported
            report["candidates"].append({"integrator": "torchdiffeq", "rtol": rtol,
                                         "failed": str(exc)})
            continue
        report["candidates"].append({"integrator": "torchdiffeq", "rtol": rtol, "error": error})
        if error <= target:
            chosen["torchdiffeq"] = {"rtol": rtol}
            break
    chosen.setdefault("implicit", {"dt": dts[-1]})
    chosen.setdefault("torchdiffeq", {"rtol": spec["rtols"][-1]})
    results: dict[str, Any] = {}
    implicit = integrator_for(problem, "implicit", **chosen["implicit"])
    results["implicit_bdf2"] = {**chosen["implicit"], "steps": implicit.n_steps,
                                **measure(implicit, params, reference, scale)}
    sqrt_c = max(1, math.ceil(math.sqrt(implicit.n_steps)))
    checkpointed = integrator_for(problem, "implicit", checkpoint_every=sqrt_c, **chosen["implicit"])
    results["implicit_bdf2_checkpointed"] = {**chosen["implicit"], "checkpoint_every": sqrt_c,
                                             **measure(checkpointed, params, reference, scale)}
    ode = integrator_for(problem, "torchdiffeq", **chosen["torchdiffeq"])
    results["torchdiffeq_dopri5"] = {**chosen["torchdiffeq"],
                                     **measure(ode, params, reference, scale)}
    report["results"] = results
    return report


class _PerColumnTangents(TorchdiffeqIntegrator):
    """The tangent right-hand side as it was before 2026-12-01: one reverse pass per column."""

    @staticmethod
    def _tangent_columns(value, p_leaf, y_leaf, V, S):
        probe = torch.zeros_like(value, requires_grad=True)
        g_p, g_y = torch.autograd.grad(value, (p_leaf, y_leaf), probe, create_graph=True,
                                       allow_unused=True)
        columns = []
        for j in range(V.shape[1]):
            pairing = sum((g * d).sum() for g, d in ((g_p, V[:, j]), (g_y, S[:, j]))
                          if g is not None)
            (column,) = torch.autograd.grad(pairing, probe, retain_graph=True, allow_unused=True)
            columns.append(torch.zeros_like(value) if column is None else column)
        return torch.stack(columns, dim=1)


def bench_jacobian(one_by_one: bool) -> dict[str, Any]:
    """The dense Jacobian of spring1d dynamic through torchdiffeq (module docstring)."""
    problem = build_problem("spring1d", {"dynamic": True, "integrator": "torchdiffeq"})
    cfg = problem.cfg
    params = problem.parameterization(problem.theta0).detach()
    directions = problem.parameterization.jacobian(problem.theta0).detach()
    kinds = {"after": TorchdiffeqIntegrator}
    if one_by_one:
        kinds["before"] = _PerColumnTangents
    out: dict[str, Any] = {"n_params": int(params.numel()), "method": cfg.ode_method.value,
                           "rtol": cfg.ode_rtol, "atol": cfg.ode_atol}
    columns = {}
    for name, cls in kinds.items():
        integrator = cls(problem.system, problem.output_times, method=cfg.ode_method.value,
                         rtol=cfg.ode_rtol, atol=cfg.ode_atol)
        integrator.solve(params)
        before = integrator.evaluations
        start = time.perf_counter()
        columns[name] = integrator.jacobian(params, directions)
        seconds = time.perf_counter() - start
        evaluations = integrator.evaluations - before
        out[name] = {"jacobian_s": seconds, "rhs_evaluations": evaluations,
                     "ms_per_rhs": 1e3 * seconds / max(evaluations, 1)}
        print(f"{name}: dense Jacobian ({params.numel()} columns) {seconds:.1f} s, "
              f"{evaluations} right-hand sides, {out[name]['ms_per_rhs']:.2f} ms each",
              file=sys.stderr, flush=True)
    if one_by_one:
        out["speedup"] = out["before"]["jacobian_s"] / out["after"]["jacobian_s"]
        scale = float(columns["before"].abs().max())
        out["max_difference_rel"] = float((columns["after"] - columns["before"]).abs().max()) / scale
    return out


def bench_first_iteration(solvers: list[str], iterations: int, timeout: float) -> dict[str, Any]:
    """The chain's first fit iterations through torchdiffeq with and without the trial
    budget (module docstring): ``{solver: {"no_budget" | "budget": {...}}}``."""
    out: dict[str, Any] = {}
    env = dict(os.environ, OMP_NUM_THREADS="1")
    for solver in solvers:
        out[solver] = {}
        for label, factor in (("no_budget", "0"), ("budget", None)):
            with tempfile.TemporaryDirectory(prefix="torchfit_bench_") as tmp:
                command = [sys.executable, str(REPO / "experiments" / "fit.py"),
                           "problem=spring1d", "problem.dynamic=true",
                           "problem.integrator=torchdiffeq", f"solver={solver}",
                           f"solver.max_iter={iterations}", "threads=1",
                           f"hydra.run.dir={tmp}/run"]
                if factor is not None:
                    command.append(f"problem.ode_trial_factor={factor}")
                start = time.perf_counter()
                try:
                    done = subprocess.run(command, cwd=REPO, env=env, capture_output=True,
                                          text=True, timeout=timeout)
                except subprocess.TimeoutExpired:
                    row = {"stopped_after_s": timeout}
                else:
                    if done.returncode != 0:
                        raise SystemExit(f"{' '.join(command)} failed:\n{done.stderr[-2000:]}")
                    result = json.loads(Path(tmp, "run", "result.json").read_text())
                    walls = [float(h["wall_time"]) for h in result["history"]]
                    row = {"iteration_0_s": walls[0],
                           "iteration_1_s": walls[1] - walls[0] if len(walls) > 1 else None,
                           "fit_s": float(result["wall_s"]), "misfit": result["misfit"],
                           "k_err_rel": result["k_err_rel"],
                           "trial_factor": result["config"]["problem"]["ode_trial_factor"]}
                row["process_s"] = time.perf_counter() - start
            out[solver][label] = row
            print(f"{solver} {label}: {row}", file=sys.stderr, flush=True)
        before, after = out[solver]["no_budget"], out[solver]["budget"]
        if before.get("iteration_1_s") and after.get("iteration_1_s"):
            out[solver]["iteration_1_speedup"] = before["iteration_1_s"] / after["iteration_1_s"]
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--target", type=float, default=1e-3,
                        help="max position error / largest displacement (default 1e-3)")
    parser.add_argument("--problems", nargs="*", default=list(PROBLEMS))
    parser.add_argument("--quick", action="store_true", help="fewer candidate steps")
    parser.add_argument("--jacobian", action="store_true",
                        help="also the torchdiffeq dense Jacobian of spring1d dynamic")
    parser.add_argument("--columns-one-by-one", action="store_true",
                        help="with --jacobian: also the per-column tangent (before 2026-12-01)")
    parser.add_argument("--first-iteration", nargs="+", default=None, metavar="SOLVER",
                        help="the torchdiffeq chain's first fit iterations with these solvers, "
                             "with and without the trial budget")
    parser.add_argument("--iterations", type=int, default=1,
                        help="with --first-iteration: solver.max_iter (default 1)")
    parser.add_argument("--run-timeout", type=float, default=3600.0,
                        help="with --first-iteration: stop a run after this many seconds")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    report: dict[str, Any] = {"machine": machine_info(), "target_error": args.target,
                              "problems": {key: bench_problem(key, args.target, args.quick)
                                           for key in args.problems}}
    if args.jacobian:
        report["torchdiffeq_dense_jacobian"] = bench_jacobian(args.columns_one_by_one)
    if args.first_iteration:
        report["torchdiffeq_first_iteration"] = bench_first_iteration(
            args.first_iteration, args.iterations, args.run_timeout)
    emit_report(report, args.out)


if __name__ == "__main__":
    main()
