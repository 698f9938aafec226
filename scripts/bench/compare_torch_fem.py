#!/usr/bin/env python
"""torchfit against torch-fem on the same elastic tet box: answers first, then time.

The problem (built here, handed to torch-fem as an ``.npz``): ``box_tetrahedra(n, n, m)``
(6 tetrahedra per cube, the box ``1 x 1 x m/n``), Young's modulus ``exp(0.5 N(0, 1))``
per tetrahedron (seeded), Poisson 0.3, float64, linear (small-strain) elasticity; the
``z = 0`` face clamped, the top face moved by ``(0.02, 0.01, -0.03) * height``. The
scalar of the backward is ``L = sum(w * u)`` over all nodes (``w`` seeded normal), its
gradient taken with respect to the element moduli (both sides use an adjoint solve).

torchfit: ``QuasistaticElasticity`` (``material='linear'``) with ``backend=pardiso`` and
``backend=amg`` (the hierarchy built once, reused by the adjoint). torch-fem (0.14, in
its own venv, ``--torch-fem-python``): ``Solid`` with ``IsotropicElasticity3D(E, 0.3)``
and ``solve(differentiable_parameters=E)``, its default solver (above 10,000 dofs CG with
its pyamg smoothed-aggregation V-cycle, Chebyshev smoothing, ``stol = 1e-10``; direct
below), run in a subprocess. Timed: forward (one solve, assembly included, the model and
mesh built beforehand) and forward + backward; the minimum of ``--repeats`` runs (one
run above 100k tetrahedra). Checked first: the relative differences of the displacements
and of the gradients (torch-fem's default against torchfit pardiso, and amg against
pardiso). Prints a table and JSON (``--out``).

``--material stable_neo_hookean``: torchfit's stable neo-Hookean energy, handed to
torch-fem as a ``Hyperelastic3D`` energy function (stress and tangent by its autograd),
both Newton solves to ``rtol = 1e-10``, ``atol = 1e-12``.

    python scripts/bench/compare_torch_fem.py --boxes 7x7x17 13x13x40 25x25x80 \\
        --torch-fem-python /work/tfem-venv/bin/python --out compare.json
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

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

MOVE = np.array([0.02, 0.01, -0.03])     # top-face displacement per unit height


def make_problem(box: str, seed: int) -> dict[str, np.ndarray]:
    """Mesh, field and boundary conditions of one box (numpy arrays, the ``.npz``)."""
    from torchfit.mesh import box_tetrahedra

    nx, ny, nz = map(int, box.split("x"))
    mesh = box_tetrahedra(nx, ny, nz, (1.0, ny / nx, nz / nx))
    points, cells = np.asarray(mesh.points), np.asarray(mesh.cells, dtype=np.int64)
    rng = np.random.default_rng(seed)
    E = np.exp(0.5 * rng.standard_normal(len(cells)))
    height = points[:, 2].max()
    bottom = np.nonzero(points[:, 2] <= 1e-12)[0]
    top = np.nonzero(points[:, 2] >= height - 1e-12)[0]
    weights = rng.standard_normal(points.shape)
    return {"points": points, "cells": cells, "E": E, "bottom": bottom, "top": top,
            "top_move": MOVE * height, "weights": weights}


# -- torch-fem (runs in its own venv: imports nothing of torchfit) ---------------------------
def stable_neo_hookean_psi(F: Any, params: Any) -> Any:
    """torchfit's ``stable_neo_hookean`` energy density (Smith, de Goes and Kim 2018, with
    their rest-consistent Lame parameters) for torch-fem's ``Hyperelastic3D``;
    ``params = (mu, lam)``."""
    import torch

    mu_s = 4.0 / 3.0 * params[0]
    lam_s = params[1] + 5.0 / 6.0 * params[0]
    alpha = 1.0 + 0.75 * mu_s / lam_s
    I_C = (F * F).sum()
    J = (F[0, 0] * (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1])
         - F[0, 1] * (F[1, 0] * F[2, 2] - F[1, 2] * F[2, 0])
         + F[0, 2] * (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]))     # functorch-safe det
    rest = 0.5 * lam_s * (1.0 - alpha) ** 2 - 0.5 * mu_s * np.log(4.0)
    return (0.5 * mu_s * (I_C - 3.0) + 0.5 * lam_s * (J - alpha) ** 2
            - 0.5 * mu_s * torch.log(I_C + 1.0) - rest)


def torch_fem_worker(problem_path: str, out_path: str, repeats: int) -> None:
    import torch
    from torchfem import Solid
    from torchfem.materials import Hyperelastic3D, IsotropicElasticity3D

    torch.set_default_dtype(torch.float64)
    data = np.load(problem_path)
    nodes = torch.from_numpy(data["points"])
    elements = torch.from_numpy(data["cells"])
    weights = torch.from_numpy(data["weights"])
    material = str(data["material"])
    # Newton to torchfit's tolerances where it iterates (torch-fem's default: 1e-8 / 1e-6)
    newton = {} if material == "linear" else {"rtol": 1e-10, "atol": 1e-12}

    def model(E: torch.Tensor) -> Any:
        if material == "linear":
            law = IsotropicElasticity3D(E, 0.3)
        else:
            nu = 0.3
            params = torch.stack([E / (2.0 * (1.0 + nu)),
                                  E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))], dim=1)
            law = Hyperelastic3D(stable_neo_hookean_psi, params)
        solid = Solid(nodes, elements, law)
        bottom, top = torch.from_numpy(data["bottom"]), torch.from_numpy(data["top"])
        solid.constraints[bottom, :] = True
        solid.constraints[top, :] = True
        solid.displacements[top, :] = torch.from_numpy(data["top_move"])
        return solid

    def forward() -> torch.Tensor:
        solid = model(torch.from_numpy(data["E"]))
        start = time.perf_counter()
        u = solid.solve(**newton)[0]
        return u, time.perf_counter() - start

    def forward_backward() -> tuple[torch.Tensor, torch.Tensor, float]:
        E = torch.from_numpy(data["E"]).clone().requires_grad_(True)
        solid = model(E)
        start = time.perf_counter()
        u = solid.solve(differentiable_parameters=E, **newton)[0]
        (grad,) = torch.autograd.grad((weights * u).sum(), E)
        return u.detach(), grad, time.perf_counter() - start

    fwd, fb = [], []
    for _ in range(repeats):
        u, seconds = forward()
        fwd.append(seconds)
        u_b, grad, seconds = forward_backward()
        fb.append(seconds)
    from torchfem.sparse import describe_method, resolve_method

    n_dofs = 3 * len(nodes)
    method = resolve_method(n_dofs, None)
    np.savez(out_path, u=u.detach().numpy(), grad=grad.numpy(), forward_s=np.array(fwd),
             forward_backward_s=np.array(fb),
             method=np.array(describe_method(method, "cpu", None)))


def run_torch_fem(python: str, problem: dict[str, np.ndarray], repeats: int) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        problem_path, out_path = Path(tmp) / "problem.npz", Path(tmp) / "out.npz"
        np.savez(problem_path, **problem)
        subprocess.run([python, __file__, "--torch-fem-worker", str(problem_path),
                        str(out_path), "--repeats", str(repeats)], check=True)
        out = np.load(out_path)
        return {key: out[key] for key in out.files}


# -- torchfit ---------------------------------------------------------------------------------
def run_torchfit(backend: str, problem: dict[str, np.ndarray], repeats: int,
                 material: str = "linear") -> dict[str, Any]:
    import torch

    from torchfit.linalg import counting
    from torchfit.physics.elasticity import QuasistaticElasticity, SimplicialElasticity

    points = torch.from_numpy(problem["points"])
    model = SimplicialElasticity(points, torch.from_numpy(problem["cells"]), material, nu=0.3)
    bottom, top = problem["bottom"], problem["top"]
    qs = QuasistaticElasticity(model, np.concatenate([bottom, top]), backend=backend)
    moved = points[top] + torch.from_numpy(problem["top_move"])
    positions = torch.cat([points[bottom], moved])[None]
    weights = torch.from_numpy(problem["weights"])[None]
    E0 = torch.from_numpy(problem["E"])
    rest = points[None]
    fwd, fb = [], []
    for _ in range(repeats):
        qs.clear_cache()
        start = time.perf_counter()
        x = qs(E0, positions)
        fwd.append(time.perf_counter() - start)
        qs.clear_cache()
        E = E0.clone().requires_grad_(True)
        with counting() as counts:
            start = time.perf_counter()
            x = qs(E, positions)
            (grad,) = torch.autograd.grad((weights * (x - rest)).sum(), E)
            fb.append(time.perf_counter() - start)
    u = (x.detach() - rest).reshape(-1, 3).numpy()
    return {"u": u, "grad": grad.numpy(), "forward_s": np.array(fwd),
            "forward_backward_s": np.array(fb), "counts": counts.as_dict()}


def rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--boxes", nargs="+", default=["9x9x10"],
                        help="NXxNYxNZ boxes (6 tetrahedra per cube)")
    parser.add_argument("--torch-fem-python", default="/work/tfem-venv/bin/python")
    parser.add_argument("--backends", nargs="+", default=["pardiso", "amg"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--material", choices=["linear", "stable_neo_hookean"],
                        default="linear", help="stable_neo_hookean: torchfit's energy "
                        "handed to torch-fem's Hyperelastic3D, Newton to 1e-10 / 1e-12")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--torch-fem-worker", nargs=2, metavar=("PROBLEM", "OUT"),
                        help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.torch_fem_worker:
        torch_fem_worker(*args.torch_fem_worker, args.repeats)
        return 0

    sys.path[:0] = [str(ROOT), str(ROOT / "scripts" / "bench")]
    from benchtools import machine_info

    report: dict[str, Any] = {"machine": machine_info(), "material": args.material, "boxes": {}}
    print(f"{'box':>10s} {'tets':>8s} {'solver':>14s} {'forward':>9s} {'fwd+bwd':>9s} "
          f"{'ratio fb':>9s} {'rel du':>8s} {'rel dgrad':>9s}")
    for box in args.boxes:
        problem = make_problem(box, args.seed)
        problem["material"] = np.array(args.material)
        n_tets = len(problem["cells"])
        repeats = args.repeats if n_tets <= 100_000 else 1
        results = {"torch-fem": run_torch_fem(args.torch_fem_python, problem, repeats)}
        for backend in args.backends:
            results[backend] = run_torchfit(backend, problem, repeats, args.material)
        reference = results[args.backends[0]]
        base = float(results["torch-fem"]["forward_backward_s"].min())
        entry: dict[str, Any] = {"tets": n_tets, "dofs": 3 * len(problem["points"]),
                                 "torch_fem_method": str(results["torch-fem"]["method"])}
        for name, result in results.items():
            row = {"forward_s": float(result["forward_s"].min()),
                   "forward_backward_s": float(result["forward_backward_s"].min()),
                   "rel_diff_u": rel(result["u"], reference["u"]),
                   "rel_diff_grad": rel(result["grad"], reference["grad"])}
            row["fb_ratio_to_torch_fem"] = row["forward_backward_s"] / base
            if "counts" in result:
                row["counts"] = result["counts"]
            entry[name] = row
            print(f"{box:>10s} {n_tets:8d} {name:>14s} {row['forward_s']:9.2f} "
                  f"{row['forward_backward_s']:9.2f} {row['fb_ratio_to_torch_fem']:9.2f} "
                  f"{row['rel_diff_u']:8.1e} {row['rel_diff_grad']:9.1e}", flush=True)
        report["boxes"][box] = entry
    text = json.dumps(report, indent=2, default=str)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
