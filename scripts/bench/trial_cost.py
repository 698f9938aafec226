"""Cost of rejected against accepted Levenberg-Marquardt iterations, with and without the
trial budget (``NewtonOptions.trial_factor``) and the predictor start.

Builds a capsule bent far at its joint (two bones; frames 0 to ``--max-angle`` degrees,
a rotation of the upper half), fits it with the problem ``animation`` and the solver
``levenberg_marquardt`` once per variant, and prints per iteration: accepted, factorisations,
solves and wall seconds; then the mean of accepted and rejected iterations, as JSON
(``--out``). ``--problem arm3d`` (or ``arm3d_short``) fits the arm instead (its own frames and
mesh settings).

    python scripts/bench/trial_cost.py --out /tmp/trial_cost.json
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from torchfit.mesh import Skeleton, write_animation
from torchfit.mesh.rig import blend, distance_weights, segment_distances
from torchfit.problems import build_problem
from torchfit.solvers.levenberg_marquardt import LevenbergMarquardt, LevenbergMarquardtConfig

RADIUS, HALF = 0.04, 0.12


def write_bent_capsule(folder: Path, angles: list[float]) -> Path:
    """A capsule along z, upper bone turned about y by ``angles`` (degrees) at the joint,
    linear blend skinning plus a bulge the material can explain."""
    mesh = trimesh.creation.capsule(height=2 * HALF, radius=RADIUS, count=[16, 16])
    rest, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    heads = np.array([[0, 0, -HALF], [0, 0, 0.0]])
    tails = np.array([[0, 0, 0.0], [0, 0, HALF]])
    transforms = np.zeros((len(angles), 2, 3, 4))
    transforms[:, :, :, :3] = np.eye(3)
    for f, degrees in enumerate(angles):
        a = np.radians(degrees)
        transforms[f, 1, :, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    weights = distance_weights(segment_distances(rest, heads, tails), 1.5 * RADIUS)
    lower = np.clip(-rest[:, 2] / HALF, 0, 1) * np.clip(rest[:, 0] / RADIUS, 0, 1) ** 2
    bulge = np.zeros((len(angles), len(rest), 3))
    bulge[:, :, 0] = 0.004 * (np.asarray(angles) / max(angles))[:, None] * lower[None]
    frames = blend(rest, weights, transforms) + bulge
    skeleton = Skeleton(heads, tails, transforms, 0.4 * RADIUS, None, ["lower", "upper"])
    write_animation(folder, rest, faces, frames, skeleton=skeleton)
    return folder


def run(problem_name: str, settings: dict, variant: dict, max_iter: int) -> dict:
    problem = build_problem(problem_name, settings)
    newton = problem.poses.quasistatic.equilibrium.newton
    for key, value in variant.items():
        setattr(newton, key, value)
    solver = LevenbergMarquardt(LevenbergMarquardtConfig(max_iter=max_iter, max_step=1.0))
    start = time.perf_counter()
    result = solver.solve(problem.residual(), problem.theta0)
    rows, previous = [], result.history[0]
    for rec in result.history[1:]:
        rows.append({"iteration": rec.iteration, "accepted": bool(rec.accepted),
                     "factorizations": rec.factorizations - previous.factorizations,
                     "solves": rec.solves - previous.solves,
                     "wall_s": rec.wall_time - previous.wall_time, "misfit": rec.misfit})
        previous = rec
    summary = {}
    for kind, accepted in (("accepted", True), ("rejected", False)):
        chosen = [r for r in rows if r["accepted"] == accepted]
        summary[kind] = {"n": len(chosen), **{key: (sum(r[key] for r in chosen) / len(chosen)
                                                    if chosen else None)
                                              for key in ("factorizations", "solves", "wall_s")}}
    return {"variant": variant, "rows": rows, "summary": summary, "misfit": result.history[-1].misfit,
            "total_s": time.perf_counter() - start}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problem", default="capsule", choices=["capsule", "arm3d", "arm3d_short"])
    parser.add_argument("--max-angle", type=float, default=150.0)
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--max-iter", type=int, default=10)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--variants", default="0,2.5,2.5p",
                        help="trial_factor per run, comma-separated; suffix p: predictor on")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    cache = Path(tempfile.mkdtemp(prefix="trial-cost-"))
    if args.problem == "capsule":
        angles = list(np.linspace(0.0, args.max_angle, args.frames))
        settings = {"path": str(write_bent_capsule(cache / "capsule", angles)),
                    "tet_edge_length": 0.08, "grid": [2, 2, 3], "cache_dir": str(cache)}
        name = "animation"
    else:
        # arm3d_short is conf/problem/arm3d_short.yaml: the arm with these overrides
        settings = {"tet_edge_length": 0.06, "frames": [0, 3, 6, 9, 11]} \
            if args.problem == "arm3d_short" else {}
        name = "arm3d"
    out = []
    for token in args.variants.split(","):
        variant = {"trial_factor": float(token.rstrip("p")), "trial_predictor": token.endswith("p")}
        report = run(name, settings, variant, args.max_iter)
        out.append(report)
        for row in report["rows"]:
            print(json.dumps({**variant, **row}), flush=True)
        print(json.dumps({**variant, **report["summary"], "misfit": report["misfit"],
                          "total_s": report["total_s"]}), flush=True)
    if args.out is not None:
        args.out.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
