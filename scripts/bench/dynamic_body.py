"""Benchmark the rigged body in time: one Levenberg-Marquardt iteration of the dynamic arm with
and without checkpointing, and a long ``simulate`` of a fitted run (JSON report).

    .venv/bin/python scripts/bench/dynamic_body.py --out bench_dynamic_body.json
    .venv/bin/python scripts/bench/dynamic_body.py --problem arm3d_short --checkpoints 1
    .venv/bin/python scripts/bench/dynamic_body.py --no-iteration --simulate-frames 240 \\
        --run outputs/arm3d/levenberg_marquardt/<fit>

**Iteration** (``--problem``, default ``arm3d``: the full arm, about 10k tetrahedra, 48 frames
at 24 fps, the default 4 substeps: 188 BDF2 steps, 192 grid nodes + alpha, beta; the
synthetic target, ``problem.dynamic=true``). For each ``checkpoint_every`` of
``--checkpoints`` (default ``1 0``: every state and factor kept; ``ceil(sqrt(steps))``), in a
process of its own (so that its memory is its own), after building the problem:

* ``forward_s``: one simulation at the start from a cleared cache, its counted
  factorisations and solves;
* ``jacobian_s``: the dense Jacobian there (tangents forward in time, 194 right-hand sides
  per step);
* ``gradient_s``: the misfit's gradient there (the discrete adjoint);
* ``lm_iteration_s``: one Levenberg-Marquardt iteration of the arm's solver settings from a
  cleared cache (simulation, Jacobian, damped step, trial simulation): what an iteration of
  the fit costs;
* ``peak_mb``: the peak resident memory above the level after building, sampled every 2 ms
  over all of the above; ``stored_states``.

The ratios of each variant to the first are printed in the same run.

**Simulate** (``--simulate-frames N --run <fitted dynamic run>``): the procedural arm with
``N`` frames at 24 fps (an ``arm3d`` run: ``problem.n_frames=N``; an ``animation`` run: the arm
``scripts/write_arm.py`` writes) and the run's fitted material simulated on it in time through :func:`torchfit.run.simulating.simulate` (every
output: OBJ frames, VTU, the USD point cache): wall time and peak memory.

One torch thread (set here): step-by-step integration is many small kernels.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchtools import emit_report, machine_info, timed  # noqa: E402
from dynamics import PeakSampler  # noqa: E402


def compose(problem: str, overrides: list[str]) -> Any:
    """The fit app's configuration of ``problem`` with ``overrides`` (Hydra, as the app)."""
    from hydra import compose as hydra_compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from torchfit.config import register_configs
    register_configs()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base=None):
        return hydra_compose(config_name="fit", overrides=[f"problem={problem}", *overrides])


def iteration_variant(problem_name: str, checkpoint_every: int) -> dict[str, Any]:
    """One variant's figures (module docstring), in this process."""
    from omegaconf import OmegaConf

    from torchfit.problems import build_problem
    from torchfit.run.solver import build_solver

    cfg = compose(problem_name, ["problem.dynamic=true", "problem.target=synthetic",
                                 f"problem.checkpoint_every={checkpoint_every}"])
    start = time.perf_counter()
    problem = build_problem(problem_name, OmegaConf.to_container(cfg.problem, resolve=True))
    build_s = time.perf_counter() - start
    theta = problem.theta0
    integrator = problem.integrator
    out: dict[str, Any] = {"checkpoint_every": checkpoint_every, "build_s": build_s,
                           "described": problem.describe()}
    with PeakSampler() as peak:
        integrator.clear_cache()
        out["forward_s"], _, out["forward_counts"] = timed(
            lambda: problem.forward(theta).detach())
        out["jacobian_s"], J, out["jacobian_counts"] = timed(
            lambda: problem.forward_jacobian(theta))
        out["jacobian_shape"] = list(J.shape)
        del J

        def gradient() -> torch.Tensor:
            leaf = theta.clone().requires_grad_(True)
            residual = problem.forward(leaf) - problem.data
            (g,) = torch.autograd.grad(0.5 * (residual * residual).sum(), leaf)
            return g

        out["gradient_s"], _, out["gradient_counts"] = timed(gradient)
        integrator.clear_cache()
        solver = build_solver(problem, {**OmegaConf.to_container(cfg.solver, resolve=True),
                                        "max_iter": 1})
        out["lm_iteration_s"], result, out["lm_iteration_counts"] = timed(
            lambda: solver.solve(problem.residual(), theta))
        out["lm_iteration_records"] = [
            {"iteration": r.iteration, "accepted": bool(getattr(r, "accepted", True)),
             "misfit": float(r.misfit)} for r in result.history]
    out["peak_mb"] = peak.mb
    return out


def simulate_shot(run: Path, n_frames: int) -> dict[str, Any]:
    """``simulate`` of ``run`` on the arm with ``n_frames`` frames (module docstring): an
    ``arm3d`` run makes its own (``problem.n_frames``, every frame), an ``animation`` run
    reads the arm written by ``scripts/write_arm.py``."""
    import yaml

    from torchfit.run.simulating import simulate

    fitted = yaml.safe_load((run / ".hydra" / "config.yaml").read_text())["problem"]["name"]
    with tempfile.TemporaryDirectory() as tmp:
        if fitted == "arm3d":
            settings: dict[str, Any] = {"n_frames": n_frames, "frames": None}
        else:
            shot = Path(tmp) / "shot"
            subprocess.run([sys.executable, str(REPO / "scripts" / "write_arm.py"), str(shot),
                            "--n-frames", str(n_frames)], check=True, capture_output=True)
            settings = {"path": str(shot), "frames": None}
        with PeakSampler() as peak:
            start = time.perf_counter()
            result = simulate(run, settings, Path(tmp) / "sim", progress_lines=False)
            wall = time.perf_counter() - start
        written = sorted(p.name for p in (Path(tmp) / "sim").iterdir())
    return {"run": str(run), "frames": n_frames, "wall_s": wall, "peak_mb": peak.mb,
            "simulated_frames": int(result.state.shape[0]), "written": written}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--problem", default="arm3d", choices=["arm3d", "arm3d_short"])
    parser.add_argument("--checkpoints", type=int, nargs="+", default=[1, 0],
                        help="checkpoint_every values, one process each (default 1 0)")
    parser.add_argument("--no-iteration", action="store_true", help="skip the iteration part")
    parser.add_argument("--simulate-frames", type=int, default=0,
                        help="frames of the simulated shot (needs --run)")
    parser.add_argument("--run", type=Path, default=None,
                        help="a fitted run directory of the dynamic arm")
    parser.add_argument("--variant", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    if args.variant is not None:               # a child process: one variant, JSON on stdout
        print(json.dumps(iteration_variant(args.problem, args.variant)))
        return
    if args.simulate_frames and args.run is None:
        parser.error("--simulate-frames needs --run <a fitted dynamic run directory>")
    report: dict[str, Any] = {"machine": machine_info(), "problem": args.problem}
    if not args.no_iteration:
        variants = []
        for c in args.checkpoints:
            done = subprocess.run([sys.executable, __file__, "--problem", args.problem,
                                   "--variant", str(c)], capture_output=True, text=True)
            if done.returncode != 0:
                raise SystemExit(f"error: the variant checkpoint_every={c} failed:\n"
                                 f"{done.stderr[-3000:]}")
            variants.append(json.loads(done.stdout.strip().splitlines()[-1]))
        first = variants[0]
        for v in variants[1:]:
            v["ratio_to_first"] = {k: v[k] / first[k] for k in
                                   ("forward_s", "jacobian_s", "gradient_s", "lm_iteration_s",
                                    "peak_mb") if first[k]}
        report["iteration"] = variants
        for v in variants:
            print(f"checkpoint_every={v['checkpoint_every']} "
                  f"({v['described']['stored_states']} states kept, "
                  f"{v['described']['steps']} steps): forward {v['forward_s']:.1f} s, Jacobian "
                  f"{v['jacobian_s']:.1f} s, gradient {v['gradient_s']:.1f} s, one LM iteration "
                  f"{v['lm_iteration_s']:.1f} s, peak {v['peak_mb']:.0f} MB"
                  + (f" (ratios to the first: {json.dumps(v['ratio_to_first'])})"
                     if "ratio_to_first" in v else ""), file=sys.stderr)
    if args.simulate_frames:
        report["simulate"] = simulate_shot(args.run, args.simulate_frames)
        s = report["simulate"]
        print(f"simulate {s['frames']} frames: {s['wall_s']:.1f} s, peak {s['peak_mb']:.0f} MB",
              file=sys.stderr)
    emit_report(report, args.out)


if __name__ == "__main__":
    main()
