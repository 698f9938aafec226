#!/usr/bin/env python
"""Which CPU factorisation for torchfit's SPD systems? A measurement.

Matrices (SPD, float64, built with :class:`torchfit.linalg.SparsePattern` exactly as
the physics assemble them, Dirichlet rows/columns dropped with ``submatrix``):

* ``chain1d_n{n}``: the stiffness matrix of the hanging spring chain (tridiagonal,
  ``n`` free nodes, log-uniform stiffness in ``[e^-1, e^1]``), default ``n = 1e5``;
* ``grid2d_N{N}``: a 5-point Laplacian-like matrix with variable coefficients on an
  ``N x N`` grid of unknowns (conductance ``exp(U(-2, 2))`` on every grid edge,
  Dirichlet ring around it, row-major numbering), default ``N = 64, 256, 512``;
* ``tet3d_{nx}x{ny}x{nz}`` (``--tet``, none by default): the linear-elastic stiffness
  (``nu = 0.3``, log-normal Young's modulus per tetrahedron) of ``box_tetrahedra(nx, ny,
  nz)`` with the ``z = 0`` face fixed, as ``SimplicialElasticity`` assembles it
  (``10x10x30``: 10,890 free dofs, ``13x13x46``: 27,048).

Methods: SuperLU through ``scipy.sparse.linalg.splu`` with its default (COLAMD,
partial pivoting), with torchfit's SPD setting (``MMD_AT_PLUS_A``, diagonal pivoting,
``SymmetricMode``), and with the natural ordering; ``spsolve`` (factor + solve every
call); torchfit's ``ScipyBackend`` (the same SuperLU plus its torch/CSR glue);
torchfit's ``LdlBackend`` (qdldl ``L D L^T``, ordering kept per pattern); dense
``scipy.linalg.cho_factor`` and ``torch.linalg.cholesky`` (<= ``--dense-max``
unknowns); LAPACK banded Cholesky (``cholesky_banded``) where the band is small and
the tridiagonal LDL^T (``dpttrf``) for the chain;
torchfit's ``CGBackend`` (Jacobi-PCG in torch, rtol 1e-12, time-capped); torchfit's
``PardisoBackend`` (MKL PARDISO, symmetric indefinite; its timed factorisations reuse the
pattern's analysis, ``analysis_plus_factor`` is the first one with it); and CHOLMOD
(scikit-sparse), PARDISO through pypardiso's own solver (analysis and factorisation
every time) and ``torch.sparse.spsolve`` when they work here.

For each: factorisation time, one solve with 1 and with 2 right-hand sides (median and
minimum over repeats), fill-in ``L.nnz + U.nnz`` (or the factor's stored entries), and
the residual of the solve. Prints JSON (and writes ``--out``).
"""
from __future__ import annotations

import argparse
import gc
import os
import statistics
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Callable

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchtools import emit_report, machine_info  # noqa: E402
from torchfit.linalg import (CGBackend, ScipyBackend, SingularMatrixError, SparsePattern,  # noqa: E402
                             blas_threads, get_backend, pardiso_available, set_threads)

TORCHFIT_CHOICE = "superlu_mmd_at_plus_a_symmetric"


# -- matrices ------------------------------------------------------------------------------
def _reduced(rows: np.ndarray, cols: np.ndarray, contributions: np.ndarray, n_nodes: int,
             keep: np.ndarray) -> tuple[SparsePattern, torch.Tensor]:
    pattern = SparsePattern(rows, cols, (n_nodes, n_nodes))
    values = pattern.assemble(torch.from_numpy(contributions))
    keep_t = torch.from_numpy(keep)
    sub, slots = pattern.submatrix(keep_t, keep_t)
    return sub, values[slots].contiguous()


def _edge_contributions(a: np.ndarray, b: np.ndarray, k: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 2x2 blocks ``k [[1, -1], [-1, 1]]`` of every edge (as the spring model)."""
    rows = np.stack([a, a, b, b], axis=1).reshape(-1)
    cols = np.stack([a, b, a, b], axis=1).reshape(-1)
    vals = np.stack([k, -k, -k, k], axis=1).reshape(-1)
    return rows, cols, vals


def chain1d(n: int, seed: int) -> tuple[SparsePattern, torch.Tensor]:
    """Spring-chain stiffness, ``n`` springs, node 0 fixed: ``n x n`` tridiagonal."""
    rng = np.random.default_rng(seed)
    k = n * np.exp(rng.uniform(-1.0, 1.0, n))  # spring stiffness k_e (rest length 1/n)
    a = np.arange(n)
    rows, cols, vals = _edge_contributions(a, a + 1, k)
    return _reduced(rows, cols, vals, n + 1, np.arange(1, n + 1))


def grid2d(N: int, seed: int) -> tuple[SparsePattern, torch.Tensor]:
    """5-point variable-coefficient operator on ``N x N`` unknowns (Dirichlet ring)."""
    rng = np.random.default_rng(seed)
    M = N + 2
    index = np.arange(M * M).reshape(M, M)
    interior = np.zeros((M, M), dtype=bool)
    interior[1:-1, 1:-1] = True
    pairs = [(index[:-1, :], index[1:, :], interior[:-1, :] | interior[1:, :]),
             (index[:, :-1], index[:, 1:], interior[:, :-1] | interior[:, 1:])]
    a = np.concatenate([p[0][p[2]] for p in pairs])
    b = np.concatenate([p[1][p[2]] for p in pairs])
    k = np.exp(rng.uniform(-2.0, 2.0, a.size))
    rows, cols, vals = _edge_contributions(a, b, k)
    return _reduced(rows, cols, vals, M * M, index[interior].reshape(-1))


def tet3d(nx: int, ny: int, nz: int, seed: int) -> tuple[SparsePattern, torch.Tensor]:
    """Linear-elastic stiffness of a tetrahedral box, the ``z = 0`` face fixed."""
    from torchfit.mesh import box_tetrahedra
    from torchfit.physics.elasticity import SimplicialElasticity

    mesh = box_tetrahedra(nx, ny, nz, (1.0, ny / nx, nz / nx))
    model = SimplicialElasticity(torch.from_numpy(mesh.points), torch.from_numpy(mesh.cells),
                                 "linear", nu=0.3)
    rng = np.random.default_rng(seed)
    E = torch.from_numpy(np.exp(rng.normal(0.0, 0.5, model.n_cells)))
    values = model.tangent_pattern.assemble(
        model.tangent_values(model.rest.points.reshape(1, -1), E))[0]
    fixed = np.nonzero(mesh.points[:, 2] <= 1e-12)[0]
    is_free = np.ones(model.n_dofs, dtype=bool)
    is_free[(fixed[:, None] * 3 + np.arange(3)).reshape(-1)] = False
    keep = torch.from_numpy(np.nonzero(is_free)[0])
    sub, slots = model.tangent_pattern.submatrix(keep, keep)
    return sub, values[slots].contiguous()


# -- measurement helpers ---------------------------------------------------------------------
def measure(fn: Callable[[], Any], repeats: int, slow_s: float = 1.0) -> tuple[dict[str, Any], Any]:
    """Median/min of up to ``repeats`` runs (a single run if the first takes > slow_s).

    The garbage collector is off while timing (as in ``timeit``); callers collect first.
    """
    times, out = [], None
    gc.disable()  # as timeit does: no collector pauses inside the timed calls
    try:
        for i in range(repeats):
            start = time.perf_counter()
            out = fn()
            times.append(time.perf_counter() - start)
            if i == 0 and times[0] > slow_s:
                break
    finally:
        gc.enable()
    return {"median_s": statistics.median(times), "min_s": min(times),
            "repeats": len(times)}, out


def residuals(A: sp.csr_matrix, x: np.ndarray, b: np.ndarray) -> dict[str, float]:
    r = A @ x - b
    norm_a = spla.norm(A, np.inf)
    return {"rel_residual": float(np.linalg.norm(r) / np.linalg.norm(b)),
            "backward_error": float(np.abs(r).max()
                                    / (norm_a * np.abs(x).max() + np.abs(b).max()))}


def envelope(A: sp.csr_matrix) -> tuple[int, int]:
    """(half-bandwidth, envelope size) of a symmetric matrix in its given ordering."""
    A = A.tocsr()
    rows = np.repeat(np.arange(A.shape[0]), np.diff(A.indptr))
    lower = A.indices <= rows
    first = np.full(A.shape[0], A.shape[0], dtype=np.int64)
    np.minimum.at(first, rows[lower], A.indices[lower])
    widths = np.arange(A.shape[0]) - np.minimum(first, np.arange(A.shape[0]))
    return int(widths.max()), int(widths.sum())


def direct_method(factorize: Callable[[], Any], solve: Callable[[Any, np.ndarray], np.ndarray],
                  fill: Callable[[Any], int] | None, A: sp.csr_matrix, b2: np.ndarray,
                  repeats: int) -> dict[str, Any]:
    fact, factor = measure(factorize, repeats)
    out: dict[str, Any] = {"factor": fact}
    for c in (1, 2):
        rhs = np.ascontiguousarray(b2[:, 0] if c == 1 else b2)
        timing, x = measure(lambda: solve(factor, rhs), max(repeats, 5))
        out[f"solve_{c}rhs"] = timing
    out.update(residuals(A, np.asarray(x), b2))
    if fill is not None:
        out["fill_nnz"] = int(fill(factor))
    return out


# -- the methods ------------------------------------------------------------------------------
SUPERLU_SETTINGS: dict[str, dict[str, Any]] = {
    "superlu_colamd_default": {},
    TORCHFIT_CHOICE: {"permc_spec": "MMD_AT_PLUS_A", "diag_pivot_thresh": 0.0,
                      "options": {"SymmetricMode": True}},
    "superlu_natural": {"permc_spec": "NATURAL"},
}


def bench_matrix(name: str, pattern: SparsePattern, values: torch.Tensor, args: argparse.Namespace
                 ) -> dict[str, Any]:
    A = pattern.to_scipy(values)
    Acsc = A.tocsc()
    n = A.shape[0]
    rng = np.random.default_rng(args.seed)
    b2 = rng.standard_normal((n, 2))
    bandwidth, env = envelope(A)
    res: dict[str, Any] = {"n": n, "nnz": int(A.nnz), "half_bandwidth": bandwidth,
                           "envelope": env, "methods": {}}
    methods = res["methods"]
    print(f"[{name}] n={n} nnz={A.nnz}", file=sys.stderr, flush=True)

    def run(label: str, fn: Callable[[], dict[str, Any]]) -> None:
        gc.collect()  # once per method (a full collection takes ~0.1 s with torch loaded)
        start = time.perf_counter()
        try:
            methods[label] = fn()
        except Exception as err:  # report, do not abort the whole benchmark
            methods[label] = {"error": f"{type(err).__name__}: {err}"}
        print(f"  {label}: {time.perf_counter() - start:.2f}s", file=sys.stderr, flush=True)

    # SuperLU variants (raw scipy, CSC input as splu wants).
    for label, kwargs in SUPERLU_SETTINGS.items():
        if label == "superlu_natural" and env > args.natural_max_envelope:
            methods[label] = {"skipped": f"envelope {env} > --natural-max-envelope "
                                         f"{args.natural_max_envelope} (fill ~ 2x envelope)"}
            continue
        run(label, lambda kw=kwargs: direct_method(
            lambda: spla.splu(Acsc, **kw), lambda lu, r: lu.solve(r),
            lambda lu: lu.L.nnz + lu.U.nnz, A, b2, args.repeats)
            | {"kwargs": {k: v for k, v in kw.items()}})

    # torchfit's ScipyBackend: the same SuperLU plus torch -> CSR -> CSC glue.
    backend = ScipyBackend()
    run("torchfit_ScipyBackend", lambda: direct_method(
        lambda: backend.factorize(pattern, values, True),
        lambda f, r: f.solve(torch.from_numpy(r)).numpy(),
        lambda f: f._lu.L.nnz + f._lu.U.nnz, A, b2, args.repeats))

    # torchfit's LdlBackend (qdldl): ordering once per pattern, then numeric L D L^T.
    run("torchfit_LdlBackend", lambda: torchfit_ldl_entry(pattern, values, A, b2, args))

    # spsolve: ordering + factorisation + solve every call (no reuse).
    def spsolve_entry() -> dict[str, Any]:
        out: dict[str, Any] = {"note": "factorises on every call (COLAMD SuperLU; UMFPACK "
                                       "is not installed)"}
        x = None
        for c in (1, 2):
            rhs = b2[:, 0] if c == 1 else b2
            out[f"factor_and_solve_{c}rhs"], x = measure(lambda: spla.spsolve(Acsc, rhs),
                                                         args.repeats)
        out.update(residuals(A, np.asarray(x), b2))
        return out

    run("scipy_spsolve", spsolve_entry)

    # Dense Cholesky (LAPACK potrf) for small systems.
    if n <= args.dense_max:
        dense = A.toarray()
        run("dense_scipy_cho_factor", lambda: direct_method(
            lambda: sla.cho_factor(dense, lower=True, check_finite=False),
            lambda f, r: sla.cho_solve(f, r, check_finite=False),
            lambda f: n * (n + 1) // 2, A, b2, args.repeats))
        dense_t = torch.from_numpy(dense)
        run("dense_torch_cholesky", lambda: direct_method(
            lambda: torch.linalg.cholesky(dense_t),
            lambda L, r: torch.cholesky_solve(torch.from_numpy(r).reshape(n, -1), L)
            .reshape(r.shape).numpy(),
            lambda L: n * (n + 1) // 2, A, b2, args.repeats))
    else:
        for label in ("dense_scipy_cho_factor", "dense_torch_cholesky"):
            methods[label] = {"skipped": f"n={n} > --dense-max {args.dense_max}"}

    # Banded Cholesky (LAPACK pbtrf) in the given ordering: exact fit for the chain.
    if bandwidth * n <= args.banded_max_entries:
        def banded_factor() -> np.ndarray:
            ab = np.zeros((bandwidth + 1, n))
            Ad = A.todia()
            for offset, data in zip(Ad.offsets, Ad.data):
                if offset >= 0:  # upper storage: ab[bw - d, j] = A[j - d, j]
                    ab[bandwidth - offset, offset:] = data[offset:]
            return sla.cholesky_banded(ab, lower=False, check_finite=False)

        run("lapack_cholesky_banded", lambda: direct_method(
            banded_factor, lambda c, r: sla.cho_solve_banded((c, False), r, check_finite=False),
            lambda c: (bandwidth + 1) * n, A, b2, args.repeats)
            | {"note": "band storage built from CSR inside the timed factorisation"})
    else:
        methods["lapack_cholesky_banded"] = {
            "skipped": f"band storage {bandwidth} x {n} > --banded-max-entries"}

    # LAPACK tridiagonal LDL^T (pttrf/pttrs): the best possible for the chain.
    if bandwidth == 1:
        diag = A.diagonal()
        off = A.diagonal(1)

        def pt_factor() -> tuple[np.ndarray, np.ndarray]:
            d, e, info = sla.lapack.dpttrf(diag, off)
            if info != 0:
                raise SingularMatrixError(f"dpttrf info={info}")
            return d, e

        def pt_solve(f: tuple[np.ndarray, np.ndarray], r: np.ndarray) -> np.ndarray:
            x, info = sla.lapack.dpttrs(f[0], f[1], r)
            return x

        run("lapack_pttrf_tridiagonal", lambda: direct_method(
            pt_factor, pt_solve, lambda f: 2 * n - 1, A, b2, args.repeats)
            | {"note": "only for tridiagonal SPD matrices (the 1-D chain)"})

    # torchfit's CGBackend: Jacobi-PCG in torch, capped in wall time.
    run("torchfit_CGBackend", lambda: cg_entry(pattern, values, A, b2, args))

    # torchfit's PardisoBackend: the analysis once per pattern, then numeric factorisations.
    run("torchfit_PardisoBackend", lambda: torchfit_pardiso_entry(pattern, values, A, b2, args))

    # Optional solvers (not installed here: no wheels for this platform / Python).
    run("cholmod_scikit_sparse", lambda: cholmod_entry(Acsc, A, b2, args))
    run("pypardiso", lambda: pardiso_entry(A, b2, args))
    run("torch_sparse_spsolve", lambda: torch_spsolve_entry(pattern, values, A, b2))

    summarize(res)
    return res


def cg_entry(pattern: SparsePattern, values: torch.Tensor, A: sp.csr_matrix, b2: np.ndarray,
             args: argparse.Namespace) -> dict[str, Any]:
    n = A.shape[0]
    iterations = [0]
    matvec = pattern.matvec

    def counted_matvec(*a: Any) -> torch.Tensor:
        iterations[0] += 1
        return matvec(*a)

    # Estimate the cost of one iteration, then cap the iterations to the time budget.
    probe_factor = CGBackend(max_iter=50).factorize(pattern, values, True)
    start = time.perf_counter()
    try:
        probe_factor.solve(torch.from_numpy(b2[:, 0].copy()))
    except SingularMatrixError:
        pass
    per_iter = (time.perf_counter() - start) / 50
    cap = int(max(100, min(10 * n, args.cg_budget_s / per_iter)))
    backend = CGBackend(max_iter=cap)
    out: dict[str, Any] = {"rtol": backend.rtol, "max_iter": cap,
                           "default_max_iter": max(100, 10 * n),
                           "est_ms_per_iteration_1rhs": 1e3 * per_iter}
    fact, factor = measure(lambda: backend.factorize(pattern, values, True), args.repeats)
    out["factor"] = fact
    out["factor_note"] = "O(nnz): keeps the matrix and the inverse diagonal"
    pattern.matvec = counted_matvec  # type: ignore[method-assign]  # count iterations
    try:
        x = None
        for c in (1, 2):
            first = out.get("solve_1rhs", {}).get("median_s", 0.0)
            if c == 2 and first > args.cg_budget_s / 2:
                out["solve_2rhs"] = {"skipped": f"the 1-rhs solve took {first:.1f} s "
                                                f"(> half of --cg-budget-s)"}
                break
            rhs = torch.from_numpy(np.ascontiguousarray(b2[:, 0] if c == 1 else b2))
            iterations[0] = 0
            start = time.perf_counter()
            try:
                x = factor.solve(rhs).numpy()
            except SingularMatrixError as err:
                out[f"solve_{c}rhs"] = {"converged": False, "iterations": iterations[0],
                                         "seconds": time.perf_counter() - start,
                                         "error": str(err)}
                break
            out[f"solve_{c}rhs"] = {"median_s": time.perf_counter() - start, "repeats": 1,
                                    "iterations": iterations[0], "converged": True}
        if x is not None and x.ndim == 2:
            out.update(residuals(A, x, b2))
    finally:
        del pattern.matvec
    return out


def cholmod_entry(Acsc: sp.csc_matrix, A: sp.csr_matrix, b2: np.ndarray,
                  args: argparse.Namespace) -> dict[str, Any]:
    try:
        from sksparse.cholmod import cholesky  # type: ignore[import-not-found]
    except ImportError as err:
        return {"unavailable": f"scikit-sparse (CHOLMOD) not importable ({err}): not "
                               "installed, it builds against a system SuiteSparse"}
    return direct_method(lambda: cholesky(Acsc), lambda f, r: f(r),
                         lambda f: f.L().nnz, A, b2, args.repeats)


def pardiso_entry(A: sp.csr_matrix, b2: np.ndarray, args: argparse.Namespace) -> dict[str, Any]:
    try:
        import pypardiso  # type: ignore[import-not-found]
    except ImportError as err:
        return {"unavailable": f"pypardiso (MKL PARDISO) not importable ({err}): not "
                               "installed in this environment"}
    solver = pypardiso.PyPardisoSolver(mtype=2)  # real SPD
    # Symmetric PARDISO types read the upper triangle only and need it alone: the full
    # matrix is invalid input there (MKL crashed on it).
    upper = sp.triu(A, format="csr")
    upper.sort_indices()

    def factor() -> Any:
        solver.factorize(upper)
        return solver

    out = direct_method(factor, lambda s, r: s.solve(upper, r), None, A, b2, args.repeats)
    out["note"] = ("pypardiso's own solver: analysis and factorisation (phase 12) every "
                   "time, MKL's default iparm, SPD (mtype 2), upper triangle")
    return out


def torchfit_pardiso_entry(pattern: SparsePattern, values: torch.Tensor, A: sp.csr_matrix,
                           b2: np.ndarray, args: argparse.Namespace) -> dict[str, Any]:
    if not pardiso_available():
        return {"unavailable": "MKL PARDISO not installed here (pip install 'torchfit[pardiso]')"}
    backend = get_backend("pardiso")
    fresh = SparsePattern(pattern.row_indices, pattern.col_indices, pattern.shape)
    first, factor = measure(lambda: backend.factorize(fresh, values, True), 1)
    out = direct_method(lambda: backend.factorize(pattern, values, True),
                        lambda f, r: f.solve(torch.from_numpy(r)).numpy(),
                        lambda f: f.report["factor_nnz"], A, b2, args.repeats)
    out["analysis_plus_factor"] = first
    out["analyses"] = backend.plan(pattern, True).analyses
    out["note"] = ("symmetric indefinite (mtype -2); 'factor' reuses the pattern's analysis, "
                   "'analysis_plus_factor' is a first factorisation of a new pattern")
    return out


def torchfit_ldl_entry(pattern: SparsePattern, values: torch.Tensor, A: sp.csr_matrix,
                       b2: np.ndarray, args: argparse.Namespace) -> dict[str, Any]:
    backend = get_backend("ldl")
    fresh = SparsePattern(pattern.row_indices, pattern.col_indices, pattern.shape)
    first, _ = measure(lambda: backend.factorize(fresh, values, True), 1)
    out = direct_method(lambda: backend.factorize(pattern, values, True),
                        lambda f, r: f.solve(torch.from_numpy(r)).numpy(),
                        lambda f: f._solver.factors()[0].nnz + A.shape[0], A, b2, args.repeats)
    out["analysis_plus_factor"] = first
    out["analyses"] = backend.plan(pattern).analyses
    out["fallbacks"] = backend.fallbacks
    out["note"] = ("qdldl L D L^T (AMD ordering, no pivoting, SPD); 'factor' reuses the "
                   "pattern's ordering (numeric update), 'analysis_plus_factor' is a first "
                   "factorisation of a new pattern; solves column by column")
    return out


def torch_spsolve_entry(pattern: SparsePattern, values: torch.Tensor, A: sp.csr_matrix,
                        b2: np.ndarray) -> dict[str, Any]:
    if not hasattr(torch.sparse, "spsolve"):
        return {"unavailable": "torch.sparse.spsolve does not exist in this torch"}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
            matrix = pattern.to_torch(values)
        x = torch.sparse.spsolve(matrix, torch.from_numpy(b2[:, 0].copy()))
    except Exception as err:
        return {"unavailable": f"{type(err).__name__}: {str(err).splitlines()[0][:200]}"}
    return {"works": True, **residuals(A, x.numpy(), b2[:, 0])}


def summarize(res: dict[str, Any]) -> None:
    """Rank the methods by factorisation + k solves (k = 1 and k = 10 ~ one GN step)."""
    table = {}
    for label, m in res["methods"].items():
        if "factor" not in m or "solve_1rhs" not in m or "median_s" not in m["solve_1rhs"]:
            continue
        f, s = m["factor"]["median_s"], m["solve_1rhs"]["median_s"]
        table[label] = {"factor_s": f, "solve_s": s, "factor_plus_1_solve_s": f + s,
                        "factor_plus_10_solves_s": f + 10 * s}
    res["summary"] = table
    # Rank distinct algorithms: the ScipyBackend row is the torchfit choice plus glue.
    direct = {k: v for k, v in table.items()
              if k not in ("torchfit_CGBackend", "torchfit_ScipyBackend")}
    if TORCHFIT_CHOICE in table and "torchfit_ScipyBackend" in table:
        res["torchfit_glue_overhead_factor_s"] = (
            table["torchfit_ScipyBackend"]["factor_s"] - table[TORCHFIT_CHOICE]["factor_s"])
    if not direct:
        return
    for key in ("factor_s", "factor_plus_1_solve_s", "factor_plus_10_solves_s"):
        best = min(direct, key=lambda k: direct[k][key])
        entry = {"fastest": best, "seconds": direct[best][key]}
        if TORCHFIT_CHOICE in direct:
            entry["torchfit_choice_over_fastest"] = direct[TORCHFIT_CHOICE][key] / direct[best][key]
        sparse_general = {k: v for k, v in direct.items()
                          if k.startswith("superlu") or k.startswith("cholmod")
                          or k.startswith("pypardiso")}
        if sparse_general:
            best_sparse = min(sparse_general, key=lambda k: sparse_general[k][key])
            entry["fastest_general_sparse"] = best_sparse
            if TORCHFIT_CHOICE in direct:
                entry["torchfit_choice_over_fastest_general_sparse"] = \
                    direct[TORCHFIT_CHOICE][key] / sparse_general[best_sparse][key]
            if "superlu_colamd_default" in direct:
                entry["colamd_default_over_torchfit_choice"] = \
                    direct["superlu_colamd_default"][key] / direct[TORCHFIT_CHOICE][key]
        res[f"best_by_{key}"] = entry




def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--chain-n", type=int, nargs="*", default=[100_000],
                        help="sizes of the 1-D chain (free nodes)")
    parser.add_argument("--grid-N", type=int, nargs="*", default=[64, 256, 512],
                        help="2-D grid sides N (N^2 unknowns)")
    parser.add_argument("--tet", nargs="*", default=[],
                        help="tetrahedral boxes NXxNYxNZ (e.g. 10x10x30 13x13x46)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--dense-max", type=int, default=5000,
                        help="largest n for the dense Cholesky")
    parser.add_argument("--banded-max-entries", type=int, default=20_000_000)
    parser.add_argument("--natural-max-envelope", type=int, default=20_000_000,
                        help="skip natural-order SuperLU when the envelope is larger")
    parser.add_argument("--cg-budget-s", type=float, default=20.0,
                        help="cap CG iterations so one solve takes about this long")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--quick", action="store_true", help="tiny matrices (smoke test)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.quick:
        args.chain_n, args.grid_N, args.repeats, args.cg_budget_s = [1000], [16], 2, 2.0
        args.tet = ["2x2x4"]
    if args.threads:
        set_threads(args.threads)
    report: dict[str, Any] = {"benchmark": "factorization", "machine": machine_info(),
                              "settings": {k: (str(v) if isinstance(v, Path) else v)
                                           for k, v in vars(args).items()},
                              "torchfit_choice": TORCHFIT_CHOICE, "matrices": {}}
    cases = [(f"chain1d_n{n}", lambda n=n: chain1d(n, args.seed)) for n in args.chain_n]
    cases += [(f"grid2d_N{N}", lambda N=N: grid2d(N, args.seed)) for N in args.grid_N]
    cases += [(f"tet3d_{box}", lambda box=box: tet3d(*map(int, box.split("x")), args.seed))
              for box in args.tet]
    for name, build in cases:
        start = time.perf_counter()
        pattern, values = build()
        build_s = time.perf_counter() - start
        report["matrices"][name] = {"build_s": build_s,
                                    **bench_matrix(name, pattern, values, args)}
        gc.collect()
    report["machine"]["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    report["machine"]["blas_threads"] = blas_threads()
    emit_report(report, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
