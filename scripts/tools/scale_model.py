"""The cost model of scripts/bench/scale.py: one LM iteration from per-frame figures.

Pure functions (no torch, no simulation): fit power laws to per-frame costs measured at a
few mesh sizes, then predict one Levenberg-Marquardt iteration of ``F`` frames of ``N``
tetrahedra on ``R`` ranks (docs/notes/scale.md states the formula)::

    T(N, F, R) = ceil(F_sim / R) * (c_trial(N) + n * c_col(N))     # every rank, in parallel
               + T_rank0                                           # serial on rank 0
               + bytes_rank0(R) / bandwidth                         # communication

with ``c_trial(N) = a_t N^b_t`` (seconds per simulated frame of the trial point) and
``c_col(N) = a_c N^b_c`` (seconds per frame and Jacobian column), ``F_sim`` the frames
simulated (distinct poses on one process; every frame under the torchrun split). Two
communication designs:

* ``gather_J`` (until 2026-11-26): the workers send rank 0 their rows of the dense Jacobian,
  ``F n_obs 3 n`` doubles in all, and the trial's vertex positions, ``F n_vertices 3``
  doubles; rank 0 forms ``J^T J`` (``F n_obs 3 n^2`` flops) alone.
* ``allreduce_JtJ`` (since 2026-11-26, ``torchfit.run.distributed.rows``, which gathers the
  partial sums to rank 0 and adds them in rank order: ``(R - 1) n^2`` doubles into rank 0,
  18.6 MB at 64 ranks and n = 192): every rank forms its own ``J_k^T J_k`` and
  ``J_k^T r_k`` and a ring all-reduce sums them, ``2 (R - 1) / R (n^2 + n)`` doubles sent
  per rank; the residual ``F n_obs 3`` doubles is still gathered for the misfit.

Rank 0's link is the bottleneck of a gather (every worker sends to it): its time is the
bytes rank 0 receives over the bandwidth; an all-reduce's is the bytes each rank sends.
"""
from __future__ import annotations

import math
from typing import Any, Iterable

DOUBLE = 8
#: the exponent assumed where only one size was measured (a sparse 3-D direct solve)
DEFAULT_EXPONENT = 1.5


def fit_power_law(sizes: Iterable[float], values: Iterable[float],
                  default_exponent: float = DEFAULT_EXPONENT) -> dict[str, float]:
    """``value = a * size ** b`` by least squares in log-log; one point: ``b`` assumed."""
    points = [(math.log(s), math.log(v)) for s, v in zip(sizes, values) if s > 0 and v > 0]
    if not points:
        raise ValueError("a power law needs at least one positive (size, value) pair")
    if len({x for x, _ in points}) < 2:
        b = default_exponent
        a = math.exp(sum(y - b * x for x, y in points) / len(points))
        return {"a": a, "b": b, "points": len(points), "b_assumed": True}
    mx = sum(x for x, _ in points) / len(points)
    my = sum(y for _, y in points) / len(points)
    b = sum((x - mx) * (y - my) for x, y in points) / sum((x - mx) ** 2 for x, _ in points)
    return {"a": math.exp(my - b * mx), "b": b, "points": len(points), "b_assumed": False}


def power(law: dict[str, float], size: float) -> float:
    return law["a"] * size ** law["b"]


def communication_bytes(design: str, n_frames: int, n_ranks: int, n_obs: int,
                        n_vertices: int, n_params: int) -> dict[str, float]:
    """Bytes per LM iteration: ``rank0_in`` (what rank 0 receives) and ``per_rank_out``
    (what one worker sends) for ``design`` ``gather_J`` or ``allreduce_JtJ``."""
    if n_ranks <= 1:
        return {"rank0_in": 0.0, "per_rank_out": 0.0, "critical": 0.0}
    others = (n_ranks - 1) / n_ranks                 # the share of frames not on rank 0
    if design == "gather_J":
        jacobian = n_frames * n_obs * 3 * n_params * DOUBLE
        positions = n_frames * n_vertices * 3 * DOUBLE
        rank0_in = others * (jacobian + positions)
        per_rank_out = math.ceil(n_frames / n_ranks) * (n_obs * 3 * n_params
                                                        + n_vertices * 3) * DOUBLE
        return {"rank0_in": rank0_in, "per_rank_out": per_rank_out, "critical": rank0_in}
    if design == "allreduce_JtJ":
        reduced = 2 * others * (n_params ** 2 + n_params) * DOUBLE   # ring all-reduce
        residual = n_frames * n_obs * 3 * DOUBLE
        rank0_in = reduced + others * residual
        per_rank_out = reduced + math.ceil(n_frames / n_ranks) * n_obs * 3 * DOUBLE
        return {"rank0_in": rank0_in, "per_rank_out": per_rank_out, "critical": rank0_in}
    raise ValueError(f"unknown design {design!r} (gather_J or allreduce_JtJ)")


def predict_iteration(*, n_tets: float, n_frames: int, n_ranks: int, n_params: int,
                      n_obs: int, n_vertices: int, trial_law: dict[str, float],
                      column_law: dict[str, float], flops_per_s: float,
                      bandwidth_bytes_per_s: float, design: str = "gather_J",
                      rank0_fixed_s: float = 0.0) -> dict[str, Any]:
    """Seconds of one LM iteration (module docstring) and its parts.

    ``n_frames``: frames simulated (``F_sim``); ``flops_per_s``: rank 0's (or each rank's)
    dense rate forming ``J^T J``; ``rank0_fixed_s``: other serial seconds on rank 0.
    """
    per_rank_frames = math.ceil(n_frames / n_ranks)
    trial = power(trial_law, n_tets)
    column = power(column_law, n_tets)
    compute = per_rank_frames * (trial + n_params * column)
    rows = n_obs * 3
    if design == "gather_J":
        normal = n_frames * rows * n_params ** 2 / flops_per_s          # rank 0 alone
    else:
        normal = per_rank_frames * rows * n_params ** 2 / flops_per_s   # every rank its own
    comm = communication_bytes(design, n_frames, n_ranks, n_obs, n_vertices, n_params)
    comm_s = comm["critical"] / bandwidth_bytes_per_s if n_ranks > 1 else 0.0
    total = compute + normal + rank0_fixed_s + comm_s
    return {"seconds": total, "compute_s": compute, "frames_per_rank": per_rank_frames,
            "trial_per_frame_s": trial, "column_per_frame_s": column, "normal_s": normal,
            "rank0_fixed_s": rank0_fixed_s, "comm_s": comm_s,
            "comm_bytes_rank0_in": comm["rank0_in"], "comm_bytes_per_rank_out":
            comm["per_rank_out"], "J_bytes_rank0": (n_frames * rows * n_params * DOUBLE
                                                    if design == "gather_J" else
                                                    per_rank_frames * rows * n_params * DOUBLE)}


def gbit(bits_per_s: float) -> float:
    """Bytes per second of a link of ``bits_per_s`` Gbit/s."""
    return bits_per_s * 1e9 / 8


def prediction_table(laws: dict[str, dict[str, float]], *, n_tets: float, n_frames: int,
                     ranks: Iterable[int], bandwidths_gbit: Iterable[float], n_params: int,
                     n_obs: int, n_vertices: int, flops_per_s: float) -> list[dict[str, Any]]:
    """Rows of the prediction: every design x bandwidth x rank count."""
    rows = []
    for design in ("gather_J", "allreduce_JtJ"):
        for bandwidth in bandwidths_gbit:
            for n_ranks in ranks:
                out = predict_iteration(n_tets=n_tets, n_frames=n_frames, n_ranks=n_ranks,
                                        n_params=n_params, n_obs=n_obs, n_vertices=n_vertices,
                                        trial_law=laws["trial"], column_law=laws["column"],
                                        flops_per_s=flops_per_s,
                                        bandwidth_bytes_per_s=gbit(bandwidth), design=design)
                rows.append({"design": design, "bandwidth_gbit": bandwidth, "ranks": n_ranks,
                             **out})
    return rows
