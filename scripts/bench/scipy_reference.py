#!/usr/bin/env python
"""Independent numpy/scipy reference for the poisson2d fits of issue 13 (no torch).

A plain implementation of the problem definition of "poisson2d" (docs/problems.md), and of the
two solvers the issue compares torchfit against:

* :func:`gauss_newton`: Gauss-Newton on ``theta = log k``, inner CGLS on ``J d = -r``
  (matrix-free, relative normal-equation residual stop), backtracking (Armijo) line
  search on ``||r||``, discrepancy stop on noisy data.
* :func:`split_bregman`: anisotropic TV of ``theta`` by Goldstein-Osher split Bregman,
  one Gauss-Newton step (stacked CGLS, fixed tolerance and cap) per Bregman update.

The forward model and the derivatives are explicit: with the edge-node incidence ``B``
(one row ``e_q - e_p`` per grid edge ``pq``), the edge-cell averaging matrix ``E`` and
edge weights ``w = E k``, the full graph Laplacian is ``L(w) = B^T diag(w) B`` and the
scheme of docs/problems.md is ``(L x)_p = 0`` at every free node ``p``. Splitting the nodes
into free ``f`` and Dirichlet ``d`` ones, ``A = L_ff`` (SPD) and

    A(k) x_f = -L_fd(k) x_d        (two right-hand sides, one per component).

Differentiating ``F(x_f, w) = P_f B^T diag(w) B x = P_f B^T diag(B x) w = 0``:

    dx_f/dw = -A^{-1} P_f B^T diag(B x),        dw/dtheta = E diag(k),

so ``J v = -S A^{-1} P_f B^T (g_c * (E (k * v)))`` per component ``c`` (``g_c = B x_c``,
``S`` the observation) and ``J^T y = -sum_c k * E^T (g_c * (B P_f^T A^{-1} S^T y_c))``.
Each product costs one SuperLU solve with two right-hand sides, using the factor of the
current ``k`` (one ``splu`` per distinct ``theta``).

Gauge: ``x(a k) = x(k)``, so ``J 1 = 0`` and the constant direction is projected out of
every step (``theta0 = 0`` stays mean-free).

Timing: every solver clock starts after :func:`make_case` and includes everything the
solver does (scale estimates, factorisations, solves); the time spent computing the
accuracy metric for the trace is measured and subtracted.

Usage::

    .venv/bin/python scripts/bench/scipy_reference.py --selftest
    .venv/bin/python scripts/bench/scipy_reference.py --case gn_dense
    .venv/bin/python scripts/bench/scipy_reference.py --case sb_dense_noisy
    .venv/bin/python scripts/bench/scipy_reference.py --case sb_sparse
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

SIDE = 0.5


# --------------------------------------------------------------------------------------
# problem


def blocks_truth(N: int, s: float = SIDE) -> np.ndarray:
    """``blocks`` truth: 1, 5 in [0.20,0.45]x[0.20,0.80], 0.25 in [0.60,0.85]x[0.30,0.60]."""
    h = s / (N - 1)
    c = (np.arange(N - 1) + 0.5) * h / s              # normalised cell-centre coordinate
    cx, cy = np.meshgrid(c, c, indexing="ij")          # cell (ci, cj) -> ci*(N-1)+cj
    k = np.ones((N - 1, N - 1))
    k[(cx >= 0.20) & (cx <= 0.45) & (cy >= 0.20) & (cy <= 0.80)] = 5.0
    k[(cx >= 0.60) & (cx <= 0.85) & (cy >= 0.30) & (cy <= 0.60)] = 0.25
    return k.ravel()


def grid_operators(N: int):
    """Incidence ``B`` (edges x nodes), averaging ``E`` (edges x cells), TV difference ``D``.

    Edges: first the x-edges ``(i, j)-(i+1, j)``, then the y-edges ``(i, j)-(i, j+1)``.
    The cells touching an x-edge are ``(i, j-1)`` and ``(i, j)`` where they exist (one on
    the bottom/top rows ``j = 0, N-1``); for a y-edge ``(i-1, j)`` and ``(i, j)``.
    """
    nn, nc = N * N, (N - 1) ** 2
    node = lambda i, j: i * N + j                       # noqa: E731
    cell = lambda i, j: i * (N - 1) + j                 # noqa: E731

    # x-edges
    I, J = np.meshgrid(np.arange(N - 1), np.arange(N), indexing="ij")
    I, J = I.ravel(), J.ravel()
    p_x, q_x = node(I, J), node(I + 1, J)
    # cells of x-edges: (I, J-1) if J>=1, (I, J) if J<=N-2
    ex_rows, ex_cols = [], []
    e_idx = np.arange(I.size)
    m = J >= 1
    ex_rows.append(e_idx[m]); ex_cols.append(cell(I[m], J[m] - 1))
    m = J <= N - 2
    ex_rows.append(e_idx[m]); ex_cols.append(cell(I[m], J[m]))
    nx_edges = I.size

    # y-edges
    I, J = np.meshgrid(np.arange(N), np.arange(N - 1), indexing="ij")
    I, J = I.ravel(), J.ravel()
    p_y, q_y = node(I, J), node(I, J + 1)
    e_idx = nx_edges + np.arange(I.size)
    m = I >= 1
    ex_rows.append(e_idx[m]); ex_cols.append(cell(I[m] - 1, J[m]))
    m = I <= N - 2
    ex_rows.append(e_idx[m]); ex_cols.append(cell(I[m], J[m]))
    ne = nx_edges + I.size

    p = np.concatenate([p_x, p_y])
    q = np.concatenate([q_x, q_y])
    rows = np.arange(ne)
    B = sp.csr_matrix((np.concatenate([-np.ones(ne), np.ones(ne)]),
                       (np.concatenate([rows, rows]), np.concatenate([p, q]))), shape=(ne, nn))
    er, ec = np.concatenate(ex_rows), np.concatenate(ex_cols)
    cnt = np.bincount(er, minlength=ne).astype(float)
    E = sp.csr_matrix((1.0 / cnt[er], (er, ec)), shape=(ne, nc))

    # TV differences between horizontally and vertically adjacent cells (anisotropic)
    M = N - 1
    CI, CJ = np.meshgrid(np.arange(M - 1), np.arange(M), indexing="ij")
    a1, b1 = cell(CI, CJ).ravel(), cell(CI + 1, CJ).ravel()
    CI, CJ = np.meshgrid(np.arange(M), np.arange(M - 1), indexing="ij")
    a2, b2 = cell(CI, CJ).ravel(), cell(CI, CJ + 1).ravel()
    a, b = np.concatenate([a1, a2]), np.concatenate([b1, b2])
    nd = a.size
    D = sp.csr_matrix((np.concatenate([-np.ones(nd), np.ones(nd)]),
                       (np.concatenate([np.arange(nd)] * 2), np.concatenate([a, b]))),
                      shape=(nd, nc))
    return B, E, D


@dataclass
class Counts:
    factorizations: int = 0
    solves: int = 0          # SuperLU solve calls (each with 2 right-hand sides)


@dataclass
class Case:
    """A poisson2d instance: operators, truth, data and the noise level."""

    N: int
    data_kind: str
    noise: float
    X: np.ndarray                 # (N*N, 2) rest positions
    free: np.ndarray              # free node ids (sorted)
    dir_: np.ndarray              # Dirichlet node ids
    obs_nodes: np.ndarray         # observed node ids (sorted)
    obs_in_free: np.ndarray       # position of each observed node in `free`
    B: sp.csr_matrix
    Bf: sp.csr_matrix
    Bd: sp.csr_matrix
    BfT: sp.csr_matrix
    E: sp.csr_matrix
    ET: sp.csr_matrix
    D: sp.csr_matrix
    xd: np.ndarray                # (n_dir, 2) Dirichlet values X/s
    k_true: np.ndarray
    y: np.ndarray                 # data, node-major (x0, y0, x1, y1, ...)
    delta: float                  # sigma * sqrt(m)
    counts: Counts = field(default_factory=Counts)

    @property
    def n(self) -> int:
        return self.E.shape[1]

    @property
    def m(self) -> int:
        return self.y.size


def make_case(N: int = 64, data: str = "dense", noise: float = 0.0, seed: int = 0) -> Case:
    """Build the poisson2d ``blocks`` case: operators, truth, (noisy) data and ``delta``.

    ``data``: ``"dense"`` (every non-Dirichlet node) or ``"sparse"`` (``i % 4 == 0`` and
    ``j % 4 == 0``, non-Dirichlet). ``noise``: sigma of i.i.d. Gaussian noise on every
    observed coordinate (numpy ``default_rng(seed)``); ``delta = sigma sqrt(m)``.
    """
    h = SIDE / (N - 1)
    I, J = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    I, J = I.ravel(), J.ravel()
    X = np.stack([I * h, J * h], axis=1)
    is_dir = (I == 0) | (I == N - 1)
    free, dir_ = np.flatnonzero(~is_dir), np.flatnonzero(is_dir)
    if data == "dense":
        obs = free
    elif data == "sparse":
        obs = np.flatnonzero(~is_dir & (I % 4 == 0) & (J % 4 == 0))
    else:
        raise ValueError(data)
    B, E, D = grid_operators(N)
    Bc = B.tocsc()
    Bf, Bd = Bc[:, free].tocsr(), Bc[:, dir_].tocsr()
    case = Case(N=N, data_kind=data, noise=float(noise), X=X, free=free, dir_=dir_,
                obs_nodes=obs, obs_in_free=np.searchsorted(free, obs),
                B=B, Bf=Bf, Bd=Bd, BfT=Bf.T.tocsr(), E=E, ET=E.T.tocsr(), D=D,
                xd=X[dir_] / SIDE, k_true=blocks_truth(N), y=np.empty(0), delta=0.0)
    st = State(case, np.log(case.k_true), count=False)
    y = st.observed()
    if noise > 0:
        y = y + np.random.default_rng(seed).normal(0.0, noise, y.size)
    case.y = y
    case.delta = float(noise) * np.sqrt(y.size)
    return case


class State:
    """Forward solve at one ``theta``: factor of ``A(k)``, free positions, ``g_c = B x_c``."""

    def __init__(self, case: Case, theta: np.ndarray, count: bool = True):
        self.case, self.theta = case, theta
        self.k = np.exp(theta)
        w = case.E @ self.k
        Wf = case.BfT.multiply(w[None, :]).tocsr()          # Bf^T diag(w)
        A = (Wf @ case.Bf).tocsc()
        rhs = -(Wf @ (case.Bd @ case.xd))                   # -L_fd x_d, (n_free, 2)
        self.lu = splu(A, permc_spec="MMD_AT_PLUS_A")
        self.xf = self.lu.solve(rhs)
        if count:
            case.counts.factorizations += 1
            case.counts.solves += 1
        self.count = count
        x = np.empty((case.X.shape[0], 2))
        x[case.free], x[case.dir_] = self.xf, case.xd
        self.x = x
        self.g = case.B @ x                                  # (n_edges, 2)

    def _solve(self, rhs: np.ndarray) -> np.ndarray:
        if self.count:
            self.case.counts.solves += 1
        return self.lu.solve(rhs)

    def observed(self) -> np.ndarray:
        return self.xf[self.case.obs_in_free].ravel()       # node-major, (x, y) per node

    def residual(self) -> np.ndarray:
        return self.observed() - self.case.y

    def jvp(self, v: np.ndarray) -> np.ndarray:
        """``J v`` (one solve, two right-hand sides)."""
        c = self.case
        dw = c.E @ (self.k * v)
        u = self._solve(-(c.BfT @ (self.g * dw[:, None])))
        return u[c.obs_in_free].ravel()

    def vjp(self, y: np.ndarray) -> np.ndarray:
        """``J^T y`` (one solve, two right-hand sides; ``A`` is symmetric)."""
        c = self.case
        Y = np.zeros_like(self.xf)
        Y[c.obs_in_free] = y.reshape(-1, 2)
        z = self._solve(Y)
        t = -(self.g * (c.Bf @ z)).sum(axis=1)              # sum over components
        return self.k * (c.ET @ t)


def aligned_error(k: np.ndarray, k_true: np.ndarray) -> float:
    """``min_a ||a k - k_true|| / ||k_true||``."""
    a = (k @ k_true) / (k @ k)
    return float(np.linalg.norm(a * k - k_true) / np.linalg.norm(k_true))


def project(v: np.ndarray) -> np.ndarray:
    """Remove the constant (gauge) direction."""
    return v - v.mean()


class Tracer:
    """Trace (wall seconds since start minus metric time, iteration, k_err_rel_aligned)."""

    def __init__(self, case: Case):
        self.case, self.t0, self.metric_time, self.trace = case, time.perf_counter(), 0.0, []

    def record(self, it: int, theta: np.ndarray) -> None:
        t_in = time.perf_counter()
        err = aligned_error(np.exp(theta), self.case.k_true)
        t_out = time.perf_counter()
        self.trace.append((t_in - self.t0 - self.metric_time, it, err))
        self.metric_time += t_out - t_in

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0 - self.metric_time


def cgls(matvec, rmatvec, rhs: np.ndarray, n: int, rtol: float, max_iter: int):
    """CGLS for ``min ||K z - rhs||``; stops when ``||K^T(rhs - K z)|| <= rtol ||K^T rhs||``.

    Returns ``z``, the iteration count and ``K^T rhs`` (minus the gradient of
    ``0.5 ||K z - rhs||^2`` at ``z = 0``, reused by the line searches).
    """
    z = np.zeros(n)
    r = rhs.copy()
    s = rmatvec(r)
    s0 = s.copy()
    p = s.copy()
    gamma = s @ s
    stop = rtol * np.sqrt(gamma)
    it = 0
    while it < max_iter and np.sqrt(gamma) > stop:
        q = matvec(p)
        qq = q @ q
        if qq <= 0:
            break
        alpha = gamma / qq
        z += alpha * p
        r -= alpha * q
        s = rmatvec(r)
        gamma_new = s @ s
        p = s + (gamma_new / gamma) * p
        gamma = gamma_new
        it += 1
    return z, it, s0


# --------------------------------------------------------------------------------------
# Gauss-Newton


def gauss_newton(case: Case, max_iter: int = 50, cg_max_iter: int = 200,
                 cg_rtol: float = 1e-2, tau: float = 1.1, tol: float = 1e-4,
                 armijo: float = 1e-4, max_backtracks: int = 20) -> dict:
    """Gauss-Newton on ``theta = log k`` from ``k0 = 1``.

    Inner: CGLS on ``J P d = -r`` (``P`` removes the constant), stopped when the
    normal-equation residual falls below ``cg_rtol`` of its initial value or after
    ``cg_max_iter`` iterations (two solves each). Step: backtracking (halving) with the
    Armijo condition on ``0.5 ||r||^2``; the factor of the accepted point is reused for the
    next linearisation. Stops: ``||r|| <= tau delta`` (``delta > 0``); ``||r|| < 1e-10
    ||r0||``; relative misfit decrease below ``tol`` (stall); ``max_iter``.
    """
    case.counts = Counts()
    tr = Tracer(case)
    theta = np.zeros(case.n)
    st = State(case, theta)
    r = st.residual()
    nr0 = nr = np.linalg.norm(r)
    tr.record(0, theta)
    stop, cg_total = "max_iter", 0
    for it in range(1, max_iter + 1):
        if case.delta > 0 and nr <= tau * case.delta:
            stop = "discrepancy"; break
        if nr < 1e-10 * nr0:
            stop = "converged"; break
        d, cg_it, s0 = cgls(lambda v: st.jvp(project(v)), lambda y: project(st.vjp(y)),
                            -r, case.n, cg_rtol, cg_max_iter)
        cg_total += cg_it
        slope = -(s0 @ d)          # <P J^T r, d>: s0 = P J^T (-r)
        alpha, accepted = 1.0, False
        for _ in range(max_backtracks):
            st_new = State(case, theta + alpha * d)
            r_new = st_new.residual()
            nr_new = np.linalg.norm(r_new)
            if np.isfinite(nr_new) and 0.5 * nr_new**2 <= 0.5 * nr**2 + armijo * alpha * slope:
                accepted = True; break
            alpha *= 0.5
        if not accepted:
            stop = "line_search_failed"; break
        theta, st, r = theta + alpha * d, st_new, r_new
        decrease = (nr - nr_new) / nr
        nr = nr_new
        tr.record(it, theta)
        if decrease < tol:
            stop = "stalled"; break
    if case.delta > 0 and nr <= tau * case.delta:
        stop = "discrepancy"
    return dict(trace=tr.trace, theta=theta, iterations=tr.trace[-1][1], stop=stop,
                misfit=float(nr), misfit0=float(nr0), cg_iterations=cg_total,
                factorizations=case.counts.factorizations, solves=case.counts.solves,
                seconds=tr.elapsed())


# --------------------------------------------------------------------------------------
# split Bregman


def power_norm2(st: State, iters: int = 10, seed: int = 1) -> float:
    """``||J P||_2^2`` by power iteration on ``P J^T J P`` (two solves per iteration)."""
    v = project(np.random.default_rng(seed).standard_normal(st.case.n))
    lam = 0.0
    for _ in range(iters):
        v /= np.linalg.norm(v)
        u = project(st.vjp(st.jvp(v)))
        lam = float(v @ u)
        v = u
    return lam


def shrink(t: np.ndarray, thr: float) -> np.ndarray:
    return np.sign(t) * np.maximum(np.abs(t) - thr, 0.0)


def split_bregman(case: Case, lam_rel: float = 5e-5, noise_factor: float = 1.0,
                  shrink_threshold: float = 0.5, max_iter: int = 300,
                  inner_cg_max_iter: int = 50, inner_cg_rtol: float = 1e-1,
                  tau: float = 1.1, tol: float = 1e-4, armijo: float = 1e-4,
                  max_backtracks: int = 10, lam: float | None = None,
                  beta: float | None = None, verbose: bool = False) -> dict:
    """Split Bregman for ``min 0.5 ||r(theta)||^2 + lam ||D theta||_1`` (anisotropic TV).

    Goldstein-Osher: per outer iteration one Gauss-Newton step (stacked CGLS on
    ``[J P; sqrt(beta) D] s = -[r; sqrt(beta)(D theta - dd + b)]`` with the fixed
    tolerance ``inner_cg_rtol`` on the normal-equation residual and the cap
    ``inner_cg_max_iter``; Armijo backtracking on the penalised objective) from the
    current ``theta``, then ``dd = shrink(D theta + b, lam / beta)``, ``b += D theta - dd``.

    Weights: one rule for every case, from the scale of ``J`` at ``theta0``
    (``||J||_2^2`` by 10 power iterations on ``P J^T J P``, 20 solves, no factorisation)
    and the noise level ``sigma = delta / sqrt(m)``:

    * ``lam = noise_factor * sigma * ||J||_2 + lam_rel * ||J||_2^2``. At a TV minimiser
      ``J^T r = -lam D^T s`` with ``|s| <= 1``; the noise puts about ``sigma ||J e_i|| <=
      sigma ||J||_2`` into each component of ``J^T r``, so ``lam`` of that size keeps TV
      from fitting the noise. On clean data only the small floor ``lam_rel ||J||^2``
      remains (weak TV: the minimiser nearly fits the data, with least TV).
    * ``beta = lam / shrink_threshold``: the shrinkage threshold ``lam / beta`` is a fixed
      step in ``theta = log k`` (0.5, a third of the jumps ``log 5``, ``log 4`` that TV is
      meant to keep). A much smaller threshold (large ``beta``) makes the first iterates
      a strongly H1-smoothed fit that the Bregman updates undo only slowly; a much larger
      one (small ``beta``) needs many updates of ``b`` before any jump is released.

    Stops: ``||r|| <= tau delta`` (``delta > 0``), the relative change of ``theta`` below
    ``tol`` (stagnation), or ``max_iter``.
    """
    case.counts = Counts()
    tr = Tracer(case)
    n = case.n
    D, DT = case.D, case.D.T.tocsr()
    theta = np.zeros(n)
    st = State(case, theta)
    r = st.residual()
    nr0 = nr = float(np.linalg.norm(r))
    tr.record(0, theta)
    normJ2 = power_norm2(st)
    sigma = case.delta / np.sqrt(case.m)
    if lam is None:
        lam = noise_factor * sigma * np.sqrt(normJ2) + lam_rel * normJ2
    if beta is None:
        beta = lam / shrink_threshold
    sb = np.sqrt(beta)
    dd = np.zeros(D.shape[0])
    b = np.zeros(D.shape[0])
    Dth = D @ theta
    stop, cg_total, nd = "max_iter", 0, case.m

    def phi(res, Dt):
        return 0.5 * (res @ res) + 0.5 * beta * np.sum((Dt - dd + b) ** 2)

    it = 0
    for it in range(1, max_iter + 1):
        if case.delta > 0 and nr <= tau * case.delta:
            stop = "discrepancy"; it -= 1; break
        # --- one Gauss-Newton step on the penalised least-squares problem
        rhs = -np.concatenate([r, sb * (Dth - dd + b)])
        mv = lambda v: np.concatenate([st.jvp(project(v)), sb * (D @ v)])        # noqa: E731
        rmv = lambda y: project(st.vjp(y[:nd]) + sb * (DT @ y[nd:]))              # noqa: E731
        step, cg_it, s0 = cgls(mv, rmv, rhs, n, inner_cg_rtol, inner_cg_max_iter)
        cg_total += cg_it
        slope = -(s0 @ step)       # s0 = -P (J^T r + beta D^T (D theta - dd + b))
        f0 = phi(r, Dth)
        alpha, accepted = 1.0, False
        for _ in range(max_backtracks):
            th_new = theta + alpha * step
            st_new = State(case, th_new)
            r_new = st_new.residual()
            Dth_new = D @ th_new
            f_new = phi(r_new, Dth_new)
            if np.isfinite(f_new) and f_new <= f0 + armijo * alpha * slope:
                accepted = True; break
            alpha *= 0.5
        if not accepted:            # keep theta; the Bregman update still moves dd, b
            th_new, st_new, r_new, Dth_new = theta, st, r, Dth
        change = np.linalg.norm(th_new - theta) / max(np.linalg.norm(th_new), 1e-300)
        theta, st, r, Dth = th_new, st_new, r_new, Dth_new
        nr = float(np.linalg.norm(r))
        # --- Bregman / shrinkage
        dd = shrink(Dth + b, lam / beta)
        b += Dth - dd
        tr.record(it, theta)
        if verbose:
            print(f"it {it:4d} err {tr.trace[-1][2]:.3e} misfit {nr:.3e} cg {cg_it:3d} "
                  f"alpha {alpha if accepted else 0:.3g} |Dth-d| {np.linalg.norm(Dth - dd):.2e} "
                  f"tv {np.abs(Dth).sum():.3e} change {change:.2e}", file=sys.stderr)
        if change < tol:
            stop = "stagnation"; break
    if case.delta > 0 and nr <= tau * case.delta:
        stop = "discrepancy"
    return dict(trace=tr.trace, theta=theta, iterations=tr.trace[-1][1], stop=stop,
                misfit=float(nr), misfit0=nr0, cg_iterations=cg_total, lam=lam, beta=beta,
                tau_delta=tau * case.delta,
                normJ2=normJ2, factorizations=case.counts.factorizations,
                solves=case.counts.solves, seconds=tr.elapsed())


# --------------------------------------------------------------------------------------
# self-test and CLI


VECTORS = Path(__file__).resolve().parents[2] / "tests" / "data" / "vectors"


def selftest(vectors: Path = VECTORS) -> dict:
    """Forward model against the independent test vector (``tests/data/vectors``, from an
    independent implementation of the problem definitions); dot-product and Taylor tests,
    N = 16."""
    out = {}
    vec = np.load(Path(vectors) / "poisson2d_N16_blocks.npz")
    N = int(vec["N"])
    assert abs(float(vec["s"]) - SIDE) < 1e-15
    case = make_case(N=N, data="dense")
    # truth: match cells by their centres
    h = SIDE / (N - 1)
    cc = vec["cell_centres"]
    cid = np.rint(cc[:, 0] / h - 0.5).astype(int) * (N - 1) + np.rint(cc[:, 1] / h - 0.5).astype(int)
    out["truth_max_diff"] = float(np.abs(case.k_true[cid] - vec["k"]).max())
    st = State(case, np.log(vec["k"][np.argsort(cid)]), count=False)
    nid = (np.rint(vec["rest_positions"][:, 0] / h).astype(int) * N
           + np.rint(vec["rest_positions"][:, 1] / h).astype(int))
    assert np.allclose(case.X[nid], vec["rest_positions"], atol=1e-14)
    out["positions_max_diff"] = float(np.abs(st.x[nid] - vec["positions"]).max())

    rng = np.random.default_rng(0)
    for kind in ("dense", "sparse"):
        c = make_case(N=N, data=kind, noise=1e-3)
        th = 0.3 * rng.standard_normal(c.n)
        s0 = State(c, th)
        v, y = rng.standard_normal(c.n), rng.standard_normal(c.m)
        Jv, JTy = s0.jvp(v), s0.vjp(y)
        out[f"dot_test_rel_{kind}"] = float(abs(y @ Jv - v @ JTy) / abs(y @ Jv))
        r0 = s0.residual()
        errs = []
        for eps in (1e-1, 1e-2, 1e-3, 1e-4):
            r1 = State(c, th + eps * v).residual()
            errs.append((eps, float(np.linalg.norm(r1 - r0)), float(np.linalg.norm(r1 - r0 - eps * Jv))))
        rates = [np.log(errs[i][2] / errs[i + 1][2]) / np.log(10) for i in range(len(errs) - 1)]
        out[f"taylor_{kind}"] = {"eps_zeroth_first": errs, "first_order_rates": rates}
        out[f"gauge_J1_rel_{kind}"] = float(np.linalg.norm(s0.jvp(np.ones(c.n)))
                                            / np.linalg.norm(Jv) * np.linalg.norm(v) / np.sqrt(c.n))
    ok = (out["truth_max_diff"] == 0 and out["positions_max_diff"] < 1e-11
          and max(out["dot_test_rel_dense"], out["dot_test_rel_sparse"]) < 1e-10
          and all(min(out[f"taylor_{k}"]["first_order_rates"][:2]) > 1.8 for k in ("dense", "sparse")))
    out["ok"] = bool(ok)
    return out


CASES = {
    "gn_dense": (dict(N=64, data="dense", noise=0.0), gauss_newton),
    "sb_dense_noisy": (dict(N=64, data="dense", noise=1e-3), split_bregman),
    "sb_sparse": (dict(N=64, data="sparse", noise=0.0), split_bregman),
}


def run_case(name: str, seed: int = 0, with_trace: bool = False, **kw) -> dict:
    """Build a named case, run its solver; summary (and the trace if ``with_trace``)."""
    settings, solver = CASES[name]
    case = make_case(seed=seed, **settings)
    res = solver(case, **kw)
    final_t, final_it, final_err = res["trace"][-1]
    best = min(res["trace"], key=lambda t: t[2])
    out = {k: v for k, v in res.items() if k not in ("trace", "theta")}
    out.update(case=name, final_accuracy=final_err, final_iteration=final_it,
               time_to_final_accuracy=next(t for t, i, e in res["trace"] if e <= final_err),
               best_accuracy=best[2], best_iteration=best[1], delta=case.delta, m=case.m)
    if with_trace:
        out["trace"] = res["trace"]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--selftest", action="store_true")
    ap.add_argument("--case", choices=sorted(CASES))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--trace", action="store_true", help="include the per-iteration trace")
    ap.add_argument("--max-iter", type=int, help="outer iterations (solver default if unset)")
    ap.add_argument("--cg-max-iter", type=int,
                    help="CGLS cap (gauss_newton: cg_max_iter; split_bregman: inner_cg_max_iter)")
    args = ap.parse_args(argv)
    if args.selftest:
        res = selftest()
        print(json.dumps(res, indent=1))
        return 0 if res["ok"] else 1
    if args.case:
        kw = {}
        if args.max_iter is not None:
            kw["max_iter"] = args.max_iter
        if args.cg_max_iter is not None:
            key = "cg_max_iter" if CASES[args.case][1] is gauss_newton else "inner_cg_max_iter"
            kw[key] = args.cg_max_iter
        out = run_case(args.case, seed=args.seed, with_trace=args.trace, **kw)
        print(json.dumps(out, indent=1))
        return 0
    ap.print_help()
    return 2


if __name__ == "__main__":
    sys.exit(main())
