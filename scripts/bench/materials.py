#!/usr/bin/env python
"""The small per-element decompositions of the nonlinear materials: LAPACK against the
closed-form / fixed-iteration versions torchfit uses (issue 14, item 2). A measurement.

Each row times one kernel on ``--n`` elements (float64; random ``F = I + 0.3 X``, a
tenth of them inverted; the neo-Hookean rows compressed to ``0.6 I + 0.3 X`` so that
many element Hessians are indefinite) as it was (``lapack``) and as it is (``now``):

* ``svd2``: the rotation-variant 2x2 SVD (``torch.linalg.svd`` plus determinant sign
  fixes) against the closed form :func:`~torchfit.physics.elasticity.kinematics.svd2`;
* ``neo_hookean_projected_{2,3}d``: the PSD-projected ``dP/dF`` of stable neo-Hookean,
  exact ``A`` + batched Cholesky test + ``torch.linalg.eigh`` of the indefinite ones
  (:func:`~torchfit.physics.elasticity.material_base.project_psd`) against the analytic
  eigensystem (``StableNeoHookean.stress_derivative(projected=True)``);
* ``polar_solve``: the 3x3 solve of the polar derivative (``torch.linalg.solve``)
  against the adjugate :func:`~torchfit.physics.elasticity.kinematics.solve_sym3`;
* ``det3``: ``torch.linalg.det`` against the triple product;
* ``tet_box_tangent_projected``: the whole projected stable neo-Hookean tangent of a tet
  box (``SimplicialElasticity.tangent_values(projected=True)``), old path (generic
  projection) against the analytic one.

Also the largest difference between the two (they agree to round-off). Prints JSON
(``--out`` writes it too); when CUDA is present (``--device cuda``) the same rows run
there (the LAPACK rows are those that crash or ask for hundreds of GiB at 10^5..10^6
matrices on CUDA: pass ``--skip-lapack`` there).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Callable

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchtools import emit_report, machine_info  # noqa: E402

from torchfit.mesh import box_tetrahedra  # noqa: E402
from torchfit.physics.elasticity import SimplicialElasticity  # noqa: E402
from torchfit.physics.elasticity.kinematics import det3, solve_sym3, svd2  # noqa: E402
from torchfit.physics.elasticity.material_base import lame_parameters, project_psd  # noqa: E402
from torchfit.physics.elasticity.stable_neo_hookean import StableNeoHookean  # noqa: E402


def lapack_svd2(F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The 2-D rotation-variant SVD as it was: LAPACK and determinant sign fixes."""
    U, sigma, Vh = torch.linalg.svd(F)
    sign_u = torch.sign(torch.linalg.det(U))
    sign_v = torch.sign(torch.linalg.det(Vh))
    U = torch.cat([U[..., :-1], U[..., -1:] * sign_u[..., None, None]], dim=-1)
    Vh = torch.cat([Vh[..., :-1, :], Vh[..., -1:, :] * sign_v[..., None, None]], dim=-2)
    sigma = torch.cat([sigma[..., :-1], sigma[..., -1:] * (sign_u * sign_v)[..., None]], dim=-1)
    return U, sigma, Vh


def _timed(fn: Callable[[], Any], device: torch.device) -> tuple[float, Any]:
    if device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    out = fn()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - start, out


def row(name: str, n: int, lapack: Callable[[], Any] | None, now: Callable[[], Any],
        difference: Callable[[Any, Any], float] | None, repeats: int,
        device: torch.device) -> dict[str, Any]:
    """One kernel, old and new interleaved (a warm-up each, then ``repeats`` alternating
    calls), so that a machine shared with other jobs slows both alike; the minimum is the
    figure to compare, the median is reported beside it."""
    result: dict[str, Any] = {"kernel": name, "n": n}
    kernels = {"now": now} if lapack is None else {"lapack": lapack, "now": now}
    times: dict[str, list[float]] = {key: [] for key in kernels}
    outputs: dict[str, Any] = {}
    for key, fn in kernels.items():
        outputs[key] = fn()
    for _ in range(repeats):
        for key, fn in kernels.items():
            elapsed, outputs[key] = _timed(fn, device)
            times[key].append(elapsed)
    for key, values in times.items():
        result[f"{key}_min_s"] = min(values)
        result[f"{key}_median_s"] = statistics.median(values)
    if lapack is not None:
        result["speedup_min"] = result["lapack_min_s"] / result["now_min_s"]
        if difference is not None:
            result["max_abs_difference"] = difference(outputs["lapack"], outputs["now"])
    print(f"{name:28s} n={n:>8d}  " + (f"lapack {result['lapack_min_s']:.4f} s  "
                                      if lapack is not None else "")
          + f"now {result['now_min_s']:.4f} s", file=sys.stderr)
    return result


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n", type=int, default=100_000, help="elements per kernel")
    parser.add_argument("--box", type=int, nargs=3, default=[12, 12, 12],
                        help="tet box cells (6 tets each) for the whole-tangent row")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--skip-lapack", action="store_true",
                        help="time only the new kernels (LAPACK rows crash on CUDA at scale)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    g = torch.Generator().manual_seed(0)
    n = args.n
    dt = torch.float64

    def random_F(d: int, base: float) -> torch.Tensor:
        F = base * torch.eye(d, dtype=dt) + 0.3 * torch.randn(n, d, d, dtype=dt, generator=g)
        F[: n // 10, :, 0] *= -1
        return F.to(device)

    def max_diff(a: Any, b: Any) -> float:
        return float((a - b).abs().max())

    lapack_ok = not args.skip_lapack
    rows = []
    F2 = random_F(2, 1.0)
    rows.append(row("svd2", n, (lambda: lapack_svd2(F2)) if lapack_ok else None,
                    lambda: svd2(F2),
                    lambda a, b: max_diff(a[0] @ torch.diag_embed(a[1]) @ a[2],
                                          b[0] @ torch.diag_embed(b[1]) @ b[2]),
                    args.repeats, device))
    material = StableNeoHookean()
    for d in (2, 3):
        F = random_F(d, 0.6)
        mu, lam = lame_parameters(torch.rand(n, dtype=dt, generator=g).to(device) + 0.5, 0.3)
        rows.append(row(f"neo_hookean_projected_{d}d", n,
                        (lambda: project_psd(material.stress_derivative(F, mu, lam)))
                        if lapack_ok else None,
                        lambda: material.stress_derivative(F, mu, lam, projected=True),
                        max_diff, args.repeats, device))
    F3 = random_F(3, 1.0)
    K = F3 @ F3.transpose(-1, -2) + 0.1 * torch.eye(3, dtype=dt, device=device)
    rhs = torch.randn(n, 3, dtype=dt, generator=g).to(device)
    rows.append(row("polar_solve", n, (lambda: torch.linalg.solve(K, rhs)) if lapack_ok else None,
                    lambda: solve_sym3(K, rhs), lambda a, b: max_diff(a, b) / float(a.abs().max()),
                    args.repeats, device))
    rows.append(row("det3", n, (lambda: torch.linalg.det(F3)) if lapack_ok else None,
                    lambda: det3(F3), max_diff, args.repeats, device))

    mesh = box_tetrahedra(*args.box, (1.0, 1.0, 1.0))
    model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                 "stable_neo_hookean", nu=0.3, device=device)
    x = (model.rest.points @ (0.6 * torch.eye(3, dtype=dt, device=device)).T).reshape(1, -1)
    x = x + 0.03 * torch.randn(x.shape, dtype=dt, generator=g).to(device)
    E = torch.ones(model.n_cells, dtype=dt, device=device)

    def old_tangent() -> torch.Tensor:
        A = project_psd(model.stress_derivative(x, E))
        grads, volumes = model.rest.grads, model.rest.volumes
        Ke = torch.einsum("...eijkl,eaj,ebl->...eaibk", A, grads, grads)
        Ke = Ke * volumes[:, None, None, None, None]
        return Ke.reshape(Ke.shape[0], -1)

    rows.append(row("tet_box_tangent_projected", model.n_cells,
                    old_tangent if lapack_ok else None,
                    lambda: model.tangent_values(x, E, projected=True), max_diff,
                    args.repeats, device))
    report = {"benchmark": "materials", "device": str(device), "machine": machine_info(),
              "n": n, "rows": rows}
    emit_report(report, args.out)
    return report


if __name__ == "__main__":
    main()
