#!/usr/bin/env python
"""Where does AMG-preconditioned CG beat PARDISO? The crossover of the ``amg`` backend.

Matrices: the linear-elastic stiffness (``nu = 0.3``, log-normal Young's modulus per
tetrahedron) of ``box_tetrahedra(n, n, 3.2 n)``-like boxes with the ``z = 0`` face fixed,
as ``SimplicialElasticity`` assembles it (``factorization.tet3d``), e.g. ``7x7x17``
(4,998 tets), ``13x13x40`` (40,560), ``18x18x52`` (101,088), ``25x25x80`` (300,000).

For every box and backend (``pardiso``: MKL PARDISO, analysis + numeric factorisation;
``amg``: the hierarchy with the 6 rigid-body modes of the free nodes; ``amg_translations``
with the 3 translations only, up to ``--translations-max`` tets): the factorisation time,
one solve of 1 right-hand side (both the minimum of ``--repeats``, at most 2 above 100k
tetrahedra: PARDISO's first factorisation of a pattern includes its analysis, the later
ones are numeric only; ``factorize_first_s`` is the first), one solve of
``--columns`` right-hand sides (the block a
Jacobian solves per frame; 192 for the arm: scale the per-column time), CG iterations,
and the relative difference of the AMG solutions from PARDISO's. Derived: ``forward``
(torchfit's linear forward: factorisation + 2 solves for PARDISO, whose solve is refined
once, + 1 for amg, whose solve is already at its tolerance), ``forward_backward`` (one
more solve: the adjoint) and ``jacobian_192`` (factorisation + 192 columns at the
block's per-column time: the arm's dense Jacobian per frame). Prints a table and JSON
(and writes ``--out``).

    python scripts/bench/amg.py --boxes 7x7x17 13x13x40 18x18x52 25x25x80 --out amg.json
"""
from __future__ import annotations

import argparse
import gc
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
for path in (ROOT, ROOT / "scripts" / "bench"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

from factorization import tet3d  # noqa: E402
from benchtools import emit_report, machine_info  # noqa: E402
from torchfit.linalg import counting, get_backend  # noqa: E402
from torchfit.mesh import box_tetrahedra  # noqa: E402
from torchfit.physics.elasticity import SimplicialElasticity  # noqa: E402


def rigid_modes(nx: int, ny: int, nz: int) -> np.ndarray:
    """The 6 rigid-body modes of the free dofs of ``tet3d(nx, ny, nz)`` (z = 0 fixed)."""
    mesh = box_tetrahedra(nx, ny, nz, (1.0, ny / nx, nz / nx))
    model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                 "linear", nu=0.3)
    free_nodes = np.nonzero(mesh.points[:, 2] > 1e-12)[0]
    free_dofs = (free_nodes[:, None] * 3 + np.arange(3)).reshape(-1)
    return model.near_nullspace().numpy()[free_dofs]


def timed(fn: Any) -> tuple[float, Any]:
    start = time.perf_counter()
    out = fn()
    return time.perf_counter() - start, out


def bench_backend(name: str, pattern: Any, values: torch.Tensor, modes: np.ndarray | None,
                  rhs: torch.Tensor, reference: dict[str, torch.Tensor] | None,
                  repeats: int) -> dict[str, Any]:
    backend = get_backend("amg" if name.startswith("amg") else name)
    if name == "amg":
        backend.set_near_nullspace(pattern, modes)
    gc.collect()
    factor_times, one_times = [], []
    for _ in range(repeats):        # the minimum of repeats: the machine is shared
        factor = None
        gc.collect()
        with counting() as counts:
            t_factor, factor = timed(lambda: backend.factorize(pattern, values, True))
            t_one, x_one = timed(lambda: factor.solve(rhs[:, 0]))
            iterations_one = getattr(factor, "iterations", None)
            t_block, x_block = timed(lambda: factor.solve(rhs))
        factor_times.append(t_factor)
        one_times.append(t_one)
    t_factor, t_one = min(factor_times), min(one_times)
    entry: dict[str, Any] = {
        "factorize_s": t_factor, "solve_1_s": t_one, "solve_block_s": t_block,
        "block_columns": int(rhs.shape[1]), "solve_per_column_s": t_block / rhs.shape[1],
        "factorize_first_s": factor_times[0], "factorize_all_s": factor_times,
        "solve_1_all_s": one_times,
        "counts": counts.as_dict()}
    # torchfit's linear forward: a direct solve is followed by one refinement solve, an
    # amg solve (already at its tolerance) is not; the backward is one more solve
    forward_solves = 1 if name.startswith("amg") else 2
    entry["forward_s"] = t_factor + forward_solves * t_one
    entry["forward_backward_s"] = entry["forward_s"] + t_one
    entry["jacobian_192_s"] = t_factor + 192 * entry["solve_per_column_s"]
    if iterations_one is not None:
        entry.update(cg_iterations_1=iterations_one, cg_iterations_block=factor.iterations,
                     levels=factor.levels, operator_complexity=factor.operator_complexity)
    if reference is None:
        reference = {"one": x_one, "block": x_block}
    else:
        entry["rel_diff_1"] = float((x_one - reference["one"]).norm() / reference["one"].norm())
        entry["rel_diff_block"] = float((x_block - reference["block"]).norm()
                                        / reference["block"].norm())
    entry["_reference"] = reference
    del factor
    gc.collect()
    return entry


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--boxes", nargs="+", default=["7x7x17", "13x13x40"],
                        help="NXxNYxNZ boxes (6 tetrahedra per cube)")
    parser.add_argument("--columns", type=int, default=8,
                        help="right-hand sides of the block solve")
    parser.add_argument("--translations-max", type=int, default=50_000,
                        help="largest box (tets) also measured with 3 translation modes")
    parser.add_argument("--repeats", type=int, default=3,
                        help="factorisations and single solves timed (minimum; at most 2 "
                             "above 100k tetrahedra)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)

    report: dict[str, Any] = {"machine": machine_info(), "columns": args.columns, "boxes": {}}
    print(f"{'box':>10s} {'tets':>8s} {'dofs':>8s} {'backend':>17s} {'factor':>8s} "
          f"{'solve1':>8s} {'per col':>8s} {'its':>4s} {'fwd':>8s} {'fwd+bwd':>8s} {'jac192':>8s}"
          "  rel diff")
    for box in args.boxes:
        nx, ny, nz = map(int, box.split("x"))
        pattern, values = tet3d(nx, ny, nz, args.seed)
        n_tets = 6 * nx * ny * nz
        rhs = torch.from_numpy(np.random.default_rng(args.seed).standard_normal(
            (pattern.shape[0], args.columns)))
        modes = rigid_modes(nx, ny, nz)
        results: dict[str, Any] = {"tets": n_tets, "free_dofs": pattern.shape[0]}
        reference = None
        names = ["pardiso", "amg"] + (["amg_translations"] if n_tets <= args.translations_max
                                      else [])
        for name in names:
            repeats = args.repeats if n_tets <= 100_000 else min(args.repeats, 2)
            entry = bench_backend(name, pattern, values, modes, rhs, reference, repeats)
            reference = entry.pop("_reference")
            results[name] = entry
            print(f"{box:>10s} {n_tets:8d} {pattern.shape[0]:8d} {name:>17s} "
                  f"{entry['factorize_s']:8.2f} {entry['solve_1_s']:8.3f} "
                  f"{entry['solve_per_column_s']:8.3f} {entry.get('cg_iterations_1', ''):>4} "
                  f"{entry['forward_s']:8.2f} {entry['forward_backward_s']:8.2f} "
                  f"{entry['jacobian_192_s']:8.1f}  "
                  f"{entry.get('rel_diff_1', 0.0):.1e}", flush=True)
        report["boxes"][box] = results
    emit_report(report, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
