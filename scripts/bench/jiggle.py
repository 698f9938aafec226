"""Benchmark the keyframed-jiggle arm: the quasistatic fit and the fit in time of one target,
side by side, on a held-out later window (JSON report, the ratio printed in the same run).

    .venv/bin/python scripts/bench/jiggle.py --out bench_jiggle.json
    .venv/bin/python scripts/bench/jiggle.py --frames 24 --fitted 12 --select 6   # + a test window

The target: ``scripts/write_arm.py <dir> --n-frames F --jiggle A`` (the procedural arm,
flexion to 120 degrees and back, a small extension, with a damped oscillation of the flesh
keyed after every change of speed: a procedural layer, not this simulator). Both fits are the
fit app, ``problem=animation`` on that folder (one mesh: one cache), the rig target,
Levenberg-Marquardt, one thread, frames ``0 .. fitted-1`` fitted and the later frames held out
(``problem.validation_frames``); the body in time adds ``problem.dynamic=true``.

Reported per fit (``quasistatic``, ``in_time``): the fitted frames' mean surface error and its
reduction below the homogeneous start, the held-out window's at the homogeneous start, at the
last iterate and at the iterate of lowest held-out error (the one the fit chooses:
``params_best_validation.pt``), iterations and wall time; ``ratio_*``: the in-time reduction
over the quasistatic one. The chosen iterate is picked on the held-out window itself, so its
figure is optimistic; with ``--select K`` only the first ``K`` held-out frames choose it and
the rest (the test window, never seen by the fit nor the choice) are simulated at the chosen
iterate and at the start (``test_*``): the unbiased figure.
"""
from __future__ import annotations

import argparse
import json
import os
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

from benchtools import emit_report, machine_info  # noqa: E402


def _frames(values: list[int]) -> str:
    return "[" + ",".join(str(v) for v in values) + "]"


def fit(mode: str, arm: Path, run: Path, cache: Path, fitted: list[int], held: list[int],
        edge: float, substeps: int, max_iter: int) -> dict[str, Any]:
    """One fit through the app; its ``result.json`` figures."""
    overrides = ["problem=animation", f"problem.path={arm}", f"problem.cache_dir={cache}",
                 f"problem.tet_edge_length={edge}", f"problem.frames={_frames(fitted)}",
                 f"problem.validation_frames={_frames(held)}", "solver=levenberg_marquardt",
                 f"solver.max_iter={max_iter}", "threads=1", f"hydra.run.dir={run}"]
    if mode == "in_time":
        overrides += ["problem.dynamic=true", f"problem.substeps={substeps}"]
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "experiments/fit.py", *overrides], cwd=REPO,
                          capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"error: the {mode} fit failed (exit {proc.returncode}): "
                         f"{proc.stderr.strip().splitlines()[-1:]}")
    result = json.loads((run / "result.json").read_text())
    validation = result["validation"]
    metrics = result.get("metrics", result)
    out = {"wall_s": round(wall, 1), "iterations": result.get("iterations"),
           "stop_reason": result.get("stop_reason"),
           "fitted_surface_err_mean_mm": 1e3 * float(metrics["surface_err_mean"]),
           "fitted_reduction": float(metrics["surface_err_reduction"]),
           "held_out_last_mm": 1e3 * float(validation["final"]["surface_err_mean"]),
           "held_out_last_reduction": float(validation["final"]["surface_err_reduction"]),
           "held_out_chosen_mm": 1e3 * float(validation["chosen"]["surface_err_mean"]),
           "held_out_chosen_reduction": float(validation["chosen"]["surface_err_reduction"]),
           "chosen_iteration": validation["iteration"], "run": str(run)}
    out["held_out_start_mm"] = out["held_out_last_mm"] * out["held_out_last_reduction"]
    if mode == "in_time":
        out["time_integration"] = result.get("time_integration")
    return out


def test_window(mode: str, arm: Path, run: Path, cache: Path, fitted: list[int],
                test: list[int], edge: float, substeps: int) -> dict[str, float]:
    """The test frames' mean surface error (mm) at the homogeneous start and at ``run``'s
    chosen iterate (its ``params_best_validation.pt``), on the fit's mesh."""
    from torchfit.problems import build_problem

    settings: dict[str, Any] = {"path": str(arm), "cache_dir": str(cache),
                                "tet_edge_length": edge, "frames": fitted,
                                "validation_frames": test}
    if mode == "in_time":
        settings.update(dynamic=True, substeps=substeps)
    problem = build_problem("animation", settings).validation_problem()
    chosen = torch.load(run / "params_best_validation.pt", weights_only=False)["theta"]
    out = {}
    for name, theta in (("start", problem.theta0), ("chosen", chosen.to(problem.theta0))):
        with torch.no_grad():
            x = problem.simulate(problem.simulation_input(theta))
            out[f"test_{name}_mm"] = 1e3 * float(problem.observation.surface_errors(x, problem.x_true).mean())
    out["test_reduction"] = out["test_start_mm"] / out["test_chosen_mm"]
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--frames", type=int, default=24, help="frames of the shot (24 fps)")
    parser.add_argument("--fitted", type=int, default=12, help="frames 0 .. N-1 are fitted")
    parser.add_argument("--select", type=int, default=0, help="the first K held-out frames "
                        "choose the iterate, the rest are the test window (0: all choose)")
    parser.add_argument("--jiggle", type=float, default=1.0, help="write_arm.py --jiggle")
    parser.add_argument("--tet-edge", type=float, default=0.06)
    parser.add_argument("--substeps", type=int, default=4)
    parser.add_argument("--max-iter", type=int, default=20)
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--only", choices=["quasistatic", "in_time"], default=None)
    args = parser.parse_args(argv)
    if not 0 < args.fitted < args.frames or not 0 <= args.select < args.frames - args.fitted:
        parser.error("need 0 < --fitted < --frames and 0 <= --select < --frames - --fitted")
    torch.set_num_threads(1)
    work = args.workdir or Path(tempfile.mkdtemp(prefix="torchfit_jiggle_"))
    arm, cache = work / "arm", work / "cache"
    if not (arm / "animation.yaml").is_file():
        subprocess.run([sys.executable, "scripts/write_arm.py", str(arm), "--n-frames",
                        str(args.frames), "--jiggle", str(args.jiggle)], cwd=REPO, check=True,
                       capture_output=True)
    fitted = list(range(args.fitted))
    later = list(range(args.fitted, args.frames))
    held, test = (later[:args.select], later[args.select:]) if args.select else (later, [])
    report: dict[str, Any] = {"machine": machine_info(), "settings": vars(args) | {
        "out": str(args.out), "workdir": str(work)}, "fitted_frames": fitted,
        "held_out_frames": held, "test_frames": test}
    for mode in ("quasistatic", "in_time"):
        if args.only and mode != args.only:
            continue
        run = work / mode
        report[mode] = fit(mode, arm, run, cache, fitted, held, args.tet_edge, args.substeps,
                           args.max_iter)
        if test:
            report[mode].update(test_window(mode, arm, run, cache, fitted, test,
                                            args.tet_edge, args.substeps))
    if "quasistatic" in report and "in_time" in report:
        q, d = report["quasistatic"], report["in_time"]
        report["ratio_held_out_last"] = d["held_out_last_reduction"] / q["held_out_last_reduction"]
        report["ratio_held_out_chosen"] = \
            d["held_out_chosen_reduction"] / q["held_out_chosen_reduction"]
        report["ratio_fitted"] = d["fitted_reduction"] / q["fitted_reduction"]
        if test:
            report["ratio_test"] = d["test_reduction"] / q["test_reduction"]
    emit_report(report, args.out)


if __name__ == "__main__":
    main()
