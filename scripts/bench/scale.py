#!/usr/bin/env python
"""Scale benchmark: the arm at several mesh sizes on 1 and 2 processes, and a cost model.

Issue 30, item 5 (docs/notes/scale.md). For every size (``--sizes label:edge:epsilon``:
pytetwild's edge length and envelope, fractions of the bounding-box diagonal; the arm's
count follows the envelope more than the edge) and every process count (``--ranks``), a
fresh process (a ``torchrun --standalone --nproc_per_node=R`` job for ``R > 1``) builds
``problem=arm3d`` and measures, with counted factorisations and solves:

* ``setup``: the problem built twice (the first build tetrahedralises unless the mesh is
  in ``--cache-dir``; the time pytetwild took is stored with the cached mesh), the second
  reads the cache (one process only);
* ``simulate``: every frame at ``theta0`` from the animated pose (a fresh process), its
  Newton iterations (rank 0's frames under torchrun) and factorisations;
* ``jacobian``: the whole dense ``J`` at ``theta0`` (every parameter direction a
  right-hand side of each frame's factorisation), and ``J^T J`` formed from it;
* ``lm_accepted``: one Levenberg-Marquardt iteration from ``theta0`` with the arm's
  settings (``max_step=1``), warm starts as after the simulation (restored);
* ``lm_rejected``: the same with ``damping_init=--rejected-damping`` (default 1e-8) and
  ``max_step=--rejected-max-step`` (default 3): a nearly Gauss-Newton step far from
  ``theta0``, rejected by the gain ratio (the JSON says whether it was);
* ``peak_rss_MB``: the process's maximum resident set (every rank's largest under torchrun).

The arm's 48 frames hold 23 distinct poses, simulated once each (problems/body/repeated_poses.py);
under torchrun the ranks split the poses (12 + 11) and keep their rows of ``J``, rank 0
sums ``J^T J`` (run/distributed/rows.py). Each figure carries ``n_simulated_frames`` and
``split``; cases measured before the pose split (no ``split``) are checked as they ran:
every frame split over the ranks, ``J`` gathered on rank 0. ``--frames label=0,4,8`` fits
a subset of the frames at a size.

Then the model (scripts/tools/scale_model.py): per-frame costs fitted as power laws in the
tetrahedron count, checked against the measured LM iterations (1 and 2 processes), and its
prediction for ``--target-tets`` x ``--target-frames`` on ``--target-ranks`` at
``--bandwidths-gbit``. JSON to stdout and ``--out``; the table to stderr.

    .venv/bin/python scripts/bench/scale.py --out /work/scratch/scale.json \
        --cache-dir /work/scratch/scale-cache
    .venv/bin/python scripts/bench/scale.py --model-only /work/scratch/scale.json
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(REPO / "scripts" / "tools"))
sys.path.insert(0, str(REPO))

import scale_model  # noqa: E402

DEFAULT_SIZES = ["10k:0.028:0.001", "40k:0.016:0.0005", "160k:0.009:0.00025"]


def maxrss_mb(who: int) -> float:
    """Peak resident set (MB) of this process or of its largest waited-for child (Linux KB)."""
    return resource.getrusage(who).ru_maxrss / 1024.0


def loadavg() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def parse_size(text: str) -> dict[str, Any]:
    label, edge, epsilon = text.split(":")
    return {"label": label, "tet_edge_length": float(edge), "tet_epsilon": float(epsilon)}


def parse_frames(items: list[str]) -> dict[str, list[int]]:
    out = {}
    for item in items:
        label, numbers = item.split("=")
        out[label] = [int(f) for f in numbers.split(",") if f]
    return out


# -- inside a measuring process ----------------------------------------------------------
def settings_of(job: dict[str, Any]) -> dict[str, Any]:
    settings = {"tet_edge_length": job["tet_edge_length"], "tet_epsilon": job["tet_epsilon"],
                "model": job["model"], "cache_dir": job["cache_dir"],
                "backend": job["backend"]}
    if job.get("frames"):
        settings["frames"] = list(job["frames"])
    return settings


def build(settings: dict[str, Any]):
    from torchfit.problems import build_problem
    return build_problem("arm3d", dict(settings))


def lm_iteration(problem, theta0, state, config) -> dict[str, Any]:
    """One LM iteration (``max_iter=1``) from ``theta0`` with the warm starts ``state``."""
    from benchtools import timed
    from torchfit.run.solver import build_solver

    problem.warm_starts.restore_warm_start_state(state, problem.device)
    solver = build_solver(problem, config)
    seconds, result, counts = timed(lambda: solver.solve(problem.residual(), theta0, []))
    history = result.history
    return {"s": seconds, "counts": counts, "accepted": bool(history[-1].accepted),
            "iterations": len(history) - 1,
            "misfit": [float(r.misfit) for r in history],
            "record_wall_s": [float(r.wall_time) for r in history],
            "record_factorizations": [int(r.factorizations) for r in history],
            "damping_init": config.damping_init, "max_step": config.max_step}


def normal_seconds(jacobian) -> float:
    """Seconds of ``J^T J`` (one process's product; under torchrun the ranks' partial
    products summed on rank 0, :mod:`torchfit.run.distributed.rows`)."""
    from benchtools import timed
    return timed(lambda: jacobian.T @ jacobian)[0]


def save_partial(job: dict[str, Any], out: dict[str, Any]) -> None:
    """What is measured so far, in the child's output (a killed run leaves it)."""
    if job.get("partial_path"):
        Path(job["partial_path"]).write_text(json.dumps({**out, "partial": True}))


def measure(problem, job: dict[str, Any], n_ranks: int,
            known: dict[str, Any] | None = None) -> dict[str, Any]:
    """Simulate, Jacobian, LM accepted and rejected on ``problem`` (rank 0's view); after
    each, what is known so far (``known`` and the figures) is saved (:func:`save_partial`)."""
    import torch
    from benchtools import timed
    from torchfit.solvers import LevenbergMarquardtConfig

    poses = problem.poses.repeated_poses
    n_sim = int(poses[0].numel()) if poses is not None else int(problem.n_frames)
    n_params = int(problem.parameterization.n_params)
    out: dict[str, Any] = {
        "n_tets": int(problem.model.n_cells), "n_vertices": int(problem.model.n_vertices),
        "n_frames": int(problem.n_frames),
        "n_simulated_frames": n_sim, "n_params": n_params,
        "n_obs": int(problem.data.numel()) // (3 * int(problem.n_frames)),
        "backend": str(problem.backend), "ranks": n_ranks,
        # the ranks split the distinct poses and keep their rows of J (run/distributed_rows)
        "split": "poses", **(known or {})}
    theta0 = problem.theta0.detach().clone()
    # nothing simulated yet may answer from the cache (describe() simulates the baseline)
    problem.poses.quasistatic.equilibrium.clear_cache()
    load = loadavg()
    with torch.no_grad():
        t, _, counts = timed(lambda: problem.forward(theta0))
    newton = [int(i) for i in problem.poses.quasistatic.last_newton_iterations]
    out["simulate"] = {"s": t, "counts": counts, "per_simulated_frame_s": t / n_sim,
                       "newton_iterations_rank0": newton, "loadavg": load}
    save_partial(job, out)
    state = problem.warm_starts.warm_start_state()
    load = loadavg()
    t, jacobian, counts = timed(lambda: problem.forward_jacobian(theta0))
    shape = tuple(jacobian.shape)
    t_normal = normal_seconds(jacobian)
    out["jacobian"] = {"s": t, "counts": counts, "shape": list(shape),
                       # the whole J's size (under torchrun its rows stay on the ranks)
                       "MB": shape[0] * shape[1] * problem.theta0.element_size() / 1e6,
                       "per_frame_column_s": t / (n_sim * n_params), "loadavg": load,
                       "JtJ_s": t_normal,
                       "JtJ_flops_per_s": shape[0] * shape[1] ** 2 / max(t_normal, 1e-9)}
    del jacobian
    save_partial(job, out)
    accepted = LevenbergMarquardtConfig(max_iter=1, max_step=1.0)
    load = loadavg()
    out["lm_accepted"] = {**lm_iteration(problem, theta0, state, accepted), "loadavg": load}
    save_partial(job, out)
    if job.get("rejected", True):
        rejected = dataclasses.replace(accepted, damping_init=job["rejected_damping"],
                                       max_step=job["rejected_max_step"])
        load = loadavg()
        out["lm_rejected"] = {**lm_iteration(problem, theta0, state, rejected), "loadavg": load}
    out["n_free_dofs"] = int(problem.describe()["n_free_dofs"])   # after: it simulates
    return out


def run_single(job: dict[str, Any]) -> dict[str, Any]:
    """One process: build twice (cold, then cached), then :func:`measure`."""
    from torchfit.linalg import set_threads
    set_threads(job["threads"])
    settings = settings_of(job)
    load = loadavg()
    start = time.perf_counter()
    first = build(settings)
    first_s = time.perf_counter() - start
    setup = {"first_build_s": first_s, "first_tet_cache_hit": bool(first.tet.from_cache),
             "tetrahedralize_s": float(first.tet.build_seconds), "loadavg": load}
    del first
    start = time.perf_counter()
    problem = build(settings)
    setup["cached_build_s"] = time.perf_counter() - start
    setup["cold_build_s"] = (first_s if not setup["first_tet_cache_hit"] else
                             setup["cached_build_s"] + setup["tetrahedralize_s"])
    out = measure(problem, job, 1, {"setup": setup})
    out["peak_rss_MB_rank0"] = maxrss_mb(resource.RUSAGE_SELF)
    return out


def run_distributed(job: dict[str, Any]) -> dict[str, Any] | None:
    """Under torchrun: rank 0 leads (:meth:`torchfit.run.distributed.DistributedSession.lead`)
    and measures, the others serve; a gather bandwidth probe first. Returns rank 0's
    figures."""
    import torch
    import torch.distributed as dist
    from torchfit.linalg import set_threads
    from torchfit.run import distributed

    set_threads(job["threads"])
    distributed.start_group()
    session = distributed.DistributedSession()
    rank, size = dist.get_rank(), dist.get_world_size()
    probe = gather_bandwidth(torch, dist, rank, size)
    config = {"solver": {"name": "levenberg_marquardt", "dense_jacobian_max_params": 10 ** 6},
              "problem": settings_of(job)}
    if rank > 0:
        code = session.serve(lambda cfg: build(cfg["problem"]))
        if code:
            raise SystemExit(code)
        return None
    load = loadavg()
    start = time.perf_counter()
    problem = build(config["problem"])
    setup = {"rank0_build_s": time.perf_counter() - start,
             "tet_cache_hit": bool(problem.tet.from_cache), "loadavg": load}
    try:
        start = time.perf_counter()
        session.lead(problem, config)
        setup["lead_s"] = time.perf_counter() - start
        out = measure(problem, job, size, {"setup": setup, "gather_probe": probe})
    finally:
        session.stop()
    out["peak_rss_MB_rank0"] = maxrss_mb(resource.RUSAGE_SELF)
    return out


def gather_bandwidth(torch, dist, rank: int, size: int, mb: float = 64.0) -> dict[str, Any]:
    """Bytes per second of a ``dist.gather`` of ``mb`` MB per worker into rank 0 (gloo)."""
    n = int(mb * 1e6 / 8)
    buffer = torch.ones(n, dtype=torch.float64)
    parts = [torch.empty_like(buffer) for _ in range(size)] if rank == 0 else None
    times = []
    for _ in range(3):
        dist.barrier()
        start = time.perf_counter()
        dist.gather(buffer, parts, dst=0)
        times.append(time.perf_counter() - start)
    received = (size - 1) * n * 8
    return {"MB_per_worker": mb, "seconds": times,
            "bytes_per_s": received / min(times) if times else None}


# -- the parent ---------------------------------------------------------------------------
def run_job(job: dict[str, Any], n_ranks: int, python: str) -> dict[str, Any]:
    """Run one size on ``n_ranks`` processes in a fresh child; its figures with peak RSS."""
    with tempfile.TemporaryDirectory(prefix="bench-scale-") as tmp:
        job_path, out_path = Path(tmp) / "job.json", Path(tmp) / "out.json"
        job_path.write_text(json.dumps(job))
        inner = [str(HERE / "scale.py"), "--child", str(job_path), "--child-out",
                 str(out_path)]
        if n_ranks == 1:
            command = [python, *inner]
        else:
            command = [python, "-m", "torch.distributed.run", "--standalone",
                       f"--nproc_per_node={n_ranks}", *inner]
        wrapper = [python, str(HERE / "scale.py"), "--rss-of", *command]
        start = time.perf_counter()
        proc = subprocess.run(wrapper, cwd=REPO, capture_output=True, text=True)
        wall = time.perf_counter() - start
        partial = proc.returncode != 0 and out_path.is_file()
        if proc.returncode != 0 and not partial:
            return {"label": job["label"], "ranks": n_ranks, "failed": True,
                    "returncode": proc.returncode, "stderr_tail": proc.stderr[-2000:],
                    "wall_s": wall}
        out = json.loads(out_path.read_text())
        if partial:
            out.update({"returncode": proc.returncode, "stderr_tail": proc.stderr[-2000:]})
        rss = [line for line in proc.stdout.splitlines() if line.startswith("peak_rss_MB ")]
        out["peak_rss_MB_any_process"] = float(rss[-1].split()[1]) if rss else None
        out.update({"label": job["label"], "tet_edge_length": job["tet_edge_length"],
                    "tet_epsilon": job["tet_epsilon"], "model": job["model"],
                    "frames": job.get("frames"), "threads": job["threads"],
                    "job_wall_s": wall})
        return out


def rss_wrapper(command: list[str]) -> int:
    """Run ``command``; print the largest RSS of any process it started (fresh wrapper)."""
    code = subprocess.call(command)
    print(f"peak_rss_MB {maxrss_mb(resource.RUSAGE_CHILDREN):.1f}", flush=True)
    return code


def model_report(cases: list[dict[str, Any]], args: argparse.Namespace) -> dict[str, Any]:
    """Power laws from the one-process cases, the check against every measured LM
    iteration, and the prediction table.

    Two estimates of a trial's simulation per frame: ``trial`` (cold), the cold simulation
    from the animated pose per simulated frame (an upper estimate), and ``trial_warm``, the
    cost per factorisation (``factorization`` law) times the factorisations per simulated
    frame of the measured accepted LM iterations (a trial starts from the last equilibrium;
    the Jacobian makes no factorisation, so every one of the iteration's is the trial's)."""
    single = [c for c in cases if not c.get("failed") and not c.get("partial")
              and c["ranks"] == 1
              and (not getattr(args, "fit_labels", None) or c["label"] in args.fit_labels)]
    if not single:
        return {"note": "no one-process case measured: no model"}
    tets = [c["n_tets"] for c in single]
    laws = {"trial": scale_model.fit_power_law(
                tets, [c["simulate"]["per_simulated_frame_s"] for c in single]),
            "column": scale_model.fit_power_law(
                tets, [c["jacobian"]["per_frame_column_s"] for c in single]),
            "factorization": scale_model.fit_power_law(
                tets, [c["simulate"]["s"] / max(c["simulate"]["counts"]["factorizations"], 1)
                       for c in single])}
    per_frame = [c["lm_accepted"]["counts"]["factorizations"] / c["n_simulated_frames"]
                 for c in single if c["lm_accepted"]["accepted"]] or [1.0]
    warm_factorizations = sum(per_frame) / len(per_frame)
    laws["trial_warm"] = {**laws["factorization"],
                          "a": laws["factorization"]["a"] * warm_factorizations,
                          "factorizations_per_frame": warm_factorizations}
    flops = min(c["jacobian"]["JtJ_flops_per_s"] for c in single)
    check = []
    for case in cases:
        if case.get("failed") or "jacobian" not in case:
            continue
        bandwidth = (case.get("gather_probe") or {}).get("bytes_per_s") or 1e9
        # cases measured before the pose split (no "split"): the ranks simulated every frame
        # and rank 0 gathered J
        poses = case.get("split") == "poses"
        n_frames = case["n_simulated_frames"] if poses or case["ranks"] == 1 \
            else case["n_frames"]
        design = "allreduce_JtJ" if poses else "gather_J"
        predicted = {trial: scale_model.predict_iteration(
            n_tets=case["n_tets"], n_frames=n_frames, n_ranks=case["ranks"],
            n_params=case["n_params"], n_obs=case["n_obs"], n_vertices=case["n_vertices"],
            trial_law=laws[trial], column_law=laws["column"], flops_per_s=flops,
            bandwidth_bytes_per_s=bandwidth, design=design)
            for trial in ("trial", "trial_warm")}
        for kind in ("lm_accepted", "lm_rejected"):
            if kind not in case:
                continue
            measured = case[kind]["s"]
            cold, warm = predicted["trial"]["seconds"], predicted["trial_warm"]["seconds"]
            check.append({"label": case["label"], "ranks": case["ranks"], "kind": kind,
                          "design": design,
                          "accepted": case[kind]["accepted"],
                          "n_simulated_frames": n_frames,
                          "predicted_s": cold, "measured_s": measured,
                          "measured_over_predicted": measured / cold,
                          "predicted_warm_s": warm,
                          "measured_over_predicted_warm": measured / warm,
                          "parts": predicted["trial"], "parts_warm": predicted["trial_warm"],
                          "bandwidth_bytes_per_s": bandwidth,
                          "loadavg": case[kind]["loadavg"]})
    n_vertices = args.target_tets / args.tets_per_vertex
    table = []
    for cold in scale_model.prediction_table(
            laws, n_tets=args.target_tets, n_frames=args.target_frames,
            ranks=args.target_ranks, bandwidths_gbit=args.bandwidths_gbit,
            n_params=args.target_params, n_obs=args.target_obs, n_vertices=int(n_vertices),
            flops_per_s=flops):
        warm = scale_model.predict_iteration(
            n_tets=args.target_tets, n_frames=args.target_frames, n_ranks=cold["ranks"],
            n_params=args.target_params, n_obs=args.target_obs, n_vertices=int(n_vertices),
            trial_law=laws["trial_warm"], column_law=laws["column"], flops_per_s=flops,
            bandwidth_bytes_per_s=scale_model.gbit(cold["bandwidth_gbit"]),
            design=cold["design"])
        table.append({**cold, "warm_seconds": warm["seconds"],
                      "warm_compute_s": warm["compute_s"]})
    return {"laws": laws, "fitted_to": [c["label"] for c in single],
            "JtJ_flops_per_s": flops, "check": check,
            "target": {"n_tets": args.target_tets, "n_frames": args.target_frames,
                       "n_params": args.target_params, "n_obs": args.target_obs,
                       "n_vertices": int(n_vertices)},
            "prediction": table}


def partial_text(c: dict[str, Any]) -> str:
    """What a killed run measured before it stopped."""
    parts = [f"partial (exit {c.get('returncode')}):"]
    sim = c.get("simulate")
    if sim:
        parts.append(f"simulate {sim['s']:.1f} s ({sim['per_simulated_frame_s']:.2f} s per "
                     f"simulated frame, {sim['counts']['factorizations']} factorisations, "
                     f"load {sim['loadavg'][0]:.1f})")
    if c.get("jacobian"):
        parts.append(f"Jacobian {c['jacobian']['s']:.1f} s "
                     f"({c['jacobian']['per_frame_column_s']:.2e} s per frame and column)")
    if c.get("lm_accepted"):
        parts.append(f"LM iteration {c['lm_accepted']['s']:.1f} s "
                     f"({c['lm_accepted']['counts']['factorizations']} factorisations, "
                     f"{'accepted' if c['lm_accepted']['accepted'] else 'rejected'})")
    return parts[0] + " " + "; ".join(parts[1:])


def table_lines(cases: list[dict[str, Any]], model: dict[str, Any]) -> list[str]:
    head = ("size  tets     procs frames(sim) setup cold/cached s  simulate s (/frame)  "
            "fact.  Jacobian s (/frame/col)  LM acc s  LM rej s (acc?)  peak RSS MB  load")
    lines = [head]
    for c in cases:
        if c.get("failed"):
            lines.append(f"{c['label']:5} {'':8} {c['ranks']:5} FAILED rc={c['returncode']}")
            continue
        if c.get("partial"):
            lines.append(f"{c['label']:5} {c['n_tets']:<8} {c['ranks']:5} {partial_text(c)}")
            continue
        setup = c["setup"]
        cold = setup.get("cold_build_s", float("nan"))
        cached = setup.get("cached_build_s", setup.get("rank0_build_s", float("nan")))
        rej, sim, jac = c.get("lm_rejected"), c["simulate"], c["jacobian"]
        rss = c.get("peak_rss_MB_any_process") or c["peak_rss_MB_rank0"]
        lines.append(
            f"{c['label']:5} {c['n_tets']:<8} {c['ranks']:5} "
            f"{c['n_frames']:3}({c['n_simulated_frames']:2})      {cold:7.1f}/{cached:6.1f}"
            f"    {sim['s']:7.1f} ({sim['per_simulated_frame_s']:.2f})   "
            f"{sim['counts']['factorizations']:5}  {jac['s']:7.1f} "
            f"({jac['per_frame_column_s']:.2e})       {c['lm_accepted']['s']:7.1f}  "
            + (f"{rej['s']:7.1f} ({rej['accepted']})" if rej else "   -          ")
            + f"   {rss:8.0f}   {sim['loadavg'][0]:.1f}")
    for row in model.get("check", []):
        lines.append(f"check {row['label']} {row['ranks']} proc {row['kind']}: predicted "
                     f"{row['predicted_s']:.1f} s (warm {row['predicted_warm_s']:.1f} s), "
                     f"measured {row['measured_s']:.1f} s, ratio "
                     f"{row['measured_over_predicted']:.2f} "
                     f"(warm {row['measured_over_predicted_warm']:.2f})")
    for row in model.get("prediction", []):
        lines.append(f"predict {row['design']:13} {row['bandwidth_gbit']:>5} Gbit/s "
                     f"{row['ranks']:3} ranks: {row['seconds']:9.1f} s, warm "
                     f"{row['warm_seconds']:9.1f} s (compute "
                     f"{row['compute_s']:.1f}, JtJ {row['normal_s']:.1f}, "
                     f"comm {row['comm_s']:.1f})")
    return lines


def markdown_lines(report: dict[str, Any]) -> list[str]:
    """The measured table, the model's check and its prediction as Markdown (docs)."""
    lines = ["| size | tets | procs | frames (simulated) | set-up cold / cached s | "
             "simulate s (per sim. frame) | factorisations (Newton its, rank 0) | "
             "Jacobian s (per frame and column) | LM accepted s | LM rejected s | "
             "peak RSS MB | load |", "|" + " --- |" * 12]
    for c in report["cases"]:
        if c.get("failed"):
            lines.append(f"| {c['label']} | | {c['ranks']} | failed | | | | | | | | |")
            continue
        if c.get("partial"):
            lines.append(f"| {c['label']} | {c['n_tets']:,} | {c['ranks']} | {c['n_frames']} "
                         f"({c['n_simulated_frames']}) | {partial_text(c)} |")
            continue
        setup, sim, jac = c["setup"], c["simulate"], c["jacobian"]
        cold = setup.get("cold_build_s")
        cached = setup.get("cached_build_s", setup.get("rank0_build_s"))
        rej = c.get("lm_rejected")
        rej_text = (f"{rej['s']:.1f} ({'accepted' if rej['accepted'] else 'rejected'}, "
                    f"{rej['counts']['factorizations']} fact.)" if rej else "-")
        lines.append(
            f"| {c['label']} | {c['n_tets']:,} | {c['ranks']} | {c['n_frames']} "
            f"({c['n_simulated_frames']}) | {'-' if cold is None else f'{cold:.1f}'} / "
            f"{cached:.1f} | {sim['s']:.1f} ({sim['per_simulated_frame_s']:.2f}) | "
            f"{sim['counts']['factorizations']} ({sum(sim['newton_iterations_rank0'])}) | "
            f"{jac['s']:.1f} ({jac['per_frame_column_s']:.2e}) | "
            f"{c['lm_accepted']['s']:.1f} ({c['lm_accepted']['counts']['factorizations']} "
            f"fact.) | {rej_text} | "
            f"{c.get('peak_rss_MB_any_process') or c['peak_rss_MB_rank0']:.0f} | "
            f"{sim['loadavg'][0]:.1f} |")
    model = report.get("model", {})
    if model.get("check"):
        lines += ["", "| size | procs | iteration | simulated frames | predicted s, cold "
                  "/ warm trial | measured s | measured / predicted, cold / warm | load |",
                  "|" + " --- |" * 8]
        for row in model["check"]:
            kind = row["kind"][3:] + ("" if row["accepted"] == (row["kind"] == "lm_accepted")
                                      else " (attempt accepted)")
            lines.append(f"| {row['label']} | {row['ranks']} | {kind} | "
                         f"{row['n_simulated_frames']} | {row['predicted_s']:.1f} / "
                         f"{row['predicted_warm_s']:.1f} | {row['measured_s']:.1f} | "
                         f"{row['measured_over_predicted']:.2f} / "
                         f"{row['measured_over_predicted_warm']:.2f} | "
                         f"{row['loadavg'][0]:.1f} |")
    if model.get("prediction"):
        lines += ["", "| design | link Gbit/s | ranks | frames per rank | compute s | "
                  "J^T J s | communication s (MB into rank 0) | iteration s, cold trial | "
                  "iteration s, warm trial | J per rank GB |", "|" + " --- |" * 10]
        for row in model["prediction"]:
            lines.append(f"| {row['design']} | {row['bandwidth_gbit']:g} | {row['ranks']} | "
                         f"{row['frames_per_rank']} | {row['compute_s']:.0f} | "
                         f"{row['normal_s']:.1f} | {row['comm_s']:.1f} "
                         f"({row['comm_bytes_rank0_in'] / 1e6:.0f}) | {row['seconds']:.0f} | "
                         f"{row['warm_seconds']:.0f} | {row['J_bytes_rank0'] / 1e9:.1f} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=DEFAULT_SIZES,
                        help="label:tet_edge_length:tet_epsilon")
    parser.add_argument("--frames", nargs="*", default=[],
                        help="label=0,4,8: fit these frames at that size (default all 48)")
    parser.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--ranks-for", nargs="*", default=[],
                        help="label=1: process counts at that size (default --ranks)")
    parser.add_argument("--no-rejected", nargs="*", default=[],
                        help="labels whose rejected LM iteration is skipped")
    parser.add_argument("--model", default="corotated")
    parser.add_argument("--backend", default="auto")
    parser.add_argument("--threads", type=int, default=1, help="per process")
    parser.add_argument("--rejected-damping", type=float, default=1e-8)
    parser.add_argument("--rejected-max-step", type=float, default=3.0)
    parser.add_argument("--cache-dir", default=None,
                        help="tet mesh and animation cache (default: a fresh temporary one)")
    parser.add_argument("--target-tets", type=float, default=300_000)
    parser.add_argument("--target-frames", type=int, default=500)
    parser.add_argument("--target-ranks", type=int, nargs="+", default=[1, 8, 64])
    parser.add_argument("--target-params", type=int, default=192)
    parser.add_argument("--target-obs", type=int, default=10_000,
                        help="observed surface vertices of the character (an assumption)")
    parser.add_argument("--tets-per-vertex", type=float, default=3.9,
                        help="tetrahedra per tet vertex (the arm's ratio)")
    parser.add_argument("--bandwidths-gbit", type=float, nargs="+", default=[10.0, 1.0])
    parser.add_argument("--model-only", type=Path, default=None,
                        help="recompute the model and table from an earlier --out")
    parser.add_argument("--fit-labels", nargs="*", default=[],
                        help="fit the laws to these sizes' one-process runs only (the same "
                             "frames at every size; default: every one-process run)")
    parser.add_argument("--markdown", action="store_true",
                        help="print the tables as Markdown to stderr (for docs/notes/scale.md)")
    parser.add_argument("--merge", type=Path, nargs="*", default=[],
                        help="with --model-only: add the cases of these earlier --out files")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--child", type=Path, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--child-out", type=Path, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--rss-of", nargs=argparse.REMAINDER, default=None,
                        help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    if args.rss_of is not None:
        return rss_wrapper(args.rss_of)
    if args.child is not None:
        job = {**json.loads(args.child.read_text()), "partial_path": str(args.child_out)}
        result = run_distributed(job) if int(os.environ.get("WORLD_SIZE", "1")) > 1 \
            else run_single(job)
        if result is not None:
            args.child_out.write_text(json.dumps(result))
        return 0

    from benchtools import emit_report, machine_info
    if args.model_only is not None:
        report = json.loads(args.model_only.read_text())
        for path in args.merge:
            report["cases"] += json.loads(path.read_text())["cases"]
        report["model"] = model_report(report["cases"], args)
    else:
        cache = args.cache_dir or tempfile.mkdtemp(prefix="torchfit-scale-")
        frames = parse_frames(args.frames)
        ranks_for = {k: [int(r) for r in v] for k, v in parse_frames(args.ranks_for).items()}
        cases = []
        for size in map(parse_size, args.sizes):
            job = {**size, "model": args.model, "backend": args.backend, "cache_dir": cache,
                   "threads": args.threads, "frames": frames.get(size["label"]),
                   "rejected": size["label"] not in args.no_rejected,
                   "rejected_damping": args.rejected_damping,
                   "rejected_max_step": args.rejected_max_step}
            for n_ranks in ranks_for.get(size["label"], args.ranks):
                case = run_job(job, n_ranks, sys.executable)
                cases.append(case)
                print("\n".join(table_lines([case], {})[1:]), file=sys.stderr, flush=True)
        report = {"benchmark": "scale", "machine": machine_info(), "cache_dir": cache,
                  "cases": cases}
        report["model"] = model_report(cases, args)
    lines = markdown_lines(report) if args.markdown else table_lines(report["cases"],
                                                                      report["model"])
    print("\n".join(lines), file=sys.stderr)
    emit_report(report, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
