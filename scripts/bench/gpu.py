#!/usr/bin/env python
"""The same problems on the CPU and (where present) CUDA: set-up phase by phase, forward,
backward, one Gauss-Newton step, counted analyses, factorisations and solves, peak memory
(issues 14 and 39). JSON.

Rows (``--devices``, default ``cpu`` plus ``cuda`` when torch sees a GPU; backend
``auto`` unless ``--backend``: pardiso/scipy on the CPU, cudss on CUDA where installed,
else cg):

* ``device_init``, once per device, before any other row (so that the rows below do not
  carry one-off costs): ``cuda_init_s`` (the CUDA context), ``autograd_thread_s`` (the
  first backward on the device: autograd starts its device thread; before it
  ``autograd_warm_up_s``, torch's lazy imports that ``torchfit.fit`` pays in its set-up), and
  with cuDSS
  ``cudss_first_s`` (a tiny system factorised and solved: the library's first call) and
  ``cudss_new_thread_s`` (the same again on a new Python thread: what a thread's first
  call into nvmath costs, e.g. autograd's).

* ``tetbox``, for every ``n`` of ``--tet-sizes`` (a box of ``n x n x n`` cubes, 6
  tetrahedra each, :func:`torchfit.mesh.box_tetrahedra`, bottom face fixed, top face
  pulled; ``--material``, default ``linear``; ``--frames`` frames):

  - ``setup``: the mesh (host), the model (rest shape + CSR pattern, built on the device)
    and the equilibrium (Dirichlet sub-pattern and its slots), each timed; the model's
    parts measured again one by one (``rest_shape_s``, ``pattern_s``);
    ``pattern_host_numpy_s`` (``--compare-host-pattern``): the pattern as built before
    issue 14 (``np.unique`` on the host), up to ``--host-pattern-max`` tetrahedra;
  - ``forward`` (from a cleared cache: the analysis, the factorisations, the solves),
    ``backward`` (the gradient w.r.t. the per-tet modulus: the first of the row) and
    ``backward_again`` (the same product again), ``forward_again`` (at a modulus 10 %
    stiffer: factorisations and solves with the analysis kept) and its ``backward``, with
    their counts, unless ``--setup-only``;
  - ``rhs_blocks`` (``--rhs-blocks``, cudss only): seconds of one solve of ``--rhs-columns``
    columns with the factor of the forward, per right-hand-side block width.

* ``batched_factorization`` (``--batch-factorization B``, cudss only, on the first box):
  nvmath's explicit batch of ``B`` matrices of one pattern against one matrix at a time
  (:func:`batched_factorization_row`).

* ``poisson2d``, for every ``N`` of ``--poisson-sizes``: build, forward, backward, one
  Gauss-Newton step from ``theta0`` (evaluated first, as in a running fit), counts.

Memory: ``peak_rss_mb`` (the process's high-water mark so far, from ``resource``) on the
CPU; ``torch.cuda.max_memory_allocated`` per row on CUDA. Timings are wall clock after
``torch.cuda.synchronize`` on CUDA; on a shared CPU use ``--threads 1``.

Examples::

    .venv/bin/python scripts/bench/gpu.py --tet-sizes 10 20 40 --setup-only --threads 1
    .venv/bin/python scripts/bench/gpu.py --devices cuda --tet-sizes 80 --poisson-sizes 256
    .venv/bin/python scripts/bench/gpu.py --devices cuda --tet-sizes 55 \
        --material stable_neo_hookean --frames 4
"""
from __future__ import annotations

import argparse
import gc
import resource
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from torch import Tensor

ROOT = Path(__file__).resolve().parents[2]
try:        # a torchfit on PYTHONPATH (another checkout: before/after figures) is used as is
    import torchfit  # noqa: F401
except ImportError:
    sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchtools import emit_report, loadavg, machine_info  # noqa: E402
from torchfit.linalg import counting  # noqa: E402
from torchfit.linalg.backends.choice import default_backend  # noqa: E402
from torchfit.mesh import box_tetrahedra  # noqa: E402
from torchfit.physics import NewtonOptions  # noqa: E402
from torchfit.physics.elasticity import QuasistaticElasticity, SimplicialElasticity  # noqa: E402


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn: Callable[[], Any], device: torch.device) -> tuple[float, Any, dict[str, int]]:
    """(seconds, result, counter delta) of one call, synchronised on CUDA."""
    sync(device)
    with counting() as delta:
        start = time.perf_counter()
        out = fn()
        sync(device)
        seconds = time.perf_counter() - start
        counts = delta.as_dict()
    return seconds, out, counts


def peak_memory(device: torch.device) -> dict[str, float]:
    out = {"peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}
    if device.type == "cuda":
        out["cuda_max_allocated_mb"] = torch.cuda.max_memory_allocated(device) / 2 ** 20
    return out


def reset_peak(device: torch.device) -> None:
    gc.collect()
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)


def host_pattern_seconds(cells: np.ndarray, n_vertices: int, d: int = 3) -> float:
    """The pattern as it was built before issue 14: np.unique of every contribution."""
    start = time.perf_counter()
    dofs = (cells[:, :, None] * d + np.arange(d)).reshape(len(cells), -1)
    k = dofs.shape[1]
    rows = np.broadcast_to(dofs[:, :, None], (len(cells), k, k)).reshape(-1)
    cols = np.broadcast_to(dofs[:, None, :], (len(cells), k, k)).reshape(-1)
    n = n_vertices * d
    unique_keys, scatter = np.unique(rows * n + cols, return_inverse=True)
    crow = np.zeros(n + 1, dtype=np.int64)
    np.add.at(crow, unique_keys // n + 1, 1)
    np.cumsum(crow, out=crow)
    del scatter
    return time.perf_counter() - start


def device_init_row(device: torch.device, backend: str) -> dict[str, Any]:
    """One-off costs of a process on ``device`` (module docstring), before the rows."""
    import threading

    row: dict[str, Any] = {"problem": "device_init", "device": str(device)}
    if device.type == "cuda":
        start = time.perf_counter()
        torch.cuda.init()
        torch.zeros(1, device=device)
        sync(device)
        row["cuda_init_s"] = time.perf_counter() - start
    from torchfit.residual import warm_up_autograd

    # torch's lazy imports (sympy, at the first vector-Jacobian product: ~1 s), as fit() pays
    # them in its set-up; then the device's first backward (autograd's device thread)
    row["autograd_warm_up_s"], _, _ = timed(warm_up_autograd, device)
    leaf = torch.ones(8, dtype=torch.float64, device=device, requires_grad=True)
    row["autograd_thread_s"], _, _ = timed(lambda: torch.autograd.grad(
        leaf * leaf, leaf, torch.ones_like(leaf)), device)
    name = backend if backend != "auto" else default_backend(3, device)
    if name == "cudss":
        from torchfit.linalg import get_backend

        pattern, values = stiffness_at_rest(2, device)
        rhs = torch.ones(pattern.shape[0], dtype=torch.float64, device=device)

        def solve_once() -> None:
            get_backend("cudss").factorize(pattern, values, True).solve(rhs)

        def on_new_thread(key: str) -> None:
            try:
                row[key] = timed(solve_once, device)[0]
            except Exception as err:  # noqa: BLE001 - the report says what failed
                row[key] = None
                row[key.replace("_s", "_error")] = f"{type(err).__name__}: {err}".splitlines()[0]

        for key in ("cudss_first_s", "cudss_new_thread_s"):
            thread = threading.Thread(target=on_new_thread, args=(key,))
            thread.start()
            thread.join()
    return row


def tetbox_row(n: int, device: torch.device, backend: str, material: str, frames: int,
               setup_only: bool, compare_host: bool, host_max: int,
               rhs_blocks: list[int], rhs_columns: int) -> dict[str, Any]:
    from torchfit.linalg import SparsePattern
    from torchfit.physics.elasticity.kinematics import RestShape

    reset_peak(device)
    row: dict[str, Any] = {"problem": "tetbox", "n": n, "device": str(device),
                           "material": material}
    t_mesh, mesh, _ = timed(lambda: box_tetrahedra(n, n, n, (1.0, 1.0, 1.0)), device)
    cells = torch.from_numpy(mesh.cells)
    points = torch.from_numpy(mesh.points)
    t_model, model, _ = timed(lambda: SimplicialElasticity(
        points, cells, material, nu=0.3, device=device), device)
    # the model's parts again, one by one (where the model phase goes)
    t_rest, rest, _ = timed(lambda: RestShape(points, cells, device=device), device)
    t_pattern, _, _ = timed(lambda: SparsePattern.from_dense_blocks(rest.cells, 3,
                                                                    rest.n_vertices), device)
    rest = None                     # the copy's device memory
    X = model.rest.points
    bottom = torch.nonzero(X[:, 2] <= 1e-12).reshape(-1).cpu()
    top = torch.nonzero(X[:, 2] >= 1.0 - 1e-12).reshape(-1).cpu()
    backend_name = backend if backend != "auto" else default_backend(3, device)
    t_eq, qs, _ = timed(lambda: QuasistaticElasticity(
        model, torch.cat([bottom, top]), backend=backend_name,
        newton=NewtonOptions(rtol=1e-10, atol=1e-12)), device)
    row.update(tets=model.n_cells, vertices=model.n_vertices,
               free_dofs=int(qs.equilibrium.free_dofs.numel()),
               nnz_free=qs.equilibrium.free_pattern.nnz, backend=backend_name,
               setup={"mesh_s": t_mesh, "model_s": t_model, "equilibrium_s": t_eq,
                      "total_s": t_mesh + t_model + t_eq, "rest_shape_s": t_rest,
                      "pattern_s": t_pattern})
    if compare_host and model.n_cells <= host_max:
        row["setup"]["pattern_host_numpy_s"] = host_pattern_seconds(mesh.cells,
                                                                    model.n_vertices)
    if not setup_only:
        shifts = torch.zeros(frames, 3, dtype=X.dtype, device=device)
        shifts[:, 2] = -0.05 * (1 + torch.arange(frames, dtype=X.dtype, device=device)) / frames
        shifts[:, 0] = 0.02
        positions = [torch.cat([X[bottom.to(device)], X[top.to(device)] + s]) for s in shifts]
        g = None
        for key, spread in (("forward", 0.0), ("forward_again", 0.1)):
            # the next point of a fit: another field (a uniform scale would not move x)
            E = torch.exp(spread * torch.randn(model.n_cells, dtype=X.dtype, generator=torch.
                                               Generator().manual_seed(2))).to(device)
            E.requires_grad_(True)
            if key == "forward":
                qs.clear_cache()
            t_f, x, c_f = timed(lambda: qs(E, positions), device)
            if g is None:
                g = torch.randn(x.shape, dtype=x.dtype,
                                generator=torch.Generator().manual_seed(0)).to(device)
            t_b, (grad,), c_b = timed(lambda: torch.autograd.grad(x, E, g, retain_graph=True),
                                      device)
            assert bool(torch.isfinite(grad).all())
            row[key] = {"seconds": t_f, "counts": c_f, "newton_iterations":
                        list(qs.last_newton_iterations),
                        "backward": {"seconds": t_b, "counts": c_b}}
            if key == "forward":
                t_b2, _, c_b2 = timed(lambda: torch.autograd.grad(x, E, g), device)
                row["backward"] = {"seconds": t_b, "counts": c_b}
                row["backward_again"] = {"seconds": t_b2, "counts": c_b2}
                row["frames"] = frames
                row["newton_iterations"] = qs.last_newton_iterations
                if backend_name == "cudss" and rhs_blocks:
                    row["rhs_blocks"] = rhs_block_seconds(qs, rhs_blocks, rhs_columns, device)
    row["memory"] = peak_memory(device)
    return row


def stiffness_at_rest(n: int, device: torch.device) -> tuple[Any, Tensor]:
    """The free-free linear stiffness of the ``n^3``-cube box at rest (bottom fixed):
    ``(pattern, values)`` on ``device``."""
    mesh = box_tetrahedra(n, n, n, (1.0, 1.0, 1.0))
    model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                 "linear", nu=0.3, device=device)
    free = torch.nonzero(model.rest.points[:, 2] > 1e-12).reshape(-1)
    dofs = (free[:, None] * 3 + torch.arange(3, device=free.device)).reshape(-1)
    pattern, slots = model.tangent_pattern.submatrix(dofs, dofs)
    E = torch.ones(model.n_cells, dtype=torch.float64, device=device)
    values = model.tangent_pattern.assemble(model.tangent_values(
        model.rest.points.reshape(1, -1), E))[0][slots.to(device)]
    return pattern, values


def batched_factorization_row(n: int, device: torch.device, batch: int,
                              runtime: Any = None) -> dict[str, Any]:
    """cuDSS through nvmath's documented batching: ``batch`` matrices of one pattern (the
    box's stiffness scaled per member, one RHS column each) in one ``DirectSolver`` of an
    explicit batch, against one single-matrix ``DirectSolver`` factorising them in turn
    (its values updated in place). Whether cuDSS analyses a batch of one pattern once
    (``plan_batch_s`` near ``plan_single_s``) or once per member decides whether the frames
    of a Newton round can be factorised as one batch without more analyses (issue 39)."""
    from torchfit.linalg.backends.cudss import NvmathRuntime
    from torchfit.linalg.pattern import csr_matrix

    runtime = runtime or NvmathRuntime()
    advanced = runtime.advanced
    pattern, values = stiffness_at_rest(n, device)
    size = pattern.shape
    crow = pattern.crow_indices.to(device=device, dtype=torch.int32)
    col = pattern.col_indices.to(device=device, dtype=torch.int32)
    scales = [1.0 + 0.1 * k for k in range(batch)]
    options = advanced.DirectSolverOptions(sparse_system_type=advanced.DirectSolverMatrixType.SPD)

    def matrix(scale: float) -> Tensor:
        return csr_matrix(crow, col, scale * values, size)

    def column() -> Tensor:
        return torch.ones(1, size[0], dtype=torch.float64, device=device).T

    def call(fn: Callable[[], Any]) -> tuple[float, Any]:
        runtime.make_current(device)
        seconds, out, _ = timed(fn, device)
        return seconds, out

    row: dict[str, Any] = {"problem": "batched_factorization", "n": n, "device": str(device),
                           "free_dofs": size[0], "nnz": pattern.nnz, "batch": batch}
    single_matrix, single_rhs = matrix(1.0), column()
    runtime.make_current(device)
    single = advanced.DirectSolver(single_matrix, single_rhs, options=options)
    row["plan_single_s"], _ = call(single.plan)
    solutions, factorize_s, solve_s = [], 0.0, 0.0
    for scale in scales:
        single_matrix.values().copy_(scale * values)
        seconds, _ = call(single.factorize)
        factorize_s += seconds
        seconds, x = call(single.solve)
        solve_s += seconds
        solutions.append(torch.as_tensor(x).reshape(-1).clone())
    row["factorize_single_each_s"], row["solve_single_each_s"] = factorize_s, solve_s
    runtime.make_current(device)
    single.free()
    runtime.make_current(device)
    batched = advanced.DirectSolver([matrix(s) for s in scales], [column() for _ in scales],
                                    options=options)
    row["plan_batch_s"], _ = call(batched.plan)
    row["factorize_batch_s"], _ = call(batched.factorize)
    row["solve_batch_s"], xs = call(batched.solve)
    row["max_difference"] = max(float((torch.as_tensor(x).reshape(-1) - y).abs().max())
                                for x, y in zip(xs, solutions))
    runtime.make_current(device)
    batched.free()
    return row


def rhs_block_seconds(qs: QuasistaticElasticity, blocks: list[int], columns: int,
                      device: torch.device) -> list[dict[str, Any]]:
    """Seconds of one solve of ``columns`` right-hand sides with the box's tangent at rest,
    factorised by cuDSS with each RHS block width (its first solve, the numeric
    factorisation, timed apart)."""
    from torchfit.linalg.backends.cudss import CudssBackend

    eq = qs.equilibrium
    E = torch.ones(qs.model.n_cells, dtype=torch.float64, device=device)
    values = eq.reduction.free_values(eq.reduction.tangent(qs.model.rest.points.reshape(
        1, -1).to(E), E))[0]
    rhs = torch.randn(eq.free_pattern.shape[0], columns, dtype=torch.float64,
                      generator=torch.Generator().manual_seed(1)).to(device)
    def row(block: int) -> dict[str, Any]:
        factor = CudssBackend(rhs_block=block).factorize(eq.free_pattern, values, True)
        t_first, _, counts = timed(lambda: factor.solve(rhs[:, :1]), device)
        t_solve, _, _ = timed(lambda: factor.solve(rhs), device)
        t_one, _, _ = timed(lambda: factor.solve(rhs[:, :1]), device)
        return {"rhs_block": block, "first_solve_s": t_first, "columns": columns,
                "solve_s": t_solve, "one_column_s": t_one, "counts": counts}

    return [row(block) for block in blocks]      # each factor freed before the next


def poisson_row(N: int, device: torch.device, backend: str) -> dict[str, Any]:
    from torchfit.problems import build_problem
    from torchfit.solvers.gauss_newton import GaussNewtonConfig, gauss_newton

    reset_peak(device)
    settings = {"N": N, "device": str(device), "backend": backend}
    t_build, problem, _ = timed(lambda: build_problem("poisson2d", settings), device)
    residual = problem.residual()
    theta = problem.theta0.detach().clone().requires_grad_(True)
    problem.equilibrium.clear_cache()
    t_f, x, c_f = timed(lambda: problem.simulate(problem.parameterization(theta)), device)
    g = torch.randn(x.shape, dtype=x.dtype, generator=torch.Generator().manual_seed(0)).to(x.device)
    t_b, _, c_b = timed(lambda: torch.autograd.grad(x, theta, g), device)
    problem.equilibrium.clear_cache()
    residual.linearize(problem.theta0)
    t_gn, result, c_gn = timed(lambda: gauss_newton(residual, problem.theta0,
                                                    GaussNewtonConfig(max_iter=1)), device)
    return {"problem": "poisson2d", "N": N, "device": str(device),
            "backend": getattr(problem.equilibrium.backend, "name", backend),
            "n_params": int(problem.theta0.numel()), "build_s": t_build,
            "forward": {"seconds": t_f, "counts": c_f},
            "backward": {"seconds": t_b, "counts": c_b},
            "gn_step": {"seconds": t_gn, "counts": c_gn,
                        "cg_iterations": int(result.history[-1].cg_iterations)},
            "memory": peak_memory(device)}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--devices", nargs="+", default=None)
    parser.add_argument("--backend", default="auto")
    parser.add_argument("--tet-sizes", type=int, nargs="*", default=[8, 16, 24])
    parser.add_argument("--poisson-sizes", type=int, nargs="*", default=[64, 128])
    parser.add_argument("--material", default="linear")
    parser.add_argument("--frames", type=int, default=1)
    parser.add_argument("--setup-only", action="store_true")
    parser.add_argument("--compare-host-pattern", action="store_true")
    parser.add_argument("--host-pattern-max", type=int, default=2_000_000,
                        help="largest tet count for --compare-host-pattern")
    parser.add_argument("--rhs-blocks", type=int, nargs="*", default=[],
                        help="cudss: RHS block widths to time (e.g. 1 8 32 64)")
    parser.add_argument("--rhs-columns", type=int, default=192,
                        help="right-hand sides of the --rhs-blocks solves (the arm: 192)")
    parser.add_argument("--batch-factorization", type=int, default=0,
                        help="cudss: time nvmath's explicit batch of this many matrices "
                             "against one matrix at a time (on the first --tet-sizes box)")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    devices = args.devices or (["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"])
    import torchfit
    report: dict[str, Any] = {"benchmark": "gpu", "machine": machine_info(),
                              "torchfit": str(Path(torchfit.__file__).parent),
                              "loadavg_start": loadavg(), "settings": vars(args) | {
                                  "out": str(args.out) if args.out else None},
                              "rows": []}
    if torch.cuda.is_available():
        report["machine"]["cuda_device"] = torch.cuda.get_device_name(0)
        report["machine"]["torch_cuda"] = torch.version.cuda
    for name in devices:
        device = torch.device(name)
        report["rows"].append(device_init_row(device, args.backend))
        for n in args.tet_sizes:
            row = tetbox_row(n, device, args.backend, args.material, args.frames,
                             args.setup_only, args.compare_host_pattern, args.host_pattern_max,
                             args.rhs_blocks, args.rhs_columns)
            print(f"tetbox n={n} {name}: {row['tets']} tets, {row['free_dofs']} free dofs, "
                  f"set-up {row['setup']['total_s']:.2f} s", file=sys.stderr)
            report["rows"].append(row)
        if args.batch_factorization and args.tet_sizes and row["backend"] == "cudss":
            report["rows"].append(batched_factorization_row(args.tet_sizes[0], device,
                                                            args.batch_factorization))
        if not args.setup_only:
            for N in args.poisson_sizes:
                row = poisson_row(N, device, args.backend)
                print(f"poisson2d N={N} {name}: forward {row['forward']['seconds']:.3f} s, "
                      f"GN step {row['gn_step']['seconds']:.3f} s", file=sys.stderr)
                report["rows"].append(row)
    report["loadavg_end"] = loadavg()
    emit_report(report, args.out)
    return report


if __name__ == "__main__":
    main()
